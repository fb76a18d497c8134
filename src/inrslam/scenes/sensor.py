"""Simulated depth-sensor effects (pure numpy, deterministic from the given generator)."""

from __future__ import annotations

import numpy as np


def frame_rng(seed: int, index: int, stream: int) -> np.random.Generator:
    """Independent generator for one (seed, frame, effect) triple, so frames can be produced in any order."""
    return np.random.default_rng([int(seed), int(index), int(stream), 0x5CE7E])


def add_depth_noise(depth: np.ndarray, std_at_1m: float, rng: np.random.Generator) -> np.ndarray:
    """Kinect-like axial noise: z' = z + N(0, 1) * std_at_1m * z^2 on valid pixels.

    Args:
        depth: (H, W) float32 metres, 0 = invalid (left at 0).
        std_at_1m: noise std at 1 m, metres.
    Returns:
        (H, W) float32 metres; values that would turn non-positive become 0 (invalid).
    """
    if std_at_1m <= 0:
        return depth
    noise = rng.standard_normal(depth.shape).astype(np.float32)
    out = depth + noise * np.float32(std_at_1m) * depth * depth
    out = np.where((depth > 0) & (out > 0), out, 0.0)
    return out.astype(np.float32)


def hole_mask(shape: tuple[int, int], fraction: float, rng: np.random.Generator, blob_px: float = 6.0) -> np.ndarray:
    """Boolean (H, W) mask of missing-depth blobs covering ~`fraction` of the pixels.

    A random field on a grid of spacing `blob_px` pixels is upsampled bilinearly (smooth, blobby) and
    thresholded at its (1 - fraction) quantile, so the covered fraction matches `fraction` up to ties.
    """
    H, W = shape
    if fraction <= 0:
        return np.zeros(shape, dtype=bool)
    if fraction >= 1:
        return np.ones(shape, dtype=bool)
    gh, gw = int(np.ceil(H / blob_px)) + 2, int(np.ceil(W / blob_px)) + 2
    coarse = rng.random((gh, gw))
    y = (np.arange(H) + 0.5) / blob_px
    x = (np.arange(W) + 0.5) / blob_px
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = (y - y0)[:, None], (x - x0)[None, :]
    field = (coarse[y0][:, x0] * (1 - fx) + coarse[y0][:, x0 + 1] * fx) * (1 - fy) + (
        coarse[y0 + 1][:, x0] * (1 - fx) + coarse[y0 + 1][:, x0 + 1] * fx
    ) * fy
    field = field + 1e-9 * rng.random((H, W))  # break ties so the quantile is exact
    return field > np.quantile(field, 1.0 - fraction)


def apply_sensor(depth: np.ndarray, seed: int, index: int, depth_noise: float, missing_depth: float) -> np.ndarray:
    """Holes then noise on one clean (H, W) depth map; deterministic from (seed, index)."""
    out = depth
    if missing_depth > 0:
        out = np.where(hole_mask(depth.shape, missing_depth, frame_rng(seed, index, 1)), 0.0, out).astype(np.float32)
    if depth_noise > 0:
        out = add_depth_noise(out, depth_noise, frame_rng(seed, index, 2))
    return out
