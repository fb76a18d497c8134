"""Fused weights of G for CPU tensors: SDF(density) and SDF(direct) (`render.kernel`; docs/speed.md).

The references are `functional.weights_from_optical_depth(density_optical_depth(s, β))` and
`functional.direct_weights`: about ten element-wise, cumulative and reduction operations on (R, S) tensors each way
in autograd, each saving its operands for the backward. Here the element-wise sigmoids and exponentials run once,
vectorised in torch without a graph, and the per-ray scans (transmittance, first-surface mask, normalisation) and the
whole backward in one numba pass each; the tests compare values and gradients (float64 gradcheck).

Per ray (samples i; s SDF in T-units; z metres; g = ∂L/∂w):
    density: τ_i = β σ(-β s_i),  w_i = (1 - e^{-τ_i}) e^{-E_i},  E_i = Σ_{j<i} τ_j  (e^{-E_i} as a running product);
             ∂L/∂τ_i = g_i e^{-E_{i+1}} - Σ_{j>i} g_j w_j,  ∂τ_i/∂s_i = -β² σ(1-σ),  ∂τ_i/∂β = σ - β s_i σ(1-σ)
    direct:  u_i = σ(x_i) σ(-x_i) m_i with x_i = s_i / T,  w_i = u_i / (Σ_j u_j + 1e-8),  m_i = 1[z_i < z_k + T]
             (k the first sign change; every sample kept on a ray without one, or k = 0 with `keeps_all` off);
             ∂L/∂u_i = (g_i - Σ_j g_j w_j) / (Σ_j u_j + 1e-8),  ∂u_i/∂s_i = m_i σ(x_i)σ(-x_i)(σ(-x_i) - σ(x_i)) / T
Subnormal SDF gradients (samples far behind the surface) are written as zero, and so is a subnormal transmittance
(`fields.kernels.subnormal`). β's gradient is summed per ray, then over the rays in a fixed order.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from inrslam.fields.kernels.subnormal import flushed, tiny_of


@njit(parallel=True, cache=True)
def _density_forward(em, one, tiny, w, trans):  # pragma: no cover - numba
    """w (R, S) from em = expm1(-τ) (R, S); trans (R, S) <- e^{-E_{i+1}}, the transmittance after each sample, 0
    once it is subnormal (the weights behind are then below the smallest normal number too)."""
    R, S = em.shape
    for r in prange(R):
        tr = one
        for i in range(S):
            w[r, i] = -em[r, i] * tr
            tr = tr * (one + em[r, i])
            if tr < tiny:
                tr = tr * 0
            trans[r, i] = tr


@njit(parallel=True, cache=True)
def _density_backward(s, sig, beta, one, w, trans, gw, need_beta, tiny, gs, gbeta):  # pragma: no cover - numba
    """gs (R, S) and gbeta (R,) per-ray parts from σ(-β s) (sig) and the forward's w and trans."""
    R, S = s.shape
    for r in prange(R):
        suffix = one - one
        gb = one - one
        for i in range(S - 1, -1, -1):
            g_tau = gw[r, i] * trans[r, i] - suffix
            suffix += gw[r, i] * w[r, i]
            d = sig[r, i] * (one - sig[r, i])
            gs[r, i] = flushed(-beta * beta * d * g_tau, tiny)
            if need_beta:
                gb += g_tau * (sig[r, i] - beta * s[r, i] * d)
        gbeta[r] = gb


@njit(inline="always", cache=True)
def _first_change(s, r, keeps_all):  # pragma: no cover - numba
    """The first i with (s_i > 0) != (s_{i+1} > 0) on ray r; without one -1 with `keeps_all` (every sample kept),
    else 0."""
    for i in range(s.shape[1] - 1):
        if (s[r, i] > 0) != (s[r, i + 1] > 0):
            return i
    return -1 if keeps_all else 0


@njit(parallel=True, cache=True)
def _direct_forward(s, z, bell, T, eps, keeps_all, w, first, total):  # pragma: no cover - numba
    """w (R, S) from the bells σ(x)σ(-x) (R, S); first (R,) <- k (-1: every sample), total (R,) <- Σ u + eps."""
    R, S = s.shape
    for r in prange(R):
        k = _first_change(s, r, keeps_all)
        first[r] = k
        tot = eps - eps
        for i in range(S):
            u = tot - tot
            if k < 0 or z[r, i] < z[r, k] + T:
                u = bell[r, i]
            w[r, i] = u
            tot += u
        tot += eps
        total[r] = tot
        for i in range(S):
            w[r, i] = w[r, i] / tot


