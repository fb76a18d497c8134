"""Training losses (docs/spec.md §6; supplementary Eqs. (1)-(6), Hua & Wang CVPR 2024; masks after ESLAM).

    L = λ_p L_p + λ_g L_g + λ_fs L_fs + λ_c L_c + λ_t L_t

L_p: colour MSE over all rays and channels; L_g: depth MSE over rays with D > 0 (Eq. 1).
Per sample i of a ray with depth D (T = truncation, metres; s in T-units; z z-depth, metres):
    front (free space)  z < D - T                       e = s - target (target 1 T-unit; 0.1 = 'loss variant')
    centre              |z - D| < center_band·T         e = z + s·T - D  (Eq. 2)
    tail                |z - D| <= T and not centre     e = z + s·T - D
    (behind, z > D + T: unsupervised; with `behind` = b < 1 already z > D + b·T: a ray grazing an object's silhouette
    leaves the object soon after its depth, and 'inside' targets a full T behind it widen the object; a per-ray
    `behind` tensor lets the caller shorten the band only on such rays, e.g. at depth silhouettes)
Reduction: `per_ray` = mean of e² over each ray's masked samples, then mean over the rays having such samples
(Eqs. 3, 5); `global` = mean of e² over every masked sample of the batch (the reference code, docs/spec.md §13.16).
Empty sets contribute exactly 0 (never NaN).

The free-space / centre / tail terms read the field's scalar as an SDF. For renderers that are not SDF-based
(`SdfToWeights.sdf_based` False: plain NeRF density) they are meaningless — a density is not a distance — so
`compute_losses(..., sdf_terms=False)` returns them as zeros and leaves them out of `total` (L = λ_p L_p + λ_g L_g).
"""

from __future__ import annotations

import math
from typing import Any, Callable

import torch
from torch import Tensor

from inrslam.fields.config import KernelChoice
from inrslam.fields.kernels.function import cpu_floats
from inrslam.rendering.compositing import composite
from inrslam.rendering.config import LossConfig, LossReduction
from inrslam.rendering.fused_losses import composite_losses
from inrslam.rendering.render import RenderOutput, render_samples


def safe_mean(values: Tensor, mask: Tensor | None = None) -> Tensor:
    """Mean of `values` over `mask` (all if None); 0 for an empty selection, non-selected entries never leak NaN."""
    if mask is None:
        return values.sum() / max(values.numel(), 1)
    mask = mask.expand_as(values)
    return torch.where(mask, values, torch.zeros_like(values)).sum() / mask.sum().clamp_min(1)


def masked_sample_mean(values: Tensor, mask: Tensor, reduction: LossReduction) -> Tensor:
    """Reduce per-sample values over a (R, S) mask.

    Args:
        values: (R, S); mask: (R, S) bool.
        reduction: `per_ray` -> (1/|R'|) Σ_{r∈R'} (1/|P_r|) Σ_{i∈P_r} v_ri over rays R' with a non-empty P_r;
            `global` -> Σ v over the mask / |mask|.
    Returns:
        scalar (0 if the mask is empty).

    Example: v = [[1, 3, 8]], [[5, 5, 5]] with mask [[1, 1, 0], [1, 0, 0]] -> per_ray (2 + 5)/2 = 3.5,
    global (1 + 3 + 5)/3 = 3.
    """
    v = torch.where(mask, values, torch.zeros_like(values))
    if LossReduction(reduction) is LossReduction.GLOBAL:
        return v.sum() / mask.sum().clamp_min(1)
    count = mask.sum(dim=-1)
    per_ray = v.sum(dim=-1) / count.clamp_min(1)
    return per_ray.sum() / (count > 0).sum().clamp_min(1)


def sdf_masks(z: Tensor, target_depth: Tensor, truncation: float, center_band: float = 0.4,
              behind: float | Tensor = 1.0) -> tuple[Tensor, Tensor, Tensor]:
    """Per-sample masks (front, centre, tail), all False on rays without depth.

    Args:
        z: (R, S) metres; target_depth: (R,) metres (0 = none); truncation: T metres; center_band: in units of T;
        behind: centre and tail end at z <= D + behind·T (units of T): one value, or (R,) one per ray.
    Returns:
        front z < D - T; centre |z - D| < center_band·T; tail |z - D| <= T and not centre; each (R, S) bool.
    """
    d = target_depth[:, None]
    valid = d > 0
    diff = z - d
    front = (diff < -truncation) & valid
    if isinstance(behind, Tensor):
        near = valid & (diff <= behind[:, None] * truncation)
    else:
        near = valid if behind >= 1.0 else valid & (diff <= behind * truncation)
    center = (diff.abs() < center_band * truncation) & near
    tail = (diff.abs() <= truncation) & ~center & near
    return front, center, tail


