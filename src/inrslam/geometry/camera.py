"""Pinhole rays (torch, device-agnostic). OpenCV axes; pixel centres at integer (u, v).

A camera-frame ray direction is d = ((u - cx) / fx, (v - cy) / fy, 1): *not* normalised, so the ray parameter
t equals the z-depth and a sensor depth map compares directly with t.
"""

from __future__ import annotations

import torch
from torch import Tensor

from inrslam.geometry.intrinsics import Intrinsics


def pixel_directions(intr: Intrinsics, u: Tensor, v: Tensor) -> Tensor:
    """Camera-frame ray directions with z = 1.

    Args:
        intr: intrinsics.
        u, v: (N,) pixel column / row (float or int).
    Returns:
        (N, 3) directions, dtype float32 unless u is floating.
    """
    dtype = u.dtype if u.is_floating_point() else torch.float32
    x = (u.to(dtype) - intr.cx) / intr.fx
    y = (v.to(dtype) - intr.cy) / intr.fy
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)


def grid_directions(intr: Intrinsics, stride: int = 1, device: torch.device | str | None = None
                    ) -> tuple[Tensor, Tensor]:
    """Every `stride`-th row and column of the image, row-major: flat pixel indices v·W + u (M,) int64 and their
    camera-frame directions (M, 3) float32 with z = 1 (`pixel_directions`)."""
    v, u = torch.meshgrid(torch.arange(0, intr.height, stride, device=device),
                          torch.arange(0, intr.width, stride, device=device), indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    return v * intr.width + u, pixel_directions(intr, u.float(), v.float())


def world_rays(c2w: Tensor, dirs_cam: Tensor) -> tuple[Tensor, Tensor]:
    """Rotate camera-frame directions into the world.

    Args:
        c2w: (4, 4), (1, 4, 4) or (N, 4, 4) camera-to-world.
        dirs_cam: (N, 3) camera-frame directions.
    Returns:
        origins (N, 3) metres, directions (N, 3) (same length as the camera-frame ones), in the promoted dtype of
        the two inputs.
    """
    dtype = torch.promote_types(c2w.dtype, dirs_cam.dtype)
    c2w, dirs_cam = c2w.to(dtype), dirs_cam.to(dtype)
    if c2w.dim() == 3 and c2w.shape[0] == 1:
        c2w = c2w[0]  # one pose for every direction
    R = c2w[..., :3, :3]
    t = c2w[..., :3, 3]
    if c2w.dim() == 2:
        return t.expand(dirs_cam.shape[0], 3), dirs_cam @ R.T
    return t, torch.einsum("nij,nj->ni", R, dirs_cam)

