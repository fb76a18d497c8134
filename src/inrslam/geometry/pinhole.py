"""Pinhole maths in numpy (float64): the one implementation readers, scenes, evaluation and registration share.
The torch twins used on the device are in `inrslam.geometry.camera`.

OpenCV axes, pixel centres at integer (u, v); a camera-frame ray d = ((u - cx) / fx, (v - cy) / fy, 1), so the ray
parameter is the z-depth; back-projection p = z d; projection u = fx x / z + cx, v = fy y / z + cy.
"""

from __future__ import annotations

import numpy as np


def pixel_directions_np(fx: float, fy: float, cx: float, cy: float, u, v) -> np.ndarray:
    """(N,) pixel columns u and rows v -> (N, 3) float64 camera-frame directions with z = 1."""
    u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones(np.shape(u))], axis=-1)


def image_directions_np(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> np.ndarray:
    """(H*W, 3) directions of every pixel, row-major over (v, u)."""
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    return pixel_directions_np(fx, fy, cx, cy, u, v).reshape(-1, 3)


def backproject_np(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float, stride: int = 1,
                   max_depth: float = np.inf) -> np.ndarray:
    """(H, W) z-depth in metres -> (M, 3) float64 camera-frame points of the valid pixels (0 < d <= max_depth,
    finite) on every `stride`-th row and column, row-major. Example: depth 2 at pixel (cx + fx, cy) -> (2, 0, 2)."""
    d = np.asarray(depth, dtype=np.float64)[::stride, ::stride]
    v, u = np.nonzero((d > 0) & (d <= max_depth) & np.isfinite(d))
    z = d[v, u]
    u, v = u * stride, v * stride
    return np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1)


def project_np(points_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) camera-frame points -> pixel u (N,), v (N,) and z-depth (N,) (inf / nan where z = 0)."""
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return fx * p[:, 0] / z + cx, fy * p[:, 1] / z + cy, z
