"""Stateless rendering maths (nerfacc style): SDF / density -> alphas -> weights.

Conventions: R rays, S samples per ray sorted by z; `z` is the ray parameter of the unnormalised camera-z-1
direction d, i.e. the z-depth (metres); a metric length along the ray is Δz·|d|. SDF values `s` from fields are in
truncation units (metric SDF = s·T). Every function is device- and dtype-agnostic and differentiable in its float
inputs.
"""

from __future__ import annotations

import torch
from torch import Tensor

# ---------------------------------------------------------------------------------------------------------------
# Intervals and transmittance
# ---------------------------------------------------------------------------------------------------------------


def section_bounds(z: Tensor) -> tuple[Tensor, Tensor]:
    """Partition [z_0, z_{S-1}] into one section per sample, split at the mid-points between samples.

    Section i is [b_i, b_{i+1}] with b_0 = z_0, b_i = (z_{i-1} + z_i)/2, b_S = z_{S-1}. Treating each sample as the
    value of its section is the mid-point quadrature rule (second order), unlike the left-rectangle rule
    δ_i = z_{i+1} - z_i, which shifts rendered depth by half a sample spacing.

    Args:
        z: (R, S) sorted sample z-depths, metres.
    Returns:
        starts, ends: (R, S) z-depths of the section bounds (ends - starts >= 0, sums to z_{S-1} - z_0).

    Example: z = [0, 1, 3] -> starts [0, 0.5, 2], ends [0.5, 2, 3].
    """
    mid = 0.5 * (z[..., 1:] + z[..., :-1])
    starts = torch.cat([z[..., :1], mid], dim=-1)
    ends = torch.cat([mid, z[..., -1:]], dim=-1)
    return starts, ends


def transmittance_from_alpha(alpha: Tensor, eps: float = 1e-10) -> Tensor:
    """Exclusive transmittance T_i = Π_{j<i} (1 - α_j + eps).

    Args:
        alpha: (R, S) per-sample opacity in [0, 1].
    Returns:
        (R, S) transmittance, T_0 = 1.
    """
    shifted = torch.cat([torch.ones_like(alpha[..., :1]), 1.0 - alpha[..., :-1] + eps], dim=-1)
    return torch.cumprod(shifted, dim=-1)


def weights_from_alpha(alpha: Tensor, eps: float = 1e-10) -> Tensor:
    """Volume-rendering weights w_i = α_i Π_{j<i}(1 - α_j) (Max 1995; NeRF, Mildenhall et al. 2020).

    Args:
        alpha: (R, S) opacity in [0, 1].
    Returns:
        (R, S) weights >= 0 with Σ_i w_i <= 1.

    Example: α = [0.5, 0.5, 1] -> w = [0.5, 0.25, 0.25].
    """
    return alpha * transmittance_from_alpha(alpha, eps)


def weights_from_optical_depth(tau: Tensor) -> Tensor:
    """Weights from per-sample optical depths τ_i = σ_i δ_i: w_i = (1 - e^{-τ_i}) exp(-Σ_{j<i} τ_j).

    Same as `weights_from_alpha(1 - exp(-τ))` but computed with a cumulative sum (stable gradients for opaque rays).

    Args:
        tau: (R, S) optical depth >= 0 (dimensionless).
    Returns:
        (R, S) weights, Σ w <= 1.
    """
    excl = torch.cumsum(tau, dim=-1) - tau
    return -torch.expm1(-tau) * torch.exp(-excl)


# ---------------------------------------------------------------------------------------------------------------
# SDF(direct): bell-shaped weights (Azinović et al. CVPR 2022, Neural RGB-D; Co-SLAM, Wang et al. CVPR 2023)
# ---------------------------------------------------------------------------------------------------------------


def bell_weights(sdf: Tensor, truncation: float) -> Tensor:
    """Unnormalised bell ŵ_i = σ(s_i/T) σ(-s_i/T) (docs/spec.md §4.1).

    With s in T-units this is σ(d/T²)σ(-d/T²) in metric SDF d: peak 0.25 at the zero crossing, half maximum at
    |d| ≈ 1.76 T² (1.8 cm for T = 0.1 m), exactly the reference / Co-SLAM form.

    Args:
        sdf: (R, S) SDF, T-units.
        truncation: T, metres (used numerically as in the reference).
    Returns:
        (R, S) values in (0, 0.25].
    """
    x = sdf / truncation
    return torch.sigmoid(x) * torch.sigmoid(-x)


