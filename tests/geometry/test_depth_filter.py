"""The bilateral depth filter: analytic cases (constant and linear depth are kept, a step edge is not blurred),
invalid pixels, striding, and the noise it removes from a noisy plane."""

from __future__ import annotations

import numpy as np
import pytest

from inrslam.geometry.depth_filter import bilateral_depth, estimate_depth_noise


def test_radius_zero_returns_the_depth_with_invalid_pixels_zeroed():
    d = np.array([[1.0, np.nan], [np.inf, -1.0]], dtype=np.float32)
    out = bilateral_depth(d, 0, 0.004)
    assert out.dtype == np.float64 and np.array_equal(out, [[1.0, 0.0], [0.0, 0.0]])


def test_constant_depth_stays_constant():
    d = np.full((20, 30), 2.5)
    assert np.allclose(bilateral_depth(d, 2, 0.004), 2.5, rtol=0, atol=1e-12)


def test_a_linear_ramp_is_kept_away_from_the_border():
    # z(u, v) = 2 + 0.01 u - 0.005 v: the window is symmetric and so are the range weights of a ramp -> exact
    v, u = np.mgrid[0:24, 0:32].astype(np.float64)
    d = 2.0 + 0.01 * u - 0.005 * v
    out = bilateral_depth(d, 2, 0.004)
    assert np.allclose(out[2:-2, 2:-2], d[2:-2, 2:-2], rtol=0, atol=1e-12)


def test_a_depth_step_is_not_blurred():
    d = np.full((16, 16), 3.0)
    d[:, :8] = 2.0  # a 1 m step: ~14 range stds at 2 m with 4 mm noise at 1 m and 3 stds
    out = bilateral_depth(d, 3, 0.004)
    assert np.abs(out - d).max() < 1e-9


def test_invalid_neighbours_do_not_pull_the_depth_towards_zero():
    d = np.full((12, 12), 2.0)
    d[::2, ::3] = 0.0
    out = bilateral_depth(d, 2, 0.004)
    assert np.array_equal(out == 0, d == 0)
    assert np.allclose(out[d > 0], 2.0, atol=1e-12)


@pytest.mark.parametrize("stride", [2, 3])
def test_strided_filtering_equals_full_filtering_at_the_strided_pixels(stride):
    rng = np.random.default_rng(3)
    d = rng.uniform(1.0, 3.0, (23, 31))
    d[rng.random(d.shape) < 0.1] = 0
    full, strided = bilateral_depth(d, 2, 0.01), bilateral_depth(d, 2, 0.01, stride=stride)
    assert np.allclose(strided[::stride, ::stride], full[::stride, ::stride], rtol=0, atol=1e-12)
    mask = np.ones(d.shape, bool)
    mask[::stride, ::stride] = False
    assert np.array_equal(strided[mask], d[mask])  # the pixels a strided back-projection skips are left as they were


def test_noise_on_a_plane_is_reduced_without_bias():
    rng = np.random.default_rng(0)
    s, z = 0.004, 2.0  # noise std 1.6 cm at 2 m
    noisy = z + rng.standard_normal((120, 160)) * s * z * z
    out = bilateral_depth(noisy, 2, s)
    inner = (slice(2, -2), slice(2, -2))
    assert abs(out[inner].mean() - z) < 1e-3
    # a 5x5 window with sigma 1.33 px averages ~10 effective samples: std falls by more than 2.5x
    assert out[inner].std() < noisy[inner].std() / 2.5


@pytest.mark.parametrize("s", [0.001, 0.004])
def test_noise_estimate_recovers_the_std_at_one_metre_on_noisy_planes(s):
    # a tilted plane (depth 1.5-3.2 m) and a wall step: inverse depth is affine on each, noise s z^2
    rng = np.random.default_rng(1)
    v, u = np.mgrid[0:240, 0:320].astype(np.float64)
    z = 1.0 / (0.3 + 0.0008 * u + 0.0005 * v)
    z[:, 200:] = 2.0  # an edge: outliers of the second difference
    noisy = z + rng.standard_normal(z.shape) * s * z * z
    noisy[rng.random(z.shape) < 0.05] = 0.0  # holes
    assert estimate_depth_noise(noisy) == pytest.approx(s, rel=0.05)


def test_noise_estimate_of_clean_and_quantised_depth():
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    z = 1.0 / (0.3 + 0.0008 * u + 0.0005 * v)
    assert estimate_depth_noise(z) < 1e-9  # planes: affine inverse depth
    # millimetre steps (a 16-bit PNG) are noise of their own: uniform, std 1 mm / sqrt(12) at ~2 m -> s ~ 7e-5
    assert 2e-5 < estimate_depth_noise(np.round(z * 1000) / 1000) < 3e-4
    assert np.isnan(estimate_depth_noise(np.zeros((4, 4))))
