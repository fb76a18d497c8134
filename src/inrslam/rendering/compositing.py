"""Alpha compositing of per-sample colours and depths with weights from a rendering function G."""

from __future__ import annotations

import torch
from torch import Tensor


def composite(weights: Tensor, rgb: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Weighted sums along each ray, no background colour and no normalisation by Σw (docs/spec.md §4).

    Ĉ = Σ_i w_i c_i,  D̂ = Σ_i w_i z_i,  O = Σ_i w_i,  Var = Σ_i w_i (z_i - D̂)².

    Args:
        weights: (R, S) weights >= 0.
        rgb: (R, S, 3) per-sample colour in [0, 1].
        z: (R, S) sample z-depths, metres.
    Returns:
        rgb (R, 3), depth (R,) metres (z-depth), opacity (R,), depth_var (R,) m².

    Example: w = [[0.25, 0.75]], z = [[1, 2]] -> depth 1.75, opacity 1, depth_var 0.1875.
    """
    out_rgb = (weights[..., None] * rgb).sum(dim=-2)
    depth = (weights * z).sum(dim=-1)
    opacity = weights.sum(dim=-1)
    depth_var = (weights * (z - depth[..., None]) ** 2).sum(dim=-1)
    return out_rgb, depth, opacity, depth_var


def first_crossing(sdf: Tensor, z: Tensor) -> tuple[Tensor, Tensor]:
    """z-depth of the first + to - sign change of the SDF along each ray, linearly interpolated between its two
    samples: the surface the ray meets first (the depth an SDF defines, free of the bias of a weighted mean).

    Args:
        sdf: (R, S) SDF at the samples (any unit); z: (R, S) sorted sample z-depths, metres.
    Returns:
        depth (R,) metres (0 where the ray has no crossing) and has (R,) bool.

    Example: sdf = [[1, 0.5, -0.5]], z = [[1, 2, 3]] -> depth 2.5, has True.
    """
    cross = (sdf[:, :-1] > 0) & (sdf[:, 1:] <= 0)
    has = cross.any(dim=1)
    k = torch.argmax(cross.to(torch.int8), dim=1)
    r = torch.arange(z.shape[0], device=z.device)
    s0, s1 = sdf[r, k], sdf[r, k + 1]
    t = s0 / (s0 - s1).clamp_min(1e-8)
    zc = z[r, k] + t * (z[r, k + 1] - z[r, k])
    return torch.where(has, zc, torch.zeros_like(zc)), has


def surface_depth(sdf: Tensor, z: Tensor, fallback: Tensor) -> Tensor:
    """(R,) `first_crossing` depth of each ray, `fallback` (R,) (e.g. the weighted mean depth) where it has none."""
    zc, has = first_crossing(sdf, z)
    return torch.where(has, zc, fallback)
