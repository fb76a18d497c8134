"""`first_crossing`: the surface depth of an SDF along rays (held-out renders' `eval.heldout_depth: surface`)."""

from __future__ import annotations

import torch
from rendering_helpers import Out, PlaneField, SphereField, T, camera_rays, rotation_x

from inrslam.rendering import (
    RenderConfig,
    SamplingConfig,
    build_renderer,
    first_crossing,
    render_rays,
    sample_depths,
    surface_depth,
)

BOUNDS = torch.tensor([[-3.0, 3.0], [-3.0, 3.0], [-1.0, 5.0]], dtype=torch.float64)


def test_linear_sdf_crossing_is_exact_and_the_first_one_wins():
    g = torch.Generator().manual_seed(0)
    R, S = 64, 200
    z = torch.sort(torch.rand(R, S, generator=g, dtype=torch.float64) * 4 + 0.1, dim=1).values
    d = 0.5 + 3 * torch.rand(R, generator=g, dtype=torch.float64)  # a plane across each ray at z = d
    sdf = (d[:, None] - z) / T
    depth, has = first_crossing(sdf, z)
    inside = (z[:, 0] < d) & (z[:, -1] > d)
    assert torch.equal(has, inside)
    torch.testing.assert_close(depth[has], d[has], atol=1e-12, rtol=0)
    assert (depth[~has] == 0).all()
    # the SDF rises again behind the first surface (back face at d + 0.8) and falls at a second one (d + 1.6):
    # the first crossing is kept
    dd = d[:, None]
    two = torch.minimum(torch.maximum(dd - z, z - dd - 0.8), dd + 1.6 - z) / T
    assert ((two[:, :-1] > 0) & (two[:, 1:] <= 0)).sum(1).max() == 2
    torch.testing.assert_close(first_crossing(two, z)[0][has], d[has], atol=1e-12, rtol=0)


def test_ray_starting_inside_or_never_reaching_a_surface_has_no_crossing():
    z = torch.linspace(0.1, 2.0, 20, dtype=torch.float64).expand(3, 20)
    sdf = torch.stack([-torch.ones(20), torch.ones(20), (0.5 - z[2])], 0).to(torch.float64)
    depth, has = first_crossing(sdf, z)
    assert has.tolist() == [False, False, True]
    assert depth[:2].tolist() == [0.0, 0.0]
    torch.testing.assert_close(depth[2], torch.tensor(0.5, dtype=torch.float64), atol=1e-12, rtol=0)


class OneSidedPlane(PlaneField):
    """A plane whose SDF behind the surface stops at -0.3 T, as a trained field's often does (its far side is seen
    only within the band): the weight bell of SDF(direct) then loses its back half."""

    def __call__(self, x):
        out = super().__call__(x)
        return Out(out.sdf.clamp_min(-0.3), out.rgb_logits)


def test_surface_depth_is_unbiased_where_the_weighted_mean_is_not():
    """SDF(direct) with the paper's sampling on a one-sided plane: the weighted-mean depth is pulled off the
    surface (behind it here: the clamped back keeps weight); the zero crossing of the same samples is on it
    (plane tilted 0 / 30 degrees, and a sphere)."""
    renderer = build_renderer(RenderConfig(name="direct")).double()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    scenes = [OneSidedPlane(rotation_x(a) @ up, 2.0) for a in (0, 30)]
    for f in scenes + [SphereField([0.2, -0.1, 2.5], 0.8)]:
        o, d = camera_rays(5, 0.3)
        t = f.true_depth(o, d)
        keep = ~t.isnan()
        o, d, t = o[keep], d[keep], t[keep]
        z = sample_depths(t, d, o, BOUNDS, SamplingConfig(jitter=False), T, None)
        out = render_rays(f, renderer, o, d, z, T)
        depth, has = first_crossing(out.sdf, out.z)
        assert has.all()
        assert (depth - t).abs().max().item() < 1e-3  # sphere: chord of the curved SDF between two samples
        if isinstance(f, OneSidedPlane):
            torch.testing.assert_close(depth, t, atol=1e-9, rtol=0)
            assert (out.depth - t).abs().min().item() > 5e-3  # every ray's weighted mean at least 5 mm off


def test_surface_depth_takes_the_crossing_and_the_fallback_where_there_is_none():
    sdf = torch.tensor([[1.0, 0.5, -0.5], [1.0, 0.8, 0.2]])
    z = torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    out = surface_depth(sdf, z, torch.tensor([7.0, 9.0]))
    assert torch.allclose(out, torch.tensor([2.5, 9.0]))