@njit(parallel=True, cache=True)
def _direct_backward(z, sp, sm, T, w, first, total, gw, tiny, gs):  # pragma: no cover - numba
    R, S = z.shape
    for r in prange(R):
        k = first[r]
        dot = T - T
        for i in range(S):
            dot += gw[r, i] * w[r, i]
        for i in range(S):
            g = T - T
            if k < 0 or z[r, i] < z[r, k] + T:
                g = (gw[r, i] - dot) / total[r] * (sp[r, i] * sm[r, i] * (sm[r, i] - sp[r, i])) / T
            gs[r, i] = flushed(g, tiny)


class DensityWeightsFn(torch.autograd.Function):
    """SDF(density) weights (R, S) from sdf (R, S) and β (0-d); differentiable (once) in both. The element-wise
    transcendentals run vectorised in torch (as the reference's), the scans in numba."""

    @staticmethod
    def forward(ctx, sdf, beta):
        s = sdf.detach().contiguous()
        b = beta.detach().to(s.dtype)
        sig = torch.sigmoid(-b * s)
        em = torch.expm1(-(b * sig))
        w, trans = torch.empty_like(s), torch.empty_like(s)
        dt = s.numpy().dtype
        _density_forward(em.numpy(), dt.type(1.0), dt.type(tiny_of(dt)), w.numpy(), trans.numpy())
        ctx.save_for_backward(s, sig, w, trans)
        ctx.beta, ctx.beta_dtype = float(b), beta.dtype
        return w

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_w):
        s, sig, w, trans = ctx.saved_tensors
        need_s, need_beta = ctx.needs_input_grad[:2]
        sn = s.numpy()
        dt = sn.dtype
        gs = np.empty_like(sn)
        gbeta = np.zeros(sn.shape[0], dtype=dt)
        gw = g_w.detach().to(s.dtype).contiguous().numpy()
        _density_backward(sn, sig.numpy(), dt.type(ctx.beta), dt.type(1.0), w.numpy(), trans.numpy(), gw, need_beta,
                          tiny_of(dt), gs, gbeta)
        g_beta = torch.tensor(float(gbeta.astype(np.float64).sum()), dtype=ctx.beta_dtype) if need_beta else None
        return (torch.from_numpy(gs) if need_s else None), g_beta


class DirectWeightsFn(torch.autograd.Function):
    """SDF(direct) weights (R, S) from sdf (R, S) and z (R, S); differentiable (once) in sdf. The sigmoids run
    vectorised in torch (as the reference's), the first-surface mask and the normalisation in numba."""

    @staticmethod
    def forward(ctx, sdf, z, truncation, keeps_all):
        s = sdf.detach().contiguous()
        zz = z.detach().to(s.dtype).contiguous()
        x = s / truncation
        sp, sm = torch.sigmoid(x), torch.sigmoid(-x)
        bell = sp * sm
        dt = s.numpy().dtype.type
        R = s.shape[0]
        w = torch.empty_like(s)
        first, total = np.empty(R, dtype=np.int64), np.empty(R, dtype=s.numpy().dtype)
        _direct_forward(s.numpy(), zz.numpy(), bell.numpy(), dt(truncation), dt(1e-8), bool(keeps_all), w.numpy(),
                        first, total)
        ctx.save_for_backward(zz, sp, sm, w)
        ctx.T, ctx.first, ctx.total = dt(truncation), first, total
        return w

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_w):
        z, sp, sm, w = ctx.saved_tensors
        if not ctx.needs_input_grad[0]:
            return None, None, None, None
        gs = np.empty(tuple(w.shape), dtype=ctx.total.dtype)
        gw = g_w.detach().to(w.dtype).contiguous().numpy()
        _direct_backward(z.numpy(), sp.numpy(), sm.numpy(), ctx.T, w.numpy(), ctx.first, ctx.total, gw,
                         tiny_of(gs.dtype), gs)
        return torch.from_numpy(gs), None, None, None


def density_weights_fused(sdf: Tensor, beta: Tensor | float) -> Tensor:
    """`weights_from_optical_depth(density_optical_depth(sdf, beta))` fused (CPU float32 / float64).

    Args:
        sdf: (R, S) T-units; beta: β > 0 in 1/T-units, a float or a 0-d tensor (differentiable).
    Returns:
        (R, S) weights, Σ w <= 1.
    """
    b = beta if isinstance(beta, Tensor) else torch.tensor(float(beta), dtype=sdf.dtype)
    return DensityWeightsFn.apply(sdf, b)


def direct_weights_fused(sdf: Tensor, z: Tensor, truncation: float, no_crossing_keeps_all: bool = True) -> Tensor:
    """`functional.direct_weights` fused (CPU float32 / float64): sdf (R, S) T-units, z (R, S) metres, T metres ->
    (R, S) weights (Σ w = 1 up to 1e-8); differentiable in sdf."""
    return DirectWeightsFn.apply(sdf, z, float(truncation), bool(no_crossing_keeps_all))
