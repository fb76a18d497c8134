"""Training smoke test: F + G + sampling + losses fitted to one RGB-D frame reach < 2 cm depth L1.

Frame: `inrslam.scenes.load_scene("room", SceneConfig(frames=2, width=64, height=48))`. Field: a small `dense`
field from `inrslam.fields.build_field` (2 levels, 40 cm / 10 cm cells). Randomly initialised, trained with Adam
(lr 1e-2) for STEPS steps of RAYS random rays of the frame with the default sampling and losses (paper weights,
per-ray reduction).
Checked: depth L1 over every pixel of the frame (rendered with depth-guided sampling, as the paper logs it) < 2 cm,
for direct, density, neus, volsdf.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.fields import Field, FieldConfig, build_field
from inrslam.geometry.camera import pixel_directions
from inrslam.rendering import (
    DensityConfig,
    LossConfig,
    NeusConfig,
    RenderConfig,
    SamplingConfig,
    build_renderer,
    compute_losses,
    depth_l1,
    render_rays,
    renderer_param_groups,
    sample_depths,
)
from inrslam.scenes import load_scene
from inrslam.scenes.config import SceneConfig

T = 0.1
LR = 1e-2
STEPS = 300
RAYS = 256


def _frame():
    """Frame 0 of the built-in room (64x48): rgb (H,W,3), depth (H,W) m, camera dirs (H,W,3), c2w (4,4), bounds."""
    ds = load_scene("room", SceneConfig(frames=2, width=64, height=48))
    fr = ds[0]
    H, W = fr.depth.shape
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    d_cam = pixel_directions(fr.intrinsics, u.reshape(-1), v.reshape(-1)).numpy().reshape(H, W, 3)
    return fr.rgb, fr.depth, d_cam, fr.c2w, np.asarray(ds.bounds)


def make_field(bounds: np.ndarray) -> tuple[Field, list[dict]]:
    """A small randomly initialised dense field and its optimiser parameter groups (lr 1e-2)."""
    field = build_field(FieldConfig(encoding="dense", block_coarse=0.4, block_fine=0.1), np.asarray(bounds))
    return field, [{"params": [p for p in field.parameters() if p.requires_grad], "lr": LR}]


@pytest.fixture(scope="module")
def frame():
    rgb, depth, d_cam, c2w, bounds = _frame()
    R = torch.as_tensor(c2w[:3, :3], dtype=torch.float32)
    dirs = torch.as_tensor(d_cam.reshape(-1, 3), dtype=torch.float32) @ R.T
    origins = torch.as_tensor(c2w[:3, 3], dtype=torch.float32).expand_as(dirs).contiguous()
    return dict(rgb=torch.as_tensor(rgb.reshape(-1, 3)), depth=torch.as_tensor(depth.reshape(-1)), dirs=dirs,
                origins=origins, bounds=torch.as_tensor(bounds, dtype=torch.float32))


def fit(frame, rcfg: RenderConfig, steps: int = STEPS, rays: int = RAYS, seed: int = 0):
    """Fit a fresh field to the frame; returns (field, renderer, depth L1 over all pixels in metres)."""
    torch.manual_seed(seed)
    field, groups = make_field(frame["bounds"].numpy())
    renderer = build_renderer(rcfg)
    opt = torch.optim.Adam(groups + renderer_param_groups(renderer, rcfg))
    scfg, lcfg = SamplingConfig(), LossConfig()
    gen = torch.Generator().manual_seed(seed + 1)
    n = frame["depth"].shape[0]
    for _ in range(steps):
        idx = torch.randint(0, n, (rays,), generator=gen)
        o, d, D = frame["origins"][idx], frame["dirs"][idx], frame["depth"][idx]
        z = sample_depths(D, d, o, frame["bounds"], scfg, T, gen)
        out = render_rays(field, renderer, o, d, z, T)
        loss = compute_losses(out, frame["rgb"][idx], D, lcfg, T)["total"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        z = sample_depths(frame["depth"], frame["dirs"], frame["origins"], frame["bounds"], scfg, T, gen)
        out = render_rays(field, renderer, frame["origins"], frame["dirs"], z, T)
    return field, renderer, depth_l1(out.depth, frame["depth"]).item()


# Per-G settings (everything else default). density: the paper's beta = 10 renders ~3 cm in front of the surface
# (see test_rendering_analytic.test_density_paper_beta_bias; this fit measures 4.4 cm depth L1 with it, in line with
# the paper's 4.8 cm for F(dense)+G(density)), so the < 2 cm check uses beta = 30. neus: detached normals keep the
# test fast (the differentiable modes are checked in test_rendering_renderers; the double backward through the
# fields' fused kernels costs ~8x here).
SETTINGS = {
    "direct": RenderConfig(name="direct"),
    "density": RenderConfig(name="density", density=DensityConfig(beta=30.0)),
    "neus": RenderConfig(name="neus", neus=NeusConfig(normals="autograd_detached")),
    "volsdf": RenderConfig(name="volsdf"),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_fit_one_frame_depth_l1_below_2cm(frame, name):
    _, _, err = fit(frame, SETTINGS[name])
    print(f"{name}: depth L1 {err * 100:.2f} cm")
    assert err < 0.02
