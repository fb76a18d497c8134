"""benchmarks/depth_pattern.py recovers a depth error pattern fixed in the image from frames of a known scene."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from inrslam.geometry.intrinsics import Intrinsics

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "depth_pattern.py"


@pytest.fixture(scope="module")
def script():
    spec = importlib.util.spec_from_file_location("depth_pattern", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def plane_depth(K: Intrinsics, c2w: np.ndarray) -> np.ndarray:
    """(H, W) depth of the world plane z = 2 seen by a camera c2w (4, 4) looking along +z."""
    v, u = np.mgrid[0 : K.height, 0 : K.width].astype(np.float64)
    d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], -1) @ c2w[:3, :3].T
    return (2.0 - c2w[2, 3]) / d[..., 2]  # the ray o + t d meets z = 2 at t; depth is t (d's camera z is 1)


def test_pair_residual_is_zero_for_exact_depth_and_relative_for_scaled(script):
    K = Intrinsics(60.0, 60.0, 32.0, 24.0, 64, 48)
    a, b = np.eye(4), np.eye(4)
    b[:3, 3] = [0.05, -0.02, 0.1]
    da, db = plane_depth(K, a), plane_depth(K, b)
    rel = np.linalg.inv(b) @ a
    r = script.pair_residual(da, db, rel, K)
    assert np.isfinite(r).sum() > 0.8 * r.size
    assert np.nanmax(np.abs(r)) < 1e-12
    # b's depth read 1 % long: the relative residual (d_b - z) / d_b is 1 - 1 / 1.01 everywhere it is seen
    r = script.pair_residual(da, 1.01 * db, rel, K)
    np.testing.assert_allclose(r[np.isfinite(r)], 1 - 1 / 1.01, rtol=1e-9)


def test_estimate_recovers_vertical_bands(script):
    """Frames moving sideways over a wall, depth x (1 + e) with e in vertical bands: the estimate's bands match."""
    K = Intrinsics(60.0, 60.0, 32.0, 24.0, 64, 48)
    rng = np.random.default_rng(0)
    u = np.arange(K.width)
    e = np.broadcast_to(0.01 * np.sin(u / 2.0), (K.height, K.width))
    poses = []
    for _ in range(40):
        T = np.eye(4)
        T[:3, 3] = [rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), rng.uniform(-0.2, 0.2)]
        poses.append(T)
    depths = np.stack([plane_depth(K, T) * (1 + e) for T in poses])
    est, halves = script.estimate(depths, poses, K, gaps=(1, 3), step=1, block=2, iters=6)
    assert halves > 0.9  # both halves of the pairs see the same pattern
    inner = (slice(4, -4), slice(4, -4))
    fit = est[inner] - est[inner].mean()
    true = e[inner] - e[inner].mean()
    assert np.corrcoef(fit.ravel(), true.ravel())[0, 1] > 0.9
    # correcting the depth with the estimate leaves less residual than the raw depth
    raw = np.nanmean(np.abs(script.pair_residual(depths[0], depths[1], np.linalg.inv(poses[1]) @ poses[0], K)))
    fixed = np.nanmean(np.abs(script.pair_residual(depths[0] / (1 + est), depths[1] / (1 + est),
                                                   np.linalg.inv(poses[1]) @ poses[0], K)))
    assert fixed < 0.5 * raw