def first_surface_mask(sdf: Tensor, z: Tensor, truncation: float, no_crossing_keeps_all: bool = True) -> Tensor:
    """Mask m_i = 1[z_i < z_k + T] keeping samples up to T behind the first zero crossing (docs/spec.md §4.1).

    k is the first index whose sign differs from the next sample's (0 counts as inside, so a sample exactly on the
    surface closes a crossing). Rays without a crossing keep every sample (fix of docs/spec.md §13.7); with
    `no_crossing_keeps_all=False` they use k = 0 like the reference code.

    Args:
        sdf: (R, S) SDF, any units (only signs matter).
        z: (R, S) sorted z-depths, metres.
        truncation: T, metres of z.
    Returns:
        (R, S) bool mask.
    """
    pos = sdf > 0
    change = pos[..., :-1] != pos[..., 1:]
    k = torch.argmax(change.to(torch.uint8), dim=-1, keepdim=True)  # first True (0 if none)
    z_k = torch.gather(z, -1, k)
    mask = z < z_k + truncation
    if no_crossing_keeps_all:
        mask = mask | ~change.any(dim=-1, keepdim=True)
    return mask


def direct_weights(sdf: Tensor, z: Tensor, truncation: float, no_crossing_keeps_all: bool = True) -> Tensor:
    """SDF(direct) weights w_i = ŵ_i m_i / (Σ_j ŵ_j m_j + 1e-8), ŵ and m as above (docs/spec.md §4.1; Azinović et al.
    2022).

    Args:
        sdf: (R, S) T-units; z: (R, S) metres; truncation: T metres.
    Returns:
        (R, S) weights, Σ_i w_i = 1 up to the 1e-8, i.e. while Σ_j ŵ_j m_j >> 1e-8; a ray whose every |s| is
        above ~2 T-units has Σ w < 1 and renders towards black at depth 0 (s = 2: 0.93, s = 3: 6e-4).
    """
    mask = first_surface_mask(sdf.detach(), z, truncation, no_crossing_keeps_all)
    w = bell_weights(sdf, truncation) * mask
    return w / (w.sum(dim=-1, keepdim=True) + 1e-8)


# ---------------------------------------------------------------------------------------------------------------
# SDF(density): StyleSDF (Or-El et al. CVPR 2022) as used by ESLAM (Johari et al. CVPR 2023)
# ---------------------------------------------------------------------------------------------------------------


def density_optical_depth(sdf: Tensor, beta: Tensor | float) -> Tensor:
    """τ_i = β σ(-β s_i) so that α_i = 1 - exp(-τ_i) = 1 - exp(-β σ(-β s_i)) (docs/spec.md §4.2; no spacing δ enters).

    Args:
        sdf: (R, S) SDF, T-units.
        beta: sharpness, 1/T-units (10 in the paper: a ~1 cm falloff for T = 0.1 m).
    Returns:
        (R, S) optical depth in [0, β].

    Example: β = 10, s = 0 -> τ = 5, α = 0.9933.
    """
    return beta * torch.sigmoid(-beta * sdf)


# ---------------------------------------------------------------------------------------------------------------
# NeuS (Wang et al. NeurIPS 2021)
# ---------------------------------------------------------------------------------------------------------------


def neus_annealed_cos(cos: Tensor, anneal: float) -> Tensor:
    """NeuS cosine annealing ĉ = -[ReLU(-cos/2 + 1/2)(1 - a) + ReLU(-cos) a], a in [0, 1] (always <= 0).

    a = 1 is the true (clamped) cosine: only surfaces seen from outside produce opacity.
    """
    return -(torch.relu(-0.5 * cos + 0.5) * (1.0 - anneal) + torch.relu(-cos) * anneal)


def neus_alpha(sdf_prev: Tensor, sdf_next: Tensor, inv_s: Tensor | float) -> Tensor:
    """Discrete NeuS opacity α_i = clip((Φ_s(f_prev) - Φ_s(f_next)) / (Φ_s(f_prev) + 1e-5), 0, 1), Φ_s(x) = σ(x·s).

    Eq. (13) of NeuS: the exact opacity of a section whose SDF goes linearly from f_prev to f_next.

    Args:
        sdf_prev, sdf_next: (R, S) SDF at the section start / end (same unit as 1/inv_s).
        inv_s: inverse standard deviation s of the logistic density.
    Returns:
        (R, S) α in [0, 1].
    """
    cdf_prev = torch.sigmoid(sdf_prev * inv_s)
    cdf_next = torch.sigmoid(sdf_next * inv_s)
    return ((cdf_prev - cdf_next) / (cdf_prev + 1e-5)).clamp(0.0, 1.0)


