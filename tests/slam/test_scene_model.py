"""Every registered F x every registered G through the scene model's shared loss and its backward.

16 rays from a camera inside a 2 m box (two without depth), a tiny field (30 / 10 cm cells, 2^8 hash rows, 32-wide
MLP) and 8 + 4 samples per ray, so all F x G pairs together stay within a few seconds. A field or renderer added to
its registry is picked up here automatically.
"""

from __future__ import annotations

import types
import typing

import numpy as np
import pytest
import torch
from autograd_graph import node_names

from inrslam.config import RunConfig, load_config
from inrslam.fields import ENCODINGS
from inrslam.rendering import RENDERERS
from inrslam.slam.model import ModelConfig, SceneModel

BOUNDS = np.array([[-1.0, 1.0], [-0.8, 0.8], [-0.2, 1.4]])  # metres
RAYS = 16
TINY = [
    "field.block_coarse=0.3", "field.block_fine=0.1", "field.app_block_coarse=0.3", "field.app_block_fine=0.1",
    "field.plane_block_coarse=0.3", "field.log2_hashmap_size=8",
    "sampling.n_free=8", "sampling.n_surface=4",
]
# per-variant keys, given only to their variant (a key of another variant is a config error)
VARIANT = {"mlp": ["field.mlp.width=32"],
           "density": ["render.density.learn_beta=true"]}  # so every renderer with a parameter learns it


def _rays(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """c2w (4, 4), camera directions (R, 3) with z = 1, colours (R, 3), depths (R,) in metres (two rays 0 = none)."""
    g = torch.Generator().manual_seed(seed)
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.1, -0.05, 0.0])
    dirs = torch.cat([(torch.rand(RAYS, 2, generator=g) - 0.5) * 0.6, torch.ones(RAYS, 1)], dim=1)
    rgb = torch.rand(RAYS, 3, generator=g)
    depth = 0.6 + 0.5 * torch.rand(RAYS, generator=g)
    depth[:2] = 0.0
    return c2w, dirs, rgb, depth


@pytest.mark.parametrize("render", RENDERERS.names())
@pytest.mark.parametrize("encoding", ENCODINGS.names())
def test_every_field_and_renderer_train_through_the_scene_model(encoding, render):
    cfg = load_config(preset="quick", overrides=[f"field.encoding={encoding}", f"render.name={render}", *TINY,
                                                      *VARIANT.get(encoding, []), *VARIANT.get(render, [])])
    torch.manual_seed(0)
    model = SceneModel(cfg, BOUNDS)
    c2w, dirs, rgb, depth = _rays()
    c2w.requires_grad_()
    losses, out = model.loss(c2w, dirs, rgb, depth, torch.Generator().manual_seed(1))
    assert out.rgb.shape == (RAYS, 3) and out.depth.shape == (RAYS,)
    assert losses["total"].dim() == 0
    for name, value in losses.items():
        assert torch.isfinite(value).all(), f"{encoding} x {render}: loss term {name} = {value}"
    losses["total"].backward()

    def grad(p: torch.Tensor) -> torch.Tensor:
        return p.grad.coalesce().values() if p.grad.is_sparse else p.grad

    for name, p in model.field.named_parameters():
        assert p.grad is not None, f"{encoding} x {render}: no gradient for field.{name}"
        assert torch.isfinite(grad(p)).all(), f"{encoding} x {render}: non-finite gradient of field.{name}"
        assert grad(p).abs().sum() > 0, f"{encoding} x {render}: zero gradient for field.{name}"
    learnable = [(n, p) for n, p in model.renderer.named_parameters() if p.requires_grad]
    for name, p in learnable:
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs() > 0, f"{render}.{name}"
    # tracking differentiates the same loss with respect to the camera pose
    assert torch.isfinite(c2w.grad).all() and c2w.grad[:3].abs().sum() > 0
    assert set(model.make_optimizers(1e-2)) == ({"field", "render"} if learnable else {"field"})


def test_run_config_has_every_section_the_scene_model_reads():
    """`ModelConfig` (slam may not import the config layer) names RunConfig's sections with their types."""
    wanted, run = typing.get_type_hints(ModelConfig), typing.get_type_hints(RunConfig)
    assert wanted and all(run.get(name) is typ for name, typ in wanted.items()), (wanted, run)


class _Plane(torch.nn.Module):
    """Analytic field: the plane z = 0.8 m facing the camera, SDF in truncation units, constant colour."""

    def __init__(self, truncation: float):
        super().__init__()
        self.t = truncation
        self.dummy = torch.nn.Parameter(torch.zeros(1))

    def sdf(self, x):
        return (0.8 - x[:, 2]) / self.t

    def forward(self, x):
        return types.SimpleNamespace(sdf=self.sdf(x), rgb_logits=torch.zeros(x.shape[0], 3))


