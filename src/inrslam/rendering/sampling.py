"""Ray sampling (depth-guided, docs/spec.md §5.1) and pixel sampling (docs/spec.md §5.2).

Sample positions are z-depths along the unnormalised camera-z-1 directions (metres), so the point of sample z is
o + z·d and a measured depth D compares directly with z.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from inrslam.rendering.config import SamplingConfig, SamplingVariant


def aabb_exit(origins: Tensor, dirs: Tensor, bounds: Tensor) -> Tensor:
    """Ray parameter where each ray leaves an axis-aligned box (slab method).

    t_exit = min over axes of max((b_min - o)/d, (b_max - o)/d); axes with d = 0 never bound the ray.

    Args:
        origins: (R, 3) metres; dirs: (R, 3) (any length; t is in units of |d|); bounds: (3, 2) [[min, max], ...].
    Returns:
        (R,) exit parameter (negative if the box lies behind the origin; +inf if every d component is 0).

    Example: o = 0, d = (0, 0, 1), box [-1, 1]^2 x [-1, 3] -> 3.
    """
    lo, hi = bounds[:, 0], bounds[:, 1]
    safe = torch.where(dirs == 0, torch.ones_like(dirs), dirs)
    t1 = (lo - origins) / safe
    t2 = (hi - origins) / safe
    t_far = torch.maximum(t1, t2)
    t_far = torch.where(dirs == 0, torch.full_like(t_far, float("inf")), t_far)
    return t_far.min(dim=-1).values


def stratified_jitter(z: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Jitter sorted samples within their strata (docs/spec.md §5.1).

    With mid-points m_k = (z_k + z_{k+1})/2: lower = [z_0, m_0, ..., m_{S-2}], upper = [m_0, ..., m_{S-2}, z_{S-1}],
    z'_k = lower_k + u_k (upper_k - lower_k), u_k ~ U(0, 1). The result stays sorted and inside [z_0, z_{S-1}].

    Args:
        z: (R, S) sorted; generator: torch RNG on any device (None = global RNG of z's device). The uniforms are
            drawn on the generator's device and moved to z's, so a CPU generator works with CUDA samples (and
            the draws for a given seed do not depend on where z lives).
    Returns:
        (R, S) jittered samples.
    """
    mid = 0.5 * (z[..., 1:] + z[..., :-1])
    lower = torch.cat([z[..., :1], mid], dim=-1)
    upper = torch.cat([mid, z[..., -1:]], dim=-1)
    gen_device = generator.device if generator is not None else z.device
    u = torch.rand(z.shape, generator=generator, device=gen_device, dtype=z.dtype).to(z.device)
    return lower + u * (upper - lower)


def sample_counts(cfg: SamplingConfig) -> tuple[int, int]:
    """(free-space, surface) sample counts for rays with depth, after the sampling variant (docs/spec.md §7.8)."""
    if SamplingVariant(cfg.variant) is SamplingVariant.SAMPLING:
        return cfg.n_free + cfg.n_surface, 0
    return cfg.n_free, cfg.n_surface


@torch.no_grad()
def sample_depths(
    depth: Tensor,
    dirs: Tensor,
    origins: Tensor,
    bounds: Tensor | np.ndarray,
    cfg: SamplingConfig,
    truncation: float,
    generator: torch.Generator | None = None,
    kernel: str = "auto",
) -> Tensor:
    """Sample z-depths along rays, guided by the measured depth (docs/spec.md §5.1; supplementary §1).

    Rays with depth D > 0: `n_free` samples near + (far_factor·D - near)·k/(n_free-1) and `n_surface` samples
    D - band·T + 2·band·T·k/(n_surface-1) (clamped to >= near), merged and sorted (a group of one sample has only
    its k = 0 sample: near, or D - band·T).
    Rays with D = 0: S samples near + (t_far - near)·k/(S-1), t_far = `aabb_exit` + 0.01 (at least near + 0.01).
    Then stratified jitter (`cfg.jitter`). No gradient flows through the samples.

    S (same for all rays) = n_free + n_surface when any ray of the batch has depth, else `n_uniform` (e.g. held-out
    renders without depth).

    Args:
        depth: (R,) measured z-depth, metres, 0 = none.
        dirs: (R, 3) world directions (camera z component 1).
        origins: (R, 3) metres.
        bounds: (3, 2) scene box, metres.
        cfg: sampling options; truncation: T, metres.
        generator: RNG for the jitter, on any device (a CPU generator with CUDA rays is fine).
        kernel: "torch" (the reference), "numba" (one fused pass, CPU float32 / float64, bit-identical to it:
            `sampling_kernel`) or "auto" (numba where it can).
    Returns:
        (R, S) sorted z-depths, metres, dtype of `depth`.
    """
    n_free, n_surf = sample_counts(cfg)
    device, dtype = depth.device, depth.dtype if depth.is_floating_point() else torch.float32
    depth = depth.to(dtype)
    has_depth = depth > 0
    any_depth = bool(has_depth.any())
    S = n_free + n_surf if any_depth else cfg.n_uniform
    if S < 2:
        raise ValueError(f"need at least 2 samples per ray, got {S}")
    R = depth.shape[0]
    if R == 0:
        return depth.new_zeros((0, S))
    near = float(cfg.near)
    bounds_t = torch.as_tensor(bounds, dtype=dtype, device=device)

    lin = torch.linspace(0.0, 1.0, S, device=device, dtype=dtype)
    t_far = (aabb_exit(origins.to(dtype), dirs.to(dtype), bounds_t) + 0.01).clamp_min(near + 0.01)
    fusable = device.type == "cpu" and dtype in (torch.float32, torch.float64)
    if kernel == "numba" and not fusable:
        raise ValueError("sampling kernel 'numba' needs CPU float32/float64 depth; use 'auto' or 'torch'")
    if kernel not in ("auto", "torch", "numba"):
        raise ValueError(f"unknown sampling kernel {kernel!r} (choices: auto, torch, numba)")
    if kernel != "torch" and fusable:
        return _fused_samples(depth, t_far, lin, n_free, n_surf, S, near, cfg, truncation, generator)
    z = near + (t_far[:, None] - near) * lin  # rays without depth
    if any_depth:
        d = depth[:, None]
        parts = [near + (cfg.far_factor * d - near).clamp_min(0.0) * torch.linspace(0, 1, n_free, device=device,
                                                                                     dtype=dtype)]
        if n_surf > 0:
            offs = torch.linspace(-1.0, 1.0, n_surf, device=device, dtype=dtype) * (cfg.band * truncation)
            parts.append((d + offs).clamp_min(near))
        z_depth = torch.sort(torch.cat(parts, dim=-1), dim=-1).values
        z = torch.where(has_depth[:, None], z_depth, z)
    if cfg.jitter:
        z = stratified_jitter(z, generator)
    return z