def ray_slope(sdf: Tensor, z: Tensor, ray_norm: Tensor, min_step: float = 1e-6) -> Tensor:
    """Directional derivative of the SDF along the unit ray from the samples themselves (no field query).

    c_i = (f_{i+1} - f_{i-1}) / ((z_{i+1} - z_{i-1}) |d|) inside, one-sided (f_1 - f_0) / ((z_1 - z_0)|d|) and
    (f_{S-1} - f_{S-2}) / ((z_{S-1} - z_{S-2})|d|) at the ends: the slope NeuS's own up-sampling takes from
    consecutive samples (Wang et al. NeurIPS 2021, `up_sample`), here centred on the sample. Exact for an SDF that is
    linear along the ray (a plane); first-order in the field (no second derivatives), so cheap.

    Args:
        sdf: (R, S) metric SDF f at the samples, metres.
        z: (R, S) sorted sample z-depths, metres; at least 2 samples.
        ray_norm: (R, 1) |d| (metres of ray per metre of z).
        min_step: lower bound of the metric step in the denominator, metres (coincident samples).
    Returns:
        (R, S) slope ⟨d/|d|, ∇f⟩ estimate, dimensionless (-1 when walking straight into a plane).

    Example: f = [0.3, 0.1, -0.1], z = [0, 0.2, 0.4], |d| = 1 -> c = [-1, -1, -1].
    """
    if z.shape[-1] < 2:
        raise ValueError(f"ray_slope needs at least 2 samples per ray, got {z.shape[-1]}")
    fp = torch.cat([sdf[..., 1:2], sdf[..., 2:], sdf[..., -1:]], dim=-1)
    fm = torch.cat([sdf[..., :1], sdf[..., :-2], sdf[..., -2:-1]], dim=-1)
    zp = torch.cat([z[..., 1:2], z[..., 2:], z[..., -1:]], dim=-1)
    zm = torch.cat([z[..., :1], z[..., :-2], z[..., -2:-1]], dim=-1)
    return (fp - fm) / ((zp - zm) * ray_norm).clamp_min(min_step)


def neus_section_sdf(sdf: Tensor, slope: Tensor, z: Tensor, starts: Tensor, ends: Tensor, ray_norm: Tensor
                     ) -> tuple[Tensor, Tensor]:
    """First-order SDF estimates at the section bounds: f(b) = f_i + slope_i (b - z_i) |d|.

    Args:
        sdf: (R, S) metric SDF at the samples, metres.
        slope: (R, S) annealed directional derivative ĉ_i = ⟨d/|d|, ∇f⟩ (<= 0), dimensionless.
        z, starts, ends: (R, S) z-depths of samples and section bounds, metres.
        ray_norm: (R, 1) |d| (metres of ray per metre of z).
    Returns:
        sdf_prev, sdf_next: (R, S) metres.
    """
    return sdf + slope * (starts - z) * ray_norm, sdf + slope * (ends - z) * ray_norm


# ---------------------------------------------------------------------------------------------------------------
# VolSDF (Yariv et al. NeurIPS 2021)
# ---------------------------------------------------------------------------------------------------------------


def volsdf_density(sdf_metric: Tensor, beta: Tensor | float) -> Tensor:
    """σ(x) = α Ψ_β(-d(x)) with α = 1/β and Ψ_β the CDF of the zero-mean Laplace distribution of scale β (Eq. 2-3).

    Ψ_β(-d) = ½ exp(-d/β) for d >= 0 (outside), 1 - ½ exp(d/β) for d < 0 (inside). Both branches are evaluated on
    clamped inputs so neither overflows nor produces NaN gradients.

    Args:
        sdf_metric: (R, S) metric SDF d, metres.
        beta: Laplace scale β, metres.
    Returns:
        (R, S) density, 1/m, in (0, 1/β).
    """
    outside = 0.5 * torch.exp(-sdf_metric.clamp_min(0.0) / beta)
    inside = 1.0 - 0.5 * torch.exp(sdf_metric.clamp_max(0.0) / beta)
    return torch.where(sdf_metric >= 0, outside, inside) / beta
