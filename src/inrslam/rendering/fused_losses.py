"""Fused compositing + training losses for CPU tensors (`loss.kernel`; docs/speed.md).

After the fused lookups and decoders, most of what is left of a tracking or mapping iteration in autograd is the
per-sample work behind them: `composite` (four weighted sums) and `compute_losses` (the sample masks, the free-space
and SDF errors, masked means per ray), some thirty element-wise, where and reduction operations on (R, S) tensors
forward and as many backward. Here one numba pass per direction walks each ray's samples once; G's weights stay in
torch (any G), so this serves every rendering function. The reference is `composite` + `compute_losses`; the tests
compare values and gradients (float64 gradcheck).

Per ray r (samples i; w weights, c colours, z z-depths metres, s SDF in T-units; C, D the targets):
    Ĉ = Σ w_i c_i,  D̂ = Σ w_i z_i,  O = Σ w_i,  Var = Σ w_i (z_i − D̂)²
    colour = Σ_r,ch (Ĉ − C)² / (3R);  depth = Σ_{D>0} (D̂ − D)² / #(D>0)
    free-space / centre / tail: e² = (s − target)² or (z + sT − D)² over the masks of `losses.sdf_masks`, averaged
    per ray then over the rays having such samples (`per_ray`), or over all such samples (`global`).
Backward (g_X = ∂L/∂X of each term): ∂/∂w_i = Σ_ch ∂Ĉ_ch c_i,ch + ∂D̂ z_i, ∂/∂c_i = ∂Ĉ w_i, ∂/∂s_i = 2 e g / n
(n the term's divisor for that sample; the SDF errors carry a factor T). Per-ray sums are added over the rays in a
fixed order afterwards, so results do not depend on the thread count.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from inrslam.fields.kernels.subnormal import flushed, tiny_of

# indices of the per-ray partial sums
_COL, _DEP, _FS, _FS_N, _CE, _CE_N, _TA, _TA_N = range(8)
TERMS = ("color", "depth", "free_space", "center", "tail")


@njit(inline="always", cache=True)
def _masks(zi, d, valid, b, thr_front, thr_center, T):  # pragma: no cover - numba
    """(front, centre, tail) of one sample at z-depth zi on a ray with depth d (`losses.sdf_masks`)."""
    if not valid:
        return False, False, False
    diff = zi - d
    near = diff <= b
    center = abs(diff) < thr_center and near
    tail = abs(diff) <= T and not center and near
    return diff < thr_front, center, tail


@njit(parallel=True, cache=True)
def _forward(w, c, z, s, C, D, behind, thr_front, thr_center, T, fs_target, sdf_terms, comp, parts):  # pragma: no cover
    """Composites comp (R, 6: Ĉ, D̂, O, Var) and per-ray partial sums parts (R, 8) of every term."""
    R, S = w.shape
    for r in prange(R):
        c0 = 0.0
        c1 = 0.0
        c2 = 0.0
        dep = 0.0
        opa = 0.0
        for i in range(S):
            wi = w[r, i]
            c0 += wi * c[r, i, 0]
            c1 += wi * c[r, i, 1]
            c2 += wi * c[r, i, 2]
            dep += wi * z[r, i]
            opa += wi
        var = 0.0
        for i in range(S):
            var += w[r, i] * (z[r, i] - dep) ** 2
        comp[r, 0], comp[r, 1], comp[r, 2], comp[r, 3], comp[r, 4], comp[r, 5] = c0, c1, c2, dep, opa, var
        for k in range(8):
            parts[r, k] = 0.0
        parts[r, _COL] = (c0 - C[r, 0]) ** 2 + (c1 - C[r, 1]) ** 2 + (c2 - C[r, 2]) ** 2
        d = D[r]
        valid = d > 0
        if valid:
            parts[r, _DEP] = (dep - d) ** 2
        if sdf_terms and valid:
            b = behind[r]
            for i in range(S):
                front, center, tail = _masks(z[r, i], d, valid, b, thr_front, thr_center, T)
                if front:
                    parts[r, _FS] += (s[r, i] - fs_target) ** 2
                    parts[r, _FS_N] += 1.0
                elif center or tail:
                    e = z[r, i] + s[r, i] * T - d
                    k = _CE if center else _TA
                    parts[r, k] += e * e
                    parts[r, k + 1] += 1.0


def _scales(parts: np.ndarray, n_valid: int, per_ray: bool) -> tuple[np.ndarray, np.ndarray]:
    """The five terms (float64) and each SDF term's per-ray divisor scale (3, R): a sample's squared error counts
    scale[r] in its term (0 on rays without such samples)."""
    R = parts.shape[0]
    terms = np.zeros(5)
    terms[0] = parts[:, _COL].sum() / max(3 * R, 1)
    terms[1] = parts[:, _DEP].sum() / max(n_valid, 1)
    scale = np.zeros((3, R))
    for t, (k, kn) in enumerate(((_FS, _FS_N), (_CE, _CE_N), (_TA, _TA_N))):
        cnt = parts[:, kn]
        if per_ray:
            has = cnt > 0
            n_rays = max(int(has.sum()), 1)
            scale[t, has] = 1.0 / (cnt[has] * n_rays)
            terms[2 + t] = (parts[has, k] / cnt[has]).sum() / n_rays
        else:
            total = max(cnt.sum(), 1.0)
            scale[t] = 1.0 / total
            terms[2 + t] = parts[:, k].sum() / total
    return terms, scale


@njit(parallel=True, cache=True)
def _backward(w, c, z, s, C, D, behind, thr_front, thr_center, T, fs_target, sdf_terms, comp, g_col, g_dep,
              g_sdf, need_w, need_c, need_s, tiny, gw, gc, gs):  # pragma: no cover - numba
    """Gradients to w (R, S), c (R, S, 3) and s (R, S): g_col (scalar: ∂L/∂colour / (3R)), g_dep (R,) ∂L/∂D̂ per
    ray / 2, g_sdf (3, R) each SDF term's ∂L/∂term times the ray's divisor scale. Subnormal gradients (|v| < tiny:
    behind the surface, where w is) are written as zero (``fields.kernels.subnormal``)."""
    R, S = w.shape
    for r in prange(R):
        e0 = 2.0 * g_col * (comp[r, 0] - C[r, 0])
        e1 = 2.0 * g_col * (comp[r, 1] - C[r, 1])
        e2 = 2.0 * g_col * (comp[r, 2] - C[r, 2])
        ed = 2.0 * g_dep[r] * (comp[r, 3] - D[r])
        for i in range(S):
            if need_w:
                gw[r, i] = flushed(e0 * c[r, i, 0] + e1 * c[r, i, 1] + e2 * c[r, i, 2] + ed * z[r, i], tiny)
            if need_c:
                wi = w[r, i]
                gc[r, i, 0] = flushed(e0 * wi, tiny)
                gc[r, i, 1] = flushed(e1 * wi, tiny)
                gc[r, i, 2] = flushed(e2 * wi, tiny)
        if need_s:
            d = D[r]
            valid = d > 0
            b = behind[r]
            for i in range(S):
                g = 0.0
                if sdf_terms and valid:
                    front, center, tail = _masks(z[r, i], d, valid, b, thr_front, thr_center, T)
                    if front:
                        g = 2.0 * g_sdf[0, r] * (s[r, i] - fs_target)
                    elif center:
                        g = 2.0 * g_sdf[1, r] * (z[r, i] + s[r, i] * T - d) * T
                    elif tail:
                        g = 2.0 * g_sdf[2, r] * (z[r, i] + s[r, i] * T - d) * T
                gs[r, i] = flushed(g, tiny)


class CompositeLossFn(torch.autograd.Function):
    """Fused `composite` + the five loss terms on CPU tensors; differentiable (once) in w, c and s."""

    @staticmethod
    def forward(ctx, w, c, z, s, C, D, behind, T, center_band, fs_target, per_ray, sdf_terms):
        arrs = [x.detach().contiguous() for x in (w, c, z, s, C, D, behind)]
        wn, cn, zn, sn, Cn, Dn, bn = (x.numpy() for x in arrs)
        dt = wn.dtype.type
        consts = (dt(-T), dt(center_band * T), dt(T), dt(fs_target))
        R = wn.shape[0]
        comp = np.empty((R, 6), dtype=wn.dtype)
        parts = np.empty((R, 8), dtype=np.float64)
        _forward(wn, cn, zn, sn, Cn, Dn, bn, consts[0], consts[1], consts[2], consts[3], sdf_terms, comp, parts)
        n_valid = int((Dn > 0).sum())
        terms, scale = _scales(parts, n_valid, per_ray)
        ctx.save_for_backward(*arrs)
        # the backward keeps its own copy: the composites returned may be edited by the caller
        ctx.consts, ctx.sdf_terms, ctx.comp, ctx.scale, ctx.n_valid = consts, sdf_terms, comp.copy(), scale, n_valid
        comp_t = torch.from_numpy(comp)
        ctx.mark_non_differentiable(comp_t)
        return torch.from_numpy(terms.astype(wn.dtype)), comp_t

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_terms, _g_comp):
        w, c, z, s, C, D, behind = ctx.saved_tensors
        need_w, need_c, _, need_s = ctx.needs_input_grad[:4]
        g = g_terms.detach().to(torch.float64).numpy()
        R, S = w.shape
        dt = w.numpy().dtype
        Dn = D.numpy()
        g_col = g[0] / max(3 * R, 1)
        g_dep = np.where(Dn > 0, g[1] / max(ctx.n_valid, 1), 0.0)
        g_sdf = ctx.scale * g[2:, None]
        gw = np.empty((R, S) if need_w else (0, 0), dtype=dt)
        gc = np.empty((R, S, 3) if need_c else (0, 0, 3), dtype=dt)
        gs = np.empty((R, S) if need_s else (0, 0), dtype=dt)
        f, ce, T, fs = ctx.consts
        _backward(w.numpy(), c.numpy(), z.numpy(), s.numpy(), C.numpy(), Dn, behind.numpy(), f, ce, T, fs,
                  ctx.sdf_terms, ctx.comp, g_col, g_dep, g_sdf, need_w, need_c, need_s, tiny_of(dt), gw, gc, gs)
        return (torch.from_numpy(gw) if need_w else None, torch.from_numpy(gc) if need_c else None, None,
                torch.from_numpy(gs) if need_s else None, *([None] * 8))


def composite_losses(weights: Tensor, rgb: Tensor, z: Tensor, sdf: Tensor, target_rgb: Tensor, target_depth: Tensor,
                     truncation: float, center_band: float, free_space_target: float, per_ray: bool,
                     sdf_terms: bool, behind: float | Tensor = 1.0) -> tuple[dict[str, Tensor], Tensor]:
    """`composite` + `compute_losses`' five terms in one fused pass (CPU float32 / float64 tensors).

    Args:
        weights: (R, S) from G; rgb: (R, S, 3) colours in [0, 1]; z: (R, S) metres; sdf: (R, S) T-units.
        target_rgb: (R, 3); target_depth: (R,) metres (0 = none); truncation T metres; center_band in T;
        free_space_target T-units; per_ray: the SDF terms' `per_ray` reduction (else `global`); sdf_terms: False
        gives those terms as 0 (renderers that are not SDF-based); behind: the SDF band's end behind the depth,
        units of T, one value or (R,).
    Returns:
        ({'color', 'depth', 'free_space', 'center', 'tail'}: 0-d tensors, differentiable in weights, rgb, sdf),
        composites (R, 6): Ĉ (3), D̂, O, Var, without gradient.
    Raises:
        ValueError: z or the targets require a gradient (the kernel gives none: use the reference), or
            center_band > 1 (the kernel's centre band lies inside the ±T band, as `loss.center_band`'s range).
    """
    if z.requires_grad or target_rgb.requires_grad or target_depth.requires_grad:
        raise ValueError("composite_losses differentiates weights, rgb and sdf only; z and the targets must not "
                         "require grad (use composite + compute_losses)")
    if not 0 < center_band <= 1:
        raise ValueError(f"composite_losses needs 0 < center_band <= 1, got {center_band}")
    R = weights.shape[0]
    if isinstance(behind, Tensor):
        b = (behind * truncation).to(weights.dtype)
    else:  # `sdf_masks`: a scalar band end >= 1 never restricts (its masks stop at T already)
        b = weights.new_full((R,), behind * truncation if behind < 1.0 else np.inf)
    terms, comp = CompositeLossFn.apply(weights, rgb, z, sdf, target_rgb.to(weights.dtype),
                                        target_depth.to(weights.dtype), b, float(truncation), float(center_band),
                                        float(free_space_target), bool(per_ray), bool(sdf_terms))
    return dict(zip(TERMS, terms.unbind())), comp