def _fused_samples(depth: Tensor, t_far: Tensor, lin: Tensor, n_free: int, n_surf: int, S: int, near: float,
                   cfg: SamplingConfig, truncation: float, generator: torch.Generator | None) -> Tensor:
    """`sample_depths`' samples by `sampling_kernel.depth_guided_samples` (same values, same random draws)."""
    from inrslam.rendering.sampling_kernel import depth_guided_samples

    dtype = depth.dtype
    lin_free = torch.linspace(0, 1, n_free, dtype=dtype)
    offs = torch.linspace(-1.0, 1.0, n_surf, dtype=dtype) * (cfg.band * truncation)
    gen_device = generator.device if generator is not None else "cpu"
    u = (torch.rand((depth.shape[0], S), generator=generator, device=gen_device, dtype=dtype).cpu() if cfg.jitter
         else depth.new_zeros((0, S)))  # the reference's draw: same shape, dtype and generator
    out = np.empty((depth.shape[0], S), dtype=depth.numpy().dtype)
    t = depth.numpy().dtype.type
    depth_guided_samples(depth.contiguous().numpy(), t_far.contiguous().numpy(), lin_free.numpy(), offs.numpy(),
                         lin.numpy(), t(near), t(cfg.far_factor), t(0.5), t(0.0), u.numpy(), bool(cfg.jitter), out)
    return torch.from_numpy(out)


def distinct_indices(total: int, n: int, generator: torch.Generator | None = None) -> Tensor:
    """n distinct integers of [0, total), every n-subset equally likely, in random order (CPU, int64 (n,)).

    Cheaper than a full permutation when n is small against total: draws ~1.25 n with replacement, keeps the
    distinct values (a uniformly random subset of their number, by symmetry) and takes a random n of them,
    drawing again in the rare case that fewer than n are distinct. A permutation when n > total / 4.
    """
    if n > total // 4:
        return torch.randperm(total, generator=generator)[:n]
    while True:
        distinct = torch.unique(torch.randint(0, total, (n + n // 4 + 16,), generator=generator))
        if distinct.numel() >= n:
            return distinct[torch.randperm(distinct.numel(), generator=generator)[:n]]


def sample_pixels(
    height: int,
    width: int,
    n: int,
    edge_margin: int = 0,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor]:
    """Draw n distinct pixels uniformly from the image without its `edge_margin`-pixel border (docs/spec.md §5.2).

    Args:
        height, width: image size; n: number of pixels; edge_margin: border width, pixels.
        generator: torch RNG on any device (None = global CPU RNG); the permutation is drawn on the generator's
            device; device: device of the returned tensors (default: the generator's).
    Returns:
        u (column), v (row): (n,) int64 with edge_margin <= u < width - edge_margin (same for v).
    """
    h, w = height - 2 * edge_margin, width - 2 * edge_margin
    if h <= 0 or w <= 0:
        raise ValueError(f"edge_margin {edge_margin} leaves no pixels in a {width}x{height} image")
    if n > h * w:
        raise ValueError(f"cannot draw {n} distinct pixels from {h * w} ({width}x{height}, margin {edge_margin})")
    gen_device = generator.device if generator is not None else "cpu"
    idx = torch.randperm(h * w, generator=generator, device=gen_device)[:n].to(device or gen_device)
    return idx % w + edge_margin, torch.div(idx, w, rounding_mode="floor") + edge_margin
