"""Fused EHE compositing and loss for CPU tensors (docs/ehe.md §3-4).

In autograd the per-sample work after the field query (SDF(direct) weights over the packed samples, their per-ray
normalisation, the depth and colour composites, the L1 terms and the balanced free-space / SDF terms) is some
twenty element-wise and gather / scatter operations on (N,) tensors forward and as many backward, more time than
the two lookups. Here one numba kernel per direction walks each ray's samples once; its gradient is written out
below. The reference is the torch path, `render_samples` then `ehe_losses` (tests compare values and gradients).

Per ray (samples i in ray order, s_i SDF in T-units, x_i = s_i / T, σ the logistic function):
    b_i = σ(x_i) σ(−x_i),  m_i = 1[z_i < z_k + T] (k: first sign change; all i without one),  B = Σ b_i m_i
    w_i = b_i m_i / (B + 1e-8),  D̂ = Σ w_i z_i,  Ĉ = Σ_{i ∈ used} w_i c_i,  c_i = σ(logit_i)
Backward, with g_w_i = ∂L/∂w_i = g_D z_i + [i ∈ used] Σ_ch g_C,ch c_i,ch:
    ∂L/∂s_i = m_i / (B + 1e-8) · (g_w_i − Σ_j g_w_j w_j) · b_i (1 − 2σ(x_i)) / T  + the free-space / SDF terms'
    ∂L/∂c_i = g_C w_i
The bells b_i and their slopes, and the colours' sigmoid, are computed vectorised in torch (one exp per sample
each) and handed to the kernels, which then do no transcendental work.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

# the weights' normaliser B + _EPS, as `packed_direct_weights`. Sums are per ray and added over rays in a fixed
# order afterwards, so results do not depend on the thread count.
_EPS = 1e-8


@njit(inline="always", cache=True)
def _first_cut(s, z, a, e, T):  # pragma: no cover - numba
    """z_k + T of the first sign change among samples a..e-1 (inf when there is none)."""
    for i in range(a, e - 1):
        if (s[i] > 0.0) != (s[i + 1] > 0.0):
            return z[i] + T
    return np.inf


@njit(parallel=True, cache=True)
def _weights(s, z, b, start, T, w):  # pragma: no cover - numba
    """Normalised SDF(direct) weights w (N,) of packed samples from their bells b (N,)."""
    for r in prange(start.shape[0] - 1):
        a, e = start[r], start[r + 1]
        cut = _first_cut(s, z, a, e, T)
        tot = 0.0
        for i in range(a, e):
            if z[i] < cut:
                tot += b[i]
        for i in range(a, e):
            w[i] = b[i] / (tot + _EPS) if z[i] < cut else 0.0


@njit(inline="always", cache=True)
def _composite(z, b, crow, c, a, e, cut):  # pragma: no cover - numba
    """One ray's (B + _EPS, D̂, Ĉ_0, Ĉ_1, Ĉ_2) from its samples a..e-1, kept where z < cut."""
    tot = 0.0
    for i in range(a, e):
        if z[i] < cut:
            tot += b[i]
    den = tot + _EPS
    dep = 0.0
    c0 = 0.0
    c1 = 0.0
    c2 = 0.0
    for i in range(a, e):
        if z[i] < cut:
            wi = b[i] / den
            dep += wi * z[i]
            q = crow[i]
            if q >= 0:
                c0 += wi * c[q, 0]
                c1 += wi * c[q, 1]
                c2 += wi * c[q, 2]
    return den, dep, c0, c1, c2


