"""Training smoke test: F + G + sampling + losses fitted to one RGB-D frame reach < 2 cm depth L1.

Frame: `inrslam.scenes.load_scene("room", SceneConfig(frames=2, width=64, height=48))` when that package provides
it, else an analytically ray-cast box room (64x48). Field: a small `dense` field from `inrslam.fields.build_field`
(2 levels, 40 cm / 10 cm cells) when importable, else a tiny dense feature grid (trilinear `grid_sample`, 16^3 x 8)
+ 2-layer MLP defined here. Randomly initialised, trained with Adam (lr 1e-2) for STEPS steps of RAYS random rays
of the frame with the default sampling and losses (paper weights, per-ray reduction).
Checked: depth L1 over every pixel of the frame (rendered with depth-guided sampling, as the paper logs it) < 2 cm,
for direct, density, neus, volsdf.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

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

T = 0.1
LR = 1e-2
STEPS = 300
RAYS = 256


class TinyGridField(nn.Module):
    """Dense grid of C features over `bounds` (trilinear) -> MLP -> (sdf T-units, rgb logits)."""

    def __init__(self, bounds: np.ndarray, res: int = 24, feat: int = 8, hidden: int = 32, seed: int = 0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.register_buffer("lo", torch.as_tensor(bounds[:, 0], dtype=torch.float32))
        self.register_buffer("hi", torch.as_tensor(bounds[:, 1], dtype=torch.float32))
        self.grid = nn.Parameter(1e-2 * torch.randn(1, feat, res, res, res, generator=g))
        torch.manual_seed(seed)
        self.mlp = nn.Sequential(nn.Linear(feat, hidden), nn.ReLU(), nn.Linear(hidden, 4))

    def forward(self, x):
        u = (x - self.lo) / (self.hi - self.lo) * 2 - 1  # [-1, 1], grid_sample wants (x, y, z) -> (W, H, D)
        f = torch.nn.functional.grid_sample(self.grid, u[None, None, None], align_corners=True, padding_mode="border")
        h = self.mlp(f[0, :, 0, 0].T)

        class Out:
            sdf = h[:, 0]
            rgb_logits = h[:, 1:]

        return Out


def _box_room_frame():
    """64x48 frame inside the box room [-2,2]x[-1.2,1.2]x[-1.5,2.5] (OpenCV axes), depth ray-cast analytically."""
    W, H, f = 64, 48, 50.0
    room = np.array([[-2.0, 2.0], [-1.2, 1.2], [-1.5, 2.5]])
    yaw, pitch = math.radians(20), math.radians(10)
    Ry = np.array([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0], [-math.sin(yaw), 0, math.cos(yaw)]])
    Rx = np.array([[1, 0, 0], [0, math.cos(pitch), -math.sin(pitch)], [0, math.sin(pitch), math.cos(pitch)]])
    c2w = np.eye(4)
    c2w[:3, :3] = Ry @ Rx
    c2w[:3, 3] = [0.3, 0.1, -0.5]
    v, u = np.mgrid[0:H, 0:W]
    d_cam = np.stack([(u - (W - 1) / 2) / f, (v - (H - 1) / 2) / f, np.ones_like(u, dtype=float)], -1)
    d = d_cam @ c2w[:3, :3].T
    o = c2w[:3, 3]
    t_axes = np.where(d > 0, (room[:, 1] - o) / np.where(d == 0, 1, d), (room[:, 0] - o) / np.where(d == 0, 1, d))
    axis = np.argmin(t_axes, -1)
    depth = np.min(t_axes, -1)  # t along camera-z-1 dirs = z-depth
    hit = o + depth[..., None] * d
    base = np.array([[0.8, 0.3, 0.3], [0.3, 0.8, 0.3], [0.3, 0.3, 0.8]])[axis]
    rgb = base * (0.75 + 0.25 * np.sin(3 * hit[..., [1, 2, 0]]))
    bounds = room + np.array([[-0.2, 0.2]] * 3)
    return rgb.astype(np.float32), depth.astype(np.float32), d_cam, c2w, bounds


def _frame():
    try:
        from inrslam.scenes import load_scene  # noqa: F401
        from inrslam.scenes.config import SceneConfig
        from inrslam.geometry.camera import pixel_directions
    except ImportError:
        return _box_room_frame()
    ds = load_scene("room", SceneConfig(frames=2, width=64, height=48))
    fr = ds[0]
    H, W = fr.depth.shape
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    d_cam = pixel_directions(fr.intrinsics, u.reshape(-1), v.reshape(-1)).numpy().reshape(H, W, 3)
    if ds.bounds is not None:
        bounds = np.asarray(ds.bounds)
    else:  # bounds of the back-projected frame, padded
        pts = (d_cam * fr.depth[..., None]).reshape(-1, 3) @ fr.c2w[:3, :3].T + fr.c2w[:3, 3]
        pts = pts[fr.depth.reshape(-1) > 0]
        bounds = np.stack([pts.min(0) - 0.3, pts.max(0) + 0.3], -1)
    return fr.rgb, fr.depth, d_cam, fr.c2w, bounds


def make_field(bounds: np.ndarray) -> tuple[nn.Module, list[dict]]:
    """A small randomly initialised dense field and its optimiser parameter groups (lr 1e-2)."""
    try:
        from inrslam.fields import build_field
        from inrslam.fields.config import FieldConfig
    except ImportError:
        field = TinyGridField(bounds)
        return field, [{"params": list(field.parameters()), "lr": LR}]
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