def compute_losses(out: RenderOutput, target_rgb: Tensor, target_depth: Tensor, cfg: LossConfig,
                   truncation: float, sdf_terms: bool = True, behind: Tensor | None = None) -> dict[str, Tensor]:
    """All loss terms of a batch of rendered rays (see module docstring for the equations).

    Args:
        out: `render_rays` output (uses rgb, depth, sdf, z).
        target_rgb: (R, 3) in [0, 1]; target_depth: (R,) metres, 0 = none.
        cfg: weights, masks, reduction; truncation: T, metres.
        sdf_terms: compute the SDF terms (free_space, center, tail). False for renderers that are not SDF-based
            (`renderer.sdf_based`): those terms are then zero tensors (no gradient) and excluded from 'total'.
        behind: (R,) per-ray end of the SDF band behind the depth, units of T (None: `cfg.behind` for every ray).
    Returns:
        dict with scalar tensors 'color', 'depth', 'free_space', 'center', 'tail' (unweighted) and 'total'
        (weighted sum).
    """
    reduction = LossReduction(cfg.reduction)
    valid = target_depth > 0
    color = safe_mean((out.rgb - target_rgb) ** 2)
    depth = safe_mean((out.depth - target_depth) ** 2, valid)
    terms = {"color": color, "depth": depth}
    if sdf_terms:
        front, center, tail = sdf_masks(out.z, target_depth, truncation, cfg.center_band,
                                        cfg.behind if behind is None else behind)
        fs_err = (out.sdf - cfg.free_space_target) ** 2
        sdf_err = (out.z + out.sdf * truncation - target_depth[:, None]) ** 2
        terms["free_space"] = masked_sample_mean(fs_err, front, reduction)
        terms["center"] = masked_sample_mean(sdf_err, center, reduction)
        terms["tail"] = masked_sample_mean(sdf_err, tail, reduction)
    else:
        zero = out.sdf.new_zeros(())
        terms.update(free_space=zero, center=zero.clone(), tail=zero.clone())
    terms["total"] = weighted_total(terms, cfg, sdf_terms)
    return terms


def weighted_total(terms: dict[str, Tensor], cfg: LossConfig, sdf_terms: bool) -> Tensor:
    """L = λ_p L_p + λ_g L_g (+ λ_fs L_fs + λ_c L_c + λ_t L_t when `sdf_terms`), the module docstring's total."""
    total = cfg.color * terms["color"] + cfg.depth * terms["depth"]
    if sdf_terms:
        total = (total + cfg.free_space * terms["free_space"] + cfg.center * terms["center"]
                 + cfg.tail * terms["tail"])
    return total


def render_losses(field: Callable[[Tensor], Any], renderer, origins: Tensor, dirs: Tensor, z: Tensor,
                  target_rgb: Tensor, target_depth: Tensor, cfg: LossConfig, truncation: float,
                  behind: Tensor | None = None) -> tuple[dict[str, Tensor], RenderOutput]:
    """Render rays (`render_rays`) and their loss terms (`compute_losses`, SDF terms when `renderer.sdf_based`).

    `cfg.kernel`: torch composites and takes the losses in autograd (the reference); numba (CPU float32 / float64)
    runs both as one fused kernel each way (`fused_losses`: same terms, float rounding apart); auto picks numba
    where it can. Either fused choice runs the reference when z or the targets require a gradient. The fused
    path's RenderOutput holds its composites without gradient (callers only log them).
    Arguments and returns as `render_rays` and `compute_losses`.
    """
    sdf_terms = bool(getattr(renderer, "sdf_based", True))
    sdf, rgb, weights, normals = render_samples(field, renderer, origins, dirs, z, truncation)
    args = (weights, rgb, z, sdf, target_rgb, target_depth)
    kernel, fusable = KernelChoice(cfg.kernel), cpu_floats(*args)
    if kernel is KernelChoice.NUMBA and not fusable:
        raise ValueError("loss.kernel 'numba' needs CPU float32/float64 tensors of one dtype; use 'auto' or 'torch'")
    if kernel is KernelChoice.TORCH or not fusable or z.requires_grad or target_rgb.requires_grad \
            or target_depth.requires_grad:  # the kernel differentiates weights, colours and SDF only
        out = RenderOutput(*composite(weights, rgb, z), weights, sdf, z, normals)
        return compute_losses(out, target_rgb, target_depth, cfg, truncation, sdf_terms, behind), out
    terms, comp = composite_losses(*args, truncation, cfg.center_band, cfg.free_space_target,
                                   LossReduction(cfg.reduction) is LossReduction.PER_RAY, sdf_terms,
                                   cfg.behind if behind is None else behind)
    if not sdf_terms:  # as `compute_losses`: zeros without gradient, left out of the total
        terms.update({k: terms[k].detach() for k in ("free_space", "center", "tail")})
    terms["total"] = weighted_total(terms, cfg, sdf_terms)
    out = RenderOutput(comp[:, :3], comp[:, 3], comp[:, 4], comp[:, 5], weights, sdf, z, normals)
    return terms, out


def depth_l1(depth: Tensor, target_depth: Tensor) -> Tensor:
    """Mean |D̂ - D| over rays with D > 0 (metres; 0 if none) — the logged 'Depth L1' (docs/spec.md §6, §8.2)."""
    return safe_mean((depth - target_depth).abs(), target_depth > 0)


def psnr_from_mse(mse: Tensor | float) -> Tensor | float:
    """PSNR = -10 log10(MSE) in dB for images in [0, 1] (MSE clamped to >= 1e-10)."""
    if isinstance(mse, Tensor):
        return -10.0 * torch.log10(mse.clamp_min(1e-10))
    return -10.0 * math.log10(max(float(mse), 1e-10))