@pytest.mark.parametrize("render", ["direct", "nerf"])
def test_held_out_surface_depth_is_the_zero_crossing_and_nerf_keeps_the_weighted_mean(render):
    from inrslam.geometry.intrinsics import Intrinsics

    cfg = load_config(preset="quick", overrides=["field.encoding=dense", f"render.name={render}", *TINY])
    model = SceneModel(cfg, BOUNDS)
    model.field = _Plane(model.truncation)
    intr = Intrinsics(fx=8.0, fy=8.0, cx=3.5, cy=2.5, width=8, height=6)
    c2w = torch.eye(4)
    rgb_e, expected = model.render_image(c2w, intr, n_coarse=64, depth="expected")
    rgb_s, surface = model.render_image(c2w, intr, n_coarse=64, depth="surface")
    assert torch.equal(rgb_e, rgb_s)  # colour does not depend on the depth estimator
    if render == "nerf":  # no SDF to cross: the weighted mean
        assert torch.equal(surface, expected)
    else:  # a linear SDF: the interpolated zero crossing is the plane, exactly
        torch.testing.assert_close(surface, torch.full_like(surface, 0.8), atol=1e-5, rtol=0)
        assert not torch.equal(surface, expected)
    with pytest.raises(ValueError, match="depth must be"):
        model.render_image(c2w, intr, depth="median")


class _BallBeforePlane(_Plane):
    """A 1.5 cm ball at 0.46 m on the optical axis in front of the plane z = 0.8 m (SDF in truncation units)."""

    def sdf(self, x):
        ball = (x - torch.tensor([0.0, 0.0, 0.46])).norm(dim=-1) - 0.015
        return torch.minimum(ball, 0.8 - x[:, 2]) / self.t


def test_held_out_refined_surface_search_finds_a_ball_the_uniform_samples_step_over():
    from inrslam.geometry.intrinsics import Intrinsics

    cfg = load_config(preset="quick", overrides=["field.encoding=dense", "render.name=direct", *TINY])
    model = SceneModel(cfg, BOUNDS)
    model.field = _BallBeforePlane(model.truncation)
    intr = Intrinsics(fx=40.0, fy=40.0, cx=3.5, cy=2.5, width=8, height=6)  # the 4 central rays pass 8 mm off
    n = 12  # uniform samples ~13 cm apart: none inside the ball (nor the final samples around the plane)
    _, plain = model.render_image(torch.eye(4), intr, n_coarse=n, depth="surface")
    _, refined = model.render_image(torch.eye(4), intr, n_coarse=n, depth="surface", refine=8)
    centre = torch.tensor([[0.0, 0.0, 1.0]])
    assert model.field.sdf(centre * 0.46).item() < 0  # the ball is there ...
    assert (plain - 0.8).abs().max().item() < 1e-4  # ... the uniform search sees only the plane ...
    u = torch.arange(8) - 3.5
    v = torch.arange(6) - 2.5
    off = ((u[None, :] / 40) ** 2 + (v[:, None] / 40) ** 2).sqrt() * 0.46  # how far each ray passes from the centre
    on_ball = off < 0.01
    assert on_ball.sum() == 4
    assert (refined[on_ball] - 0.46).abs().max().item() < 0.015 and (refined[on_ball] < 0.46).all()  # ... refined: it
    torch.testing.assert_close(refined[~on_ball], plain[~on_ball])  # elsewhere the same surface


@pytest.mark.parametrize("preset, fused", [("fast", True), ("accurate", True), ("gicp", True), ("paper_fused", True),
                                           ("paper", False)])
def test_which_presets_run_the_fused_decoders_and_losses(preset, fused):
    """`accurate` (and `fast` and `gicp`, which inherit from it) and `paper_fused` train their map through the fused
    decoders (both in one call), G's fused weights and the fused losses; `paper` through autograd's (bit for bit the
    paper's loop)."""
    cfg = load_config(preset=preset, overrides=TINY)
    torch.manual_seed(0)
    model = SceneModel(cfg, BOUNDS)
    c2w, dirs, rgb, depth = _rays()
    losses, _ = model.loss(c2w, dirs, rgb, depth, torch.Generator().manual_seed(1))
    names = node_names(losses["total"].grad_fn)
    assert ("Mlp2SplitFnBackward" in names) == fused and ("CompositeLossFnBackward" in names) == fused
    assert ({"DirectWeightsFnBackward", "DensityWeightsFnBackward"} & set(names) != set()) == fused
    losses["total"].backward()
    assert all(p.grad is not None for p in model.field.parameters())
