"""Alpha compositing of per-sample colours and depths with weights from a rendering function G."""

from __future__ import annotations

from typing import Callable

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


def _sign_changes(sdf: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(R, S) `sdf` -> (R, S-1) cross: interval [k, k+1] goes from > 0 to <= 0; (R,) index of the first one (0 if
    none); (R,) whether there is one."""
    cross = (sdf[:, :-1] > 0) & (sdf[:, 1:] <= 0)
    return cross, torch.argmax(cross.to(torch.int8), dim=1), cross.any(dim=1)


def first_crossing(sdf: Tensor, z: Tensor) -> tuple[Tensor, Tensor]:
    """z-depth of the first + to - sign change of the SDF along each ray, linearly interpolated between its two
    samples: the surface the ray meets first (the depth an SDF defines, free of the bias of a weighted mean).

    Args:
        sdf: (R, S) SDF at the samples (any unit); z: (R, S) sorted sample z-depths, metres.
    Returns:
        depth (R,) metres (0 where the ray has no crossing) and has (R,) bool.

    Example: sdf = [[1, 0.5, -0.5]], z = [[1, 2, 3]] -> depth 2.5, has True.
    """
    _, k, has = _sign_changes(sdf)
    r = torch.arange(z.shape[0], device=z.device)
    s0, s1 = sdf[r, k], sdf[r, k + 1]
    t = s0 / (s0 - s1).clamp_min(1e-8)
    zc = z[r, k] + t * (z[r, k + 1] - z[r, k])
    return torch.where(has, zc, torch.zeros_like(zc)), has


def surface_depth(sdf: Tensor, z: Tensor, fallback: Tensor) -> Tensor:
    """(R,) `first_crossing` depth of each ray, `fallback` (R,) (e.g. the weighted mean depth) where it has none."""
    zc, has = first_crossing(sdf, z)
    return torch.where(has, zc, fallback)


def surface_intervals(sdf_m: Tensor, seg_m: Tensor, count: int, margin: float = 3.0) -> tuple[Tensor, Tensor]:
    """The first `count` sample intervals of each ray that may hold its first surface: the one where the SDF
    changes sign, and every earlier one whose end-point distances sum below `margin` x its length (a 1-Lipschitz
    SDF can reach zero between them when margin >= 1: a thin object the samples stepped over; a trained SDF is not
    1-Lipschitz, hence the default 3, measured in docs/accurate.md).

    Args:
        sdf_m: (R, S) SDF at sorted samples, metres; seg_m: (R, S-1) lengths of the intervals, metres.
    Returns:
        (R, count) index i of each interval [i, i+1] in ray order, and (R, count) bool: whether it is one.

    Example: sdf_m = [[0.1, 0.02, 0.03, -0.1]], seg_m = [[0.1, 0.1, 0.1]], count 2, margin 1 -> [[1, 2]],
    [[True, True]] (0.1 + 0.02 > 0.1: no surface fits in the first interval).
    """
    R, S = sdf_m.shape
    a, b = sdf_m[:, :-1], sdf_m[:, 1:]
    cross, k, has = _sign_changes(sdf_m)
    first = torch.where(has, k, S)  # S: no crossing
    idx = torch.arange(S - 1, device=sdf_m.device).expand(R, -1)
    near = (a > 0) & (b > 0) & (a + b < margin * seg_m)
    keep = (cross | near) & (idx <= first[:, None])
    key = torch.where(keep, idx, torch.full_like(idx, S)).sort(dim=1).values[:, :count]
    if key.shape[1] < count:
        key = torch.cat([key, key.new_full((R, count - key.shape[1]), S)], dim=1)
    valid = key < S - 1
    return key.clamp_max(S - 2), valid


def refine_crossing(sdf_fn: Callable[[Tensor], Tensor], origins: Tensor, dirs: Tensor, z: Tensor, sdf_m: Tensor,
                    n_refine: int, count: int = 8, margin: float = 3.0) -> tuple[Tensor, Tensor]:
    """The first surface along each ray, searched again inside the `surface_intervals` of a coarse pass with
    `n_refine` more samples each (uniform, inside the interval), in ray order: the first refined interval with a
    + to - crossing gives it (`first_crossing` on that interval's samples).

    Args:
        sdf_fn: (P, 3) world points -> (P,) SDF, metres. origins, dirs: (R, 3) (points = o + z d); z: (R, S) sorted
            coarse z-depths and sdf_m: (R, S) their SDF, metres.
    Returns: depth (R,) metres (0 where no refined interval crosses) and has (R,) bool.
    """
    R = z.shape[0]
    seg = (z[:, 1:] - z[:, :-1]) * dirs.norm(dim=-1, keepdim=True)
    k, valid = surface_intervals(sdf_m, seg, count, margin)
    z0, z1 = z.gather(1, k), z.gather(1, k + 1)  # (R, m)
    t = torch.arange(1, n_refine + 1, device=z.device, dtype=z.dtype) / (n_refine + 1)
    zi = z0[..., None] + t * (z1 - z0)[..., None]  # (R, m, n) interior samples
    si = torch.ones_like(zi)  # padding intervals are neither placed nor queried: no crossing
    if valid.any():
        rows = valid.nonzero()[:, 0]  # the ray of each candidate interval
        pts = origins[rows, None, :] + zi[valid][..., None] * dirs[rows, None, :]  # (V, n, 3)
        si[valid] = sdf_fn(pts.reshape(-1, 3)).reshape(-1, n_refine).to(si.dtype)
    zz = torch.cat([z0[..., None], zi, z1[..., None]], dim=-1)  # (R, m, n + 2)
    ss = torch.cat([sdf_m.gather(1, k)[..., None], si, sdf_m.gather(1, k + 1)[..., None]], dim=-1)
    ss = torch.where(valid[..., None], ss, torch.ones_like(ss))  # padding intervals: no crossing
    zc, has = first_crossing(ss.reshape(-1, n_refine + 2), zz.reshape(-1, n_refine + 2))
    zc, has = zc.reshape(R, count), has.reshape(R, count)
    j = torch.argmax(has.to(torch.int8), dim=1)
    r = torch.arange(R, device=z.device)
    found = has.any(dim=1)
    return torch.where(found, zc[r, j], torch.zeros_like(zc[r, j])), found
