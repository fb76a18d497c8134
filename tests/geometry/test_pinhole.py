"""The numpy pinhole maths: analytic cases, round trips, and agreement with the torch twins."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.errors import DataError
from inrslam.geometry.camera import grid_directions, pixel_directions
from inrslam.geometry.intrinsics import Intrinsics, reproject_image
from inrslam.geometry.pinhole import backproject_np, image_directions_np, pixel_directions_np, project_np

INTR = Intrinsics(fx=100.0, fy=120.0, cx=31.5, cy=23.5, width=64, height=48)
P = (INTR.fx, INTR.fy, INTR.cx, INTR.cy)


def test_backprojection_of_an_analytic_pixel():
    depth = np.zeros((INTR.height, INTR.width))
    depth[24, 40] = 2.0  # (u, v) = (40, 24)
    pts = backproject_np(depth, *P)
    assert np.allclose(pts, [[(40 - 31.5) / 100 * 2, (24 - 23.5) / 120 * 2, 2.0]])


def test_backproject_then_project_returns_the_pixels_and_depths():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 4.0, (INTR.height, INTR.width))
    depth[rng.random(depth.shape) < 0.1] = 0.0
    depth[0, 1], depth[2, 3] = np.inf, 9.0
    pts = backproject_np(depth, *P, stride=2, max_depth=5.0)
    u, v, z = project_np(pts, *P)
    keep = (depth[::2, ::2] > 0) & (depth[::2, ::2] <= 5.0)
    vv, uu = np.nonzero(keep)
    assert np.allclose(u, 2 * uu) and np.allclose(v, 2 * vv) and np.allclose(z, depth[::2, ::2][keep])


def test_numpy_and_torch_directions_agree():
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, 64, 50), rng.uniform(0, 48, 50)
    d_np = pixel_directions_np(*P, u, v)
    d_t = pixel_directions(INTR, torch.as_tensor(u), torch.as_tensor(v)).numpy()
    assert np.allclose(d_np, d_t)
    grid = image_directions_np(*P, INTR.width, INTR.height)
    assert grid.shape == (64 * 48, 3) and np.allclose(grid[INTR.width + 2], pixel_directions_np(*P, [2], [1])[0])


@pytest.mark.parametrize("stride", [1, 3])
def test_grid_directions_are_every_strided_pixel_row_major(stride):
    idx, dirs = grid_directions(INTR, stride)
    grid = image_directions_np(*P, INTR.width, INTR.height)
    v, u = np.mgrid[0:INTR.height:stride, 0:INTR.width:stride]
    want = (v * INTR.width + u).reshape(-1)
    assert idx.dtype == torch.int64 and np.array_equal(idx.numpy(), want)
    assert dirs.dtype == torch.float32 and np.allclose(dirs.numpy(), grid[want], atol=1e-6)
    assert np.allclose(dirs[1].numpy(), [(stride - 31.5) / 100, (0 - 23.5) / 120, 1.0])  # pixel (u, v) = (stride, 0)


def test_reproject_image_samples_the_source_camera_at_the_scaled_coordinates():
    rng = np.random.default_rng()
    src = Intrinsics(*rng.uniform(40, 50, 2), rng.uniform(30, 34), rng.uniform(22, 26), 64, 48)  # a wider camera ...
    dst = Intrinsics(*rng.uniform(62, 70, 2), 32.0, 24.0, 64, 48)  # ... seen by a narrower depth camera
    a, b, c = rng.normal(size=3)
    U, V = np.meshgrid(np.arange(64.0), np.arange(48.0))
    image = np.stack([a * U + b * V, c * U * V], axis=-1)  # bilinear in (u, v): interpolated exactly
    out = reproject_image(image, src, dst)
    u = src.cx + (np.arange(64) - dst.cx) * src.fx / dst.fx  # where each result column looks in the source
    v = src.cy + (np.arange(48) - dst.cy) * src.fy / dst.fy
    np.testing.assert_allclose(out[..., 0], a * u[None, :] + b * v[:, None], atol=1e-9)
    np.testing.assert_allclose(out[..., 1], c * np.outer(v, u), atol=1e-9)
    # a 3-D point seen at result pixel (ud, vd) has there the value of its source pixel (us, vs)
    ud, vd = 50, 7
    X = np.array([(ud - dst.cx) / dst.fx, (vd - dst.cy) / dst.fy, 1.0]) * 2.5
    us, vs = src.fx * X[0] / X[2] + src.cx, src.fy * X[1] / X[2] + src.cy
    assert out[vd, ud, 0] == pytest.approx(a * us + b * vs, abs=1e-9)
    assert np.array_equal(reproject_image(image, src, src), image)  # the same camera: unchanged
    with pytest.raises(DataError, match="64x48"):
        reproject_image(image[:10], src, dst)


def test_reproject_integer_image_rounds_to_the_nearest_level():
    rng = np.random.default_rng()
    src = Intrinsics(*rng.uniform(40, 50, 2), rng.uniform(30, 34), rng.uniform(22, 26), 64, 48)
    dst = Intrinsics(*rng.uniform(62, 70, 2), 32.0, 24.0, 64, 48)
    flat = np.full((48, 64, 3), 57, np.uint8)
    assert np.array_equal(reproject_image(flat, src, dst), flat)  # a flat image stays flat (truncation lost a level)
    image = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    exact = reproject_image(image.astype(np.float64), src, dst)
    out = reproject_image(image, src, dst)
    assert out.dtype == np.uint8 and np.abs(out - exact).max() <= 0.5 + 1e-3  # float32 weights: a hair over 0.5
    assert abs(float((out - exact).mean())) < 0.05  # unbiased (truncation: -0.5)


def test_world_rays_broadcast_one_pose_and_promote_dtypes():
    from inrslam.geometry.camera import world_rays
    from inrslam.geometry.se3 import se3_exp

    c2w = se3_exp(torch.randn(1, 6, dtype=torch.float64))[0]
    d = torch.randn(5, 3)
    o2, w2 = world_rays(c2w, d)  # (4, 4) pose: float64 result, directions rotated
    assert o2.shape == w2.shape == (5, 3) and w2.dtype == torch.float64
    torch.testing.assert_close(w2, d.double() @ c2w[:3, :3].T)
    assert torch.equal(o2, c2w[:3, 3].expand(5, 3))
    o1, w1 = world_rays(c2w[None], d)  # (1, 4, 4): the same pose for every direction
    assert torch.equal(o1, o2) and torch.equal(w1, w2)
    oN, wN = world_rays(c2w.expand(5, 4, 4), d)
    torch.testing.assert_close(wN, w2)
    torch.testing.assert_close(oN, o2)
