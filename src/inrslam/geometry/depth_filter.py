"""Edge-preserving smoothing of a depth image before registration (numpy, float64 maths; no I/O).

A depth sensor's axial noise grows with the square of the depth (Kinect-like: std = s z^2). A bilateral filter
averages each valid pixel with its valid neighbours within `radius` pixels, weighted by a spatial Gaussian and by how
close their depths are, measured in units of that noise, so that a depth edge (a chair in front of a wall) is not
blurred:

    z'(p) = sum_q w(p, q) z(q) / sum_q w(p, q),
    w(p, q) = exp(-|p - q|^2 / (2 sigma_px^2)) exp(-(z(q) - z(p))^2 / (2 (k s z(p)^2 + floor)^2)) [z(q) > 0]

with sigma_px = radius / 1.5, k = `range_sigmas` (3: neighbours within about three noise stds count fully, a step of
ten stds does not) and a 1 mm floor. Invalid pixels (0, non-finite) stay 0 and never contribute. KinectFusion
(Newcombe et al., ISMAR 2011) filters its depth the same way before ICP; on noisy depth, GICP's per-point covariances
from a few noisy neighbours are near-isotropic and the registration drifts (docs/accurate.md).
"""

from __future__ import annotations

import math

import numpy as np

RANGE_FLOOR = 1e-3  # metres: the range std never drops below this (noise-free depth still smooths within 1 mm)


def bilateral_depth(depth: np.ndarray, radius: int, noise_at_1m: float, range_sigmas: float = 3.0,
                    stride: int = 1) -> np.ndarray:
    """Bilateral filter of a z-depth image whose noise std is `noise_at_1m` x z^2.

    Args:
        depth: (H, W) metres, 0 or non-finite = invalid.
        radius: window half-size in pixels (0 = no filtering: `depth` is returned as float64).
        noise_at_1m: sensor noise std at 1 m, metres (the range weight's scale grows with z^2).
        range_sigmas: range std of the weight, in noise stds.
        stride: filter only every `stride`-th row and column (the pixels a strided back-projection reads); the
            others are returned unfiltered.
    Returns:
        (H, W) float64 metres; invalid pixels 0. Example: a constant depth stays constant; a step of 1 m between
        two planes at 2 m and 3 m stays a step (its weight is exp(-(1 / 0.05)^2 / 2) ~ 0 at s = 4 mm).
    """
    d = np.asarray(depth, dtype=np.float64)
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    if radius <= 0:
        return d
    H, W = d.shape
    pad = np.pad(d, radius)
    rows, cols = np.arange(0, H, stride), np.arange(0, W, stride)
    centre = d[np.ix_(rows, cols)]
    inv_2s2 = 1.0 / (2.0 * (range_sigmas * noise_at_1m * centre * centre + RANGE_FLOOR) ** 2)
    sigma_px = radius / 1.5
    num = np.zeros_like(centre)
    den = np.zeros_like(centre)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            nb = pad[np.ix_(rows + radius + dy, cols + radius + dx)]
            w = np.exp(-(dx * dx + dy * dy) / (2.0 * sigma_px * sigma_px) - (nb - centre) ** 2 * inv_2s2)
            w *= nb > 0
            num += w * nb
            den += w
    out = d.copy()
    out[np.ix_(rows, cols)] = np.where(centre > 0, num / np.maximum(den, 1e-300), 0.0)
    return out


def estimate_depth_noise(depth: np.ndarray, keep: float = 0.9) -> float:
    """Robust estimate of the noise std at 1 m, metres, of a depth image whose noise grows with z^2.

    Inverse depth w = 1/z is affine in the pixel coordinates on any plane, so its second difference along a row or
    column, w(u+1) - 2 w(u) + w(u-1), is zero on planes and, with independent noise dz = s z^2 per pixel
    (dw = -dz / z^2 = s N(0, 1)), has std sqrt(6) s. Edges and corners are rare large values: the RMS is taken over
    the `keep` fraction of smallest magnitudes (both directions, every valid triple) and divided by the RMS a unit
    Gaussian has over the same fraction (0.789 for 0.9), so s is unbiased on Gaussian noise. Unlike a median, this
    stays above 0 on quantised real depth (Kinect: ~1e-3), where most neighbours share a depth step. Example: z = 2
    plus N(0, 0.016^2) gives s ~ 0.004; noise-free piecewise-planar depth gives ~0. nan when no valid triple exists.
    """
    d = np.asarray(depth, dtype=np.float64)
    w = np.where(np.isfinite(d) & (d > 0), 1.0 / np.where(d > 0, d, 1.0), np.nan)
    second = [w[:, 2:] - 2 * w[:, 1:-1] + w[:, :-2], w[2:] - 2 * w[1:-1] + w[:-2]]
    vals = np.abs(np.concatenate([s[np.isfinite(s)] for s in second]))
    if vals.size == 0:
        return float("nan")
    kept = vals[vals <= np.quantile(vals, keep)]
    return float(np.sqrt(np.mean(kept * kept) / 6.0) / _truncated_unit_rms(keep))


def _truncated_unit_rms(keep: float) -> float:
    """RMS of a standard normal over its `keep` fraction of smallest magnitudes: sqrt(1 - 2 a phi(a) / keep) with
    a the (1 + keep) / 2 quantile. Example: keep = 0.9 -> a = 1.645, 0.789."""
    from statistics import NormalDist

    a = NormalDist().inv_cdf((1.0 + keep) / 2.0)
    return math.sqrt(1.0 - 2.0 * a * math.exp(-a * a / 2.0) / math.sqrt(2.0 * math.pi) / keep)