@njit(parallel=True, cache=True)
def _forward(s, z, b, start, crow, c, C, D, has_d, T, ray_terms, sample_terms):  # pragma: no cover - numba
    """Per ray: Σ_ch |Ĉ − C|, Σ_ch (Ĉ − C)², |D̂ − D| into ray_terms (R, 3); the free-space and SDF terms' sums of
    squares and the counts of front, band and supervised samples into sample_terms (R, 5)."""
    for r in prange(start.shape[0] - 1):
        a, e = start[r], start[r + 1]
        cut = _first_cut(s, z, a, e, T)
        den, dep, c0, c1, c2 = _composite(z, b, crow, c, a, e, cut)
        fs = 0.0
        sd = 0.0
        n_f = 0
        n_b = 0
        if has_d[r]:
            for i in range(a, e):
                if z[i] < D[r] - T:
                    fs += (s[i] - 1.0) ** 2
                    n_f += 1
                elif abs(z[i] - D[r]) <= T:
                    sd += (z[i] + s[i] * T - D[r]) ** 2
                    n_b += 1
        if e > a:
            d0, d1, d2 = c0 - C[r, 0], c1 - C[r, 1], c2 - C[r, 2]
            ray_terms[r, 0] = abs(d0) + abs(d1) + abs(d2)
            ray_terms[r, 1] = d0 * d0 + d1 * d1 + d2 * d2
            if has_d[r]:
                ray_terms[r, 2] = abs(dep - D[r])
        sample_terms[r, 0] = fs
        sample_terms[r, 1] = sd
        sample_terms[r, 2] = n_f
        sample_terms[r, 3] = n_b
        sample_terms[r, 4] = (e - a) if has_d[r] else 0


@njit(inline="always", cache=True)
def _sign(v):  # pragma: no cover - numba
    return 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)


@njit(parallel=True, cache=True)
def _backward(s, z, b, start, crow, c, C, D, has_d, T, slope, g_rgb, g_depth, g_fs, g_sd, gs, gc
              ):  # pragma: no cover - numba
    """gs (N,) and gc (M, 3) (gradient of the used samples' colours) for the upstream gradients of the mean terms
    (divided by their normalisers: g_rgb per |Ĉ − C| element, g_depth per ray, g_fs / g_sd per summed square);
    slope (N,) = 1 − 2σ(s/T)."""
    for r in prange(start.shape[0] - 1):
        a, e = start[r], start[r + 1]
        if e == a:
            continue
        cut = _first_cut(s, z, a, e, T)
        den, dep, c0, c1, c2 = _composite(z, b, crow, c, a, e, cut)
        gD = g_depth * _sign(dep - D[r]) if has_d[r] else 0.0
        gC0 = g_rgb * _sign(c0 - C[r, 0])
        gC1 = g_rgb * _sign(c1 - C[r, 1])
        gC2 = g_rgb * _sign(c2 - C[r, 2])
        dot = 0.0  # Σ_j g_w_j w_j
        for i in range(a, e):
            if z[i] < cut:
                gw = gD * z[i]
                q = crow[i]
                if q >= 0:
                    gw += gC0 * c[q, 0] + gC1 * c[q, 1] + gC2 * c[q, 2]
                dot += gw * b[i] / den
        for i in range(a, e):
            g = 0.0
            if z[i] < cut:
                wi = b[i] / den
                gw = gD * z[i]
                q = crow[i]
                if q >= 0:
                    gw += gC0 * c[q, 0] + gC1 * c[q, 1] + gC2 * c[q, 2]
                    gc[q, 0] = gC0 * wi
                    gc[q, 1] = gC1 * wi
                    gc[q, 2] = gC2 * wi
                g = (gw - dot) / den * b[i] * slope[i] / T
            if has_d[r]:
                if z[i] < D[r] - T:
                    g += g_fs * 2.0 * (s[i] - 1.0)
                elif abs(z[i] - D[r]) <= T:
                    g += g_sd * 2.0 * (z[i] + s[i] * T - D[r]) * T
            gs[i] = g


def bells(sdf: Tensor, truncation: float) -> tuple[Tensor, Tensor]:
    """(σ(x)σ(−x), 1 − 2σ(x)) at x = s / T of the detached sdf (N,): the bell `bell_weights` and its slope
    (d bell / dx = bell · slope), vectorised in torch."""
    x = sdf.detach() / truncation
    return torch.sigmoid(x) * torch.sigmoid(-x), -torch.tanh(0.5 * x)


