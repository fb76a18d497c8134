"""World points of a depth map's valid pixels: x = R (d · dir) + t for every listed pixel whose depth d lies in
(d_min, d_max), in pixel order.

`world_points_torch` is the reference (mask, scale, rotate, translate: five passes over a 640 x 480 frame and its
(M, 3) temporaries, about 8 ms a frame); `world_points` runs one numba pass on CPU float32 tensors, the same
operations in the same order (d · dir rounded, then ((r0 x0 + r1 x1) + r2 x2) + t per coordinate, no fused
multiply-add), so on this project's machine it equals the reference to the bit (the tests compare within one
rounding, as another BLAS may order the reference's 3 x 3 product differently).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from inrslam.geometry.camera import world_rays


def world_points_torch(depth: torch.Tensor, idx: torch.Tensor, dirs: torch.Tensor, c2w: torch.Tensor,
                       d_min: float, d_max: float) -> torch.Tensor:
    """The reference: depth (P,) metres, pixel indices idx (M,) into it, their camera directions dirs (M, 3) with
    z = 1, camera-to-world c2w (4, 4) -> world points (K, 3) of the pixels with d_min < depth < d_max."""
    d = depth[idx]
    ok = (d > d_min) & (d < d_max)
    o, w = world_rays(c2w, dirs[ok] * d[ok][:, None])
    return o + w


@njit(cache=True, fastmath=False)
def _world_points(depth, idx, dirs, c2w, d_min, d_max, out):  # pragma: no cover - numba
    """out[:K] = the reference's points; returns K."""
    k = 0
    for m in range(idx.shape[0]):
        d = depth[idx[m]]
        if not (d > d_min and d < d_max):
            continue
        x0 = dirs[m, 0] * d
        x1 = dirs[m, 1] * d
        x2 = dirs[m, 2] * d
        for j in range(3):
            out[k, j] = ((x0 * c2w[j, 0] + x1 * c2w[j, 1]) + x2 * c2w[j, 2]) + c2w[j, 3]
        k += 1
    return k


def world_points(depth: torch.Tensor, idx: torch.Tensor, dirs: torch.Tensor, c2w: torch.Tensor,
                 d_min: float, d_max: float) -> torch.Tensor:
    """`world_points_torch` (same arguments and result), in one numba pass on CPU float32 tensors; the reference on
    any other device or dtype."""
    tensors = (depth, dirs, c2w)
    if any(t.device.type != "cpu" or t.dtype != torch.float32 for t in tensors) or idx.device.type != "cpu":
        return world_points_torch(depth, idx, dirs, c2w, d_min, d_max)
    out = np.empty((idx.shape[0], 3), np.float32)
    k = _world_points(depth.contiguous().numpy(), idx.contiguous().numpy(), dirs.contiguous().numpy(),
                      c2w.detach().contiguous().numpy(), np.float32(d_min), np.float32(d_max), out)
    return torch.from_numpy(out[:k])