def fused_weights(sdf: Tensor, z: Tensor, start: Tensor, truncation: float, bell: Tensor | None = None) -> Tensor:
    """`packed_direct_weights` without gradient, (N,) (numba), from the bells (`bells`, computed if not given)."""
    b = bells(sdf, truncation)[0] if bell is None else bell
    w = np.empty(sdf.shape[0], dtype=b.numpy().dtype)
    _weights(sdf.detach().numpy(), z.numpy(), b.numpy(), start.numpy(), float(truncation), w)
    return torch.from_numpy(w)


class EheLossFn(torch.autograd.Function):
    """(sdf (N,), colours (M, 3) of the used samples) -> (4,) [L_rgb, L_depth, L_fs, L_sdf] and, without
    gradient, the colour MSE; see `fused_losses`."""

    @staticmethod
    def forward(ctx, sdf, colors, z, start, crow, rgb, depth, has_d, truncation, bell, slope):
        dt = sdf.dtype
        arrays = (sdf.detach().numpy(), z.to(dt).numpy(), bell.to(dt).numpy(), start.numpy(), crow.numpy(),
                  colors.detach().to(dt).contiguous().numpy(), rgb.to(dt).contiguous().numpy(),
                  depth.to(dt).numpy(), has_d.numpy(), float(truncation))
        R = start.shape[0] - 1
        ray_terms = np.zeros((R, 3))
        sample_terms = np.zeros((R, 5))
        _forward(*arrays, ray_terms, sample_terms)
        rt, st = ray_terms.sum(axis=0), sample_terms.sum(axis=0)  # numpy pairwise sums over rays, fixed order
        n_hit, n_d = int((start[1:] > start[:-1]).sum()), int(has_d.sum())
        n_f, n_b, n = int(st[2]), int(st[3]), int(st[4])
        fs_coef, sd_coef = (1.0 - n_f / (n_f + n_b), 1.0 - n_b / (n_f + n_b)) if n_f + n_b else (0.0, 0.0)
        norms = (3 * n_hit, n_d, n / fs_coef if fs_coef else 0, n / sd_coef if sd_coef else 0)  # 0: term off
        terms = torch.tensor([v / k if k else 0.0 for v, k in zip((rt[0], rt[2], st[0], st[1]), norms)], dtype=dt)
        mse = torch.tensor(rt[1] / (3 * n_hit) if n_hit else 0.0, dtype=dt)
        ctx.mark_non_differentiable(mse)
        ctx.arrays, ctx.norms, ctx.slope, ctx.dtypes = arrays, norms, slope.to(dt).numpy(), (dt, colors.dtype)
        ctx.m = colors.shape[0]
        return terms, mse

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_terms, g_mse):
        g = [v / k if k else 0.0 for v, k in zip(g_terms.double().tolist(), ctx.norms)]
        arrays = ctx.arrays
        gs = np.zeros(arrays[0].shape[0], dtype=arrays[0].dtype)
        gc = np.zeros((ctx.m, 3), dtype=arrays[0].dtype)
        _backward(*arrays, ctx.slope, *g, gs, gc)
        return (torch.from_numpy(gs), torch.from_numpy(gc).to(ctx.dtypes[1]), None, None, None, None, None, None,
                None, None, None)


def fused_losses(sdf: Tensor, colors: Tensor, z: Tensor, start: Tensor, crow: Tensor, rgb: Tensor, depth: Tensor,
                 has_d: Tensor, truncation: float, bell: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """EHE loss terms of packed samples in one fused pass (CPU).

    Args: sdf (N,) T-units; colors (M, 3) in [0, 1] of the samples used for colour; z (N,) metres; start (R + 1,)
        offsets of each ray's samples (`PackedSamples.start`); crow (N,) int64 the colors row of each sample (−1:
        not used for colour); rgb (R, 3), depth (R,) metres observed; has_d (R,) bool: the ray's depth is
        supervised (it has samples and depth inside the range); bell: `bells(sdf, truncation)` if already computed.
    Returns: (4,) [L_rgb, L_depth, L_fs, L_sdf] as `ehe_losses`, and the colour MSE (no gradient).
    """
    b, slope = bells(sdf, truncation) if bell is None else bell
    return EheLossFn.apply(sdf, colors, z, start, crow, rgb, depth, has_d, truncation, b, slope)
