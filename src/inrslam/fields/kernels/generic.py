"""Generic fused CPU kernels (numba, ``parallel=True``): any entry dimension D ∈ {1,2,3} along any axes (planes,
lines, mixed tables); see ``layout.py`` for the maths and ``trilinear.py`` for the grid-level specialisation.

Layout: points ``xn (N,3)`` normalised to [0,1] (float32 or float64), table ``T (M,F)``, output ``(N,E,F)``.
Race freedom: the forward and the input backward parallelise over points (each point owns its output row);
the table backward parallelises over entries, whose row ranges are disjoint, and loops over points serially
inside an entry, so no two threads ever write the same table row and each row's sum is in point order (entries
are dealt to threads in the order 0, E−1, 1, E−2, …, ``balanced_entry``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from inrslam.fields.kernels.indexing import balanced_entry, vertex_row


@njit(inline="always", cache=True)
def _axis(p, scale, offset, res):
    """Corner index i, weight w and du/dp̂ (0 where a clamp is active) of one axis."""
    du = scale
    if not p >= 0.0:  # (NaN lands here: a defined row, never an out-of-range one)
        p = 0.0
        du = 0.0
    elif p > 1.0:
        p = 1.0
        du = 0.0
    u = p * scale + offset
    hi = res - 1.0
    if u < 0.0:
        u = 0.0
        du = 0.0
    elif u > hi:
        u = hi
        du = 0.0
    i = np.int64(math.floor(u))
    if i > res - 2:
        i = res - 2
    return i, u - i, du


@njit(inline="always", cache=True)
def _setup(xn, n, e, ndim, axes, res, scale, offset):
    d = ndim[e]
    i1 = np.int64(0)
    i2 = np.int64(0)
    w1 = 0.0
    w2 = 0.0
    d1 = 0.0
    d2 = 0.0
    i0, w0, d0 = _axis(np.float64(xn[n, axes[e, 0]]), scale[e, 0], offset[e, 0], res[e, 0])
    if d > 1:
        i1, w1, d1 = _axis(np.float64(xn[n, axes[e, 1]]), scale[e, 1], offset[e, 1], res[e, 1])
    if d > 2:
        i2, w2, d2 = _axis(np.float64(xn[n, axes[e, 2]]), scale[e, 2], offset[e, 2], res[e, 2])
    return d, i0, i1, i2, w0, w1, w2, d0, d1, d2


@njit(inline="always", cache=True)
def _corner(c, d, w0, w1, w2):
    """Bits of corner c and its per-axis factors t_k = (bit ? w_k : 1 − w_k) (1 for unused axes)."""
    b0 = c & 1
    b1 = (c >> 1) & 1
    b2 = (c >> 2) & 1
    t0 = w0 if b0 else 1.0 - w0
    t1 = 1.0
    t2 = 1.0
    if d > 1:
        t1 = w1 if b1 else 1.0 - w1
    if d > 2:
        t2 = w2 if b2 else 1.0 - w2
    return b0, b1, b2, t0, t1, t2


# Unrolled corners of unhashed entries of dimension 1 (lines) and 2 (planes): the same floating-point operations in
# the same order as the generic corner loop (a weight t0·t1·t2 with unused factors 1.0 is the product of the used
# ones exactly; (dot·s)·t with s = ±1 is ±(dot·t) exactly), so results are bit-identical to it, without the loop's
# per-corner branches and index arithmetic. Corner order as `_corner`: c = x + 2y.


@njit(inline="always", cache=True)
def _low_dim(d, hashed_e):
    """True for the entries the unrolled paths serve: unhashed lines and planes."""
    return not hashed_e and d <= 2


@njit(inline="always", cache=True)
def _acc_out(out, n, e, table, r, wt):
    """out[n,e,:] += wt · T[r, :]."""
    for f in range(table.shape[1]):
        out[n, e, f] += wt * table[r, f]


@njit(inline="always", cache=True)
def _dot(table, r, g, n, e):
    """⟨T[r], g[n,e]⟩ accumulated as the generic loop does."""
    dot = 0.0
    for f in range(table.shape[1]):
        dot += table[r, f] * g[n, e, f]
    return dot


@njit(inline="always", cache=True)
def _touch(slot, out_rows, out_vals, cb, cnt, r, wt, g, n, e):
    """Adds wt · g[n,e] to row r's sparse gradient (a zero weight does not touch the row; the first touch writes the
    row into out_rows[cb + cnt] and its values, so out_vals need not be zeroed); returns the new count."""
    if wt == 0.0:
        return cnt
    s = slot[r]
    if s < 0:
        s = cnt
        slot[r] = cnt
        out_rows[cb + cnt] = r
        for f in range(out_vals.shape[1]):
            out_vals[cb + s, f] = wt * g[n, e, f]
        return cnt + 1
    for f in range(out_vals.shape[1]):
        out_vals[cb + s, f] += wt * g[n, e, f]
    return cnt


@njit(parallel=True, cache=True, fastmath=False)
def interp_forward(xn, table, ndim, axes, res, scale, offset, stride, hashed, rows, row_off, out):
    """out[n,e,:] = Σ_c w_c(n,e) · T[row_c(n,e), :]   (out pre-zeroed, (N,E,F))."""
    N = xn.shape[0]
    E = ndim.shape[0]
    F = table.shape[1]
    for n in prange(N):
        for e in range(E):
            d, i0, i1, i2, w0, w1, w2, _d0, _d1, _d2 = _setup(xn, n, e, ndim, axes, res, scale, offset)
            base = row_off[e]
            if _low_dim(d, hashed[e]):
                s0 = stride[e, 0]
                ra = base + i0 * s0 + i1 * stride[e, 1] + i2 * stride[e, 2]
                if d == 1:
                    _acc_out(out, n, e, table, ra, 1.0 - w0)
                    _acc_out(out, n, e, table, ra + s0, w0)
                else:
                    s1 = stride[e, 1]
                    u0 = 1.0 - w0
                    u1 = 1.0 - w1
                    _acc_out(out, n, e, table, ra, u0 * u1)
                    _acc_out(out, n, e, table, ra + s0, w0 * u1)
                    _acc_out(out, n, e, table, ra + s1, u0 * w1)
                    _acc_out(out, n, e, table, ra + s0 + s1, w0 * w1)
                continue
            for c in range(1 << d):
                b0, b1, b2, t0, t1, t2 = _corner(c, d, w0, w1, w2)
                wt = t0 * t1 * t2
                r = base + vertex_row(hashed[e], rows[e], i0 + b0, i1 + b1, i2 + b2,
                                stride[e, 0], stride[e, 1], stride[e, 2])
                for f in range(F):
                    out[n, e, f] += wt * table[r, f]


@njit(parallel=True, cache=True, fastmath=False)
def interp_backward_x(xn, table, g, ndim, axes, res, scale, offset, stride, hashed, rows, row_off, gx):
    """gx[n,a] += Σ_e Σ_c (∂w_c/∂u_k · du_k/dp̂_a) ⟨T[row_c], g[n,e]⟩   (gx pre-zeroed float64 (N,3))."""
    N = xn.shape[0]
    E = ndim.shape[0]
    F = table.shape[1]
    for n in prange(N):
        for e in range(E):
            d, i0, i1, i2, w0, w1, w2, d0, d1, d2 = _setup(xn, n, e, ndim, axes, res, scale, offset)
            base = row_off[e]
            gu0 = 0.0
            gu1 = 0.0
            gu2 = 0.0
            if _low_dim(d, hashed[e]):
                s0 = stride[e, 0]
                ra = base + i0 * s0 + i1 * stride[e, 1] + i2 * stride[e, 2]
                if d == 1:
                    gu0 -= _dot(table, ra, g, n, e)
                    gu0 += _dot(table, ra + s0, g, n, e)
                    gx[n, axes[e, 0]] += gu0 * d0
                else:
                    s1 = stride[e, 1]
                    u0 = 1.0 - w0
                    u1 = 1.0 - w1
                    da = _dot(table, ra, g, n, e)
                    db = _dot(table, ra + s0, g, n, e)
                    dc = _dot(table, ra + s1, g, n, e)
                    dd = _dot(table, ra + s0 + s1, g, n, e)
                    gu0 -= da * u1
                    gu1 -= da * u0
                    gu0 += db * u1
                    gu1 -= db * w0
                    gu0 -= dc * w1
                    gu1 += dc * u0
                    gu0 += dd * w1
                    gu1 += dd * w0
                    gx[n, axes[e, 0]] += gu0 * d0
                    gx[n, axes[e, 1]] += gu1 * d1
                continue
            for c in range(1 << d):
                b0, b1, b2, t0, t1, t2 = _corner(c, d, w0, w1, w2)
                r = base + vertex_row(hashed[e], rows[e], i0 + b0, i1 + b1, i2 + b2,
                                stride[e, 0], stride[e, 1], stride[e, 2])
                dot = 0.0
                for f in range(F):
                    dot += table[r, f] * g[n, e, f]
                s0 = 1.0 if b0 else -1.0
                s1 = 1.0 if b1 else -1.0
                s2 = 1.0 if b2 else -1.0
                gu0 += dot * s0 * t1 * t2
                gu1 += dot * t0 * s1 * t2
                gu2 += dot * t0 * t1 * s2
            gx[n, axes[e, 0]] += gu0 * d0
            if d > 1:
                gx[n, axes[e, 1]] += gu1 * d1
            if d > 2:
                gx[n, axes[e, 2]] += gu2 * d2


@njit(parallel=True, cache=True, fastmath=False)
def interp_backward_table_dense(xn, g, ndim, axes, res, scale, offset, stride, hashed, rows, row_off, grad):
    """grad[row_c] += w_c · g[n,e] into a pre-zeroed dense (M,F) array (parallel over entries)."""
    N = xn.shape[0]
    E = ndim.shape[0]
    F = grad.shape[1]
    for ie in prange(E):
        e = balanced_entry(ie, E)
        base = row_off[e]
        for n in range(N):
            d, i0, i1, i2, w0, w1, w2, _d0, _d1, _d2 = _setup(xn, n, e, ndim, axes, res, scale, offset)
            for c in range(1 << d):
                b0, b1, b2, t0, t1, t2 = _corner(c, d, w0, w1, w2)
                wt = t0 * t1 * t2
                r = base + vertex_row(hashed[e], rows[e], i0 + b0, i1 + b1, i2 + b2,
                                stride[e, 0], stride[e, 1], stride[e, 2])
                for f in range(F):
                    grad[r, f] += wt * g[n, e, f]


@njit(parallel=True, cache=True, fastmath=False)
def interp_backward_table_sparse(xn, g, ndim, axes, res, scale, offset, stride, hashed, rows, row_off,
                                 slot, cap_off, out_rows, out_vals, counts):
    """Touched rows (non-zero interpolation weight) and their summed gradients, per entry: rows
    out_rows[cap_off[e] : cap_off[e] + counts[e]] (unique, in first-touch order), values out_vals[same] (written on
    first touch, so they need not be pre-zeroed). ``slot`` (M,) and ``out_rows`` are int32 or int64 (one dtype for
    both, ``function.row_index_dtype``); ``slot`` must be all −1 on entry and is restored to −1 on exit; cost is
    O(N·2^D) per entry, independent of the table size."""
    N = xn.shape[0]
    E = ndim.shape[0]
    for ie in prange(E):
        e = balanced_entry(ie, E)
        base = row_off[e]
        cb = cap_off[e]
        cnt = 0
        for n in range(N):
            d, i0, i1, i2, w0, w1, w2, _d0, _d1, _d2 = _setup(xn, n, e, ndim, axes, res, scale, offset)
            if _low_dim(d, hashed[e]):
                s0 = stride[e, 0]
                ra = base + i0 * s0 + i1 * stride[e, 1] + i2 * stride[e, 2]
                if d == 1:
                    cnt = _touch(slot, out_rows, out_vals, cb, cnt, ra, 1.0 - w0, g, n, e)
                    cnt = _touch(slot, out_rows, out_vals, cb, cnt, ra + s0, w0, g, n, e)
                else:
                    s1 = stride[e, 1]
                    u0 = 1.0 - w0
                    u1 = 1.0 - w1
                    cnt = _touch(slot, out_rows, out_vals, cb, cnt, ra, u0 * u1, g, n, e)
                    cnt = _touch(slot, out_rows, out_vals, cb, cnt, ra + s0, w0 * u1, g, n, e)
                    cnt = _touch(slot, out_rows, out_vals, cb, cnt, ra + s1, u0 * w1, g, n, e)
                    cnt = _touch(slot, out_rows, out_vals, cb, cnt, ra + s0 + s1, w0 * w1, g, n, e)
                continue
            for c in range(1 << d):
                b0, b1, b2, t0, t1, t2 = _corner(c, d, w0, w1, w2)
                wt = t0 * t1 * t2
                r = base + vertex_row(hashed[e], rows[e], i0 + b0, i1 + b1, i2 + b2,
                                stride[e, 0], stride[e, 1], stride[e, 2])
                cnt = _touch(slot, out_rows, out_vals, cb, cnt, r, wt, g, n, e)
        counts[e] = cnt
        for k in range(cnt):
            slot[out_rows[cb + k]] = -1


@njit(parallel=True, cache=True, fastmath=False)
def interp_backward_x_backward(xn, table, g, ggx, ndim, axes, res, scale, offset, stride, hashed, rows, row_off,
                               want_g, grad_g, gxx, out_rows, out_vals):
    """Backward of the input backward gx[n,a] = Σ_{e,f} g[n,e,f] J[n,e,f,a] (J = ∂out/∂p̂, ``interp_backward_x``) for
    its output gradient ggx (N,3): with A_k = ggx[n, a_k] · du_k/dp̂_{a_k} and v_c = Σ_k A_k ∂w_c/∂u_k
    (∂w_c/∂u_k = s_k Π_{j≠k} t_j, s_k = ±1 the corner's side along k, t_j its per-axis factors),

        grad_g[n,e,f] = Σ_c v_c T[r_c, f]                                   (written if ``want_g``, (N,E,F))
        ∂/∂T[r_c, f]  = v_c g[n,e,f]: out_rows[n,e,c] = r_c, out_vals[n,e,c,:] (rows −1 where v_c = 0, and for
                        c ≥ 2^D; (N,E,C) and (N,E,C,F), C ≥ 2^max D; ``out_rows`` of size 0: not wanted)
        gxx[n, a_k]  += du_k/dp̂ Σ_c ⟨T[r_c], g[n,e]⟩ s_k Σ_{j≠k} A_j s_j Π_{l≠k,j} t_l   (float64 (N,3), pre-zeroed)

    The last line is the Hessian of the multilinear interpolation: its diagonal is 0 (linear along each axis), only
    the cross terms j ≠ k remain. Parallel over points; every (n,e,c) owns its output slot, so no races."""
    N = xn.shape[0]
    E = ndim.shape[0]
    F = table.shape[1]
    want_t = out_rows.shape[0] > 0
    C = out_rows.shape[2] if want_t else 0
    for n in prange(N):
        for e in range(E):
            d, i0, i1, i2, w0, w1, w2, d0, d1, d2 = _setup(xn, n, e, ndim, axes, res, scale, offset)
            a0 = ggx[n, axes[e, 0]] * d0
            a1 = ggx[n, axes[e, 1]] * d1 if d > 1 else 0.0
            a2 = ggx[n, axes[e, 2]] * d2 if d > 2 else 0.0
            base = row_off[e]
            h0 = 0.0
            h1 = 0.0
            h2 = 0.0
            if want_g:
                for f in range(F):
                    grad_g[n, e, f] = 0.0
            for c in range(1 << d):
                b0, b1, b2, t0, t1, t2 = _corner(c, d, w0, w1, w2)
                s0 = 1.0 if b0 else -1.0
                s1 = 1.0 if b1 else -1.0
                s2 = 1.0 if b2 else -1.0
                v = a0 * s0 * t1 * t2
                if d > 1:
                    v += a1 * t0 * s1 * t2
                if d > 2:
                    v += a2 * t0 * t1 * s2
                r = base + vertex_row(hashed[e], rows[e], i0 + b0, i1 + b1, i2 + b2,
                                      stride[e, 0], stride[e, 1], stride[e, 2])
                dot = 0.0
                for f in range(F):
                    dot += table[r, f] * g[n, e, f]
                    if want_g:
                        grad_g[n, e, f] += v * table[r, f]
                if d > 1:
                    # ∂v/∂u_k without the a_k term: Σ_{j≠k} a_j s_j s_k Π_{l≠k,j} t_l (unused axes: a_j = 0, t = 1)
                    h0 += dot * s0 * (a1 * s1 * t2 + a2 * t1 * s2)
                    h1 += dot * s1 * (a0 * s0 * t2 + a2 * t0 * s2)
                    h2 += dot * s2 * (a0 * s0 * t1 + a1 * t0 * s1)
                if want_t:
                    if v != 0.0:
                        out_rows[n, e, c] = r
                        for f in range(F):
                            out_vals[n, e, c, f] = v * g[n, e, f]
                    else:
                        out_rows[n, e, c] = -1
            if want_t:
                for c in range(1 << d, C):
                    out_rows[n, e, c] = -1
            if d > 1:
                gxx[n, axes[e, 0]] += h0 * d0
                gxx[n, axes[e, 1]] += h1 * d1
            if d > 2:
                gxx[n, axes[e, 2]] += h2 * d2


# ---------------------------------------------------------------------------------------------------------------
# Lookups that also output their input Jacobian J[n,e,f,a] = ∂out[n,e,f]/∂p̂_a as a differentiable output (second-
# order backward: SDF normals). The backward gets the gradient gj (N,E,F,3) of J besides g of the output.
# ---------------------------------------------------------------------------------------------------------------


@njit(inline="always", cache=True)
def _dweights(d, s0, s1, s2, t0, t1, t2, d0, d1, d2):
    """∂w_c/∂p̂ along the entry's axes k: D_k = du_k/dp̂ · s_k Π_{j≠k} t_j (0 for unused axes)."""
    D0 = d0 * s0 * t1 * t2
    D1 = d1 * t0 * s1 * t2 if d > 1 else 0.0
    D2 = d2 * t0 * t1 * s2 if d > 2 else 0.0
    return D0, D1, D2


@njit(inline="always", cache=True)
def _pair(a, b):
    """Index of the axis pair {a, b} (a ≠ b) in (xy, xz, yz)."""
    return a + b - 1


@njit(parallel=True, cache=True, fastmath=False)
def interp_forward_jac(xn, table, ndim, axes, res, scale, offset, stride, hashed, rows, row_off, out, jac, hess):
    """out[n,e,:] = Σ_c w_c T[r_c, :], jac[n,e,f,a] = Σ_c ∂w_c/∂p̂_a T[r_c, f] and the mixed second derivatives
    hess[n,e,f,p] = ∂²out[n,e,f]/∂p̂_a∂p̂_b, pairs p = (xy, xz, yz): du_k/dp̂ du_j/dp̂ Σ_c s_k s_j Π_{l≠k,j} t_l T[r_c, f]
    (the pure second derivatives are 0: linear along each axis). out, jac (N,E,F,3), hess (N,E,F,3) pre-zeroed;
    0 along axes the entry does not read."""
    N = xn.shape[0]
    E = ndim.shape[0]
    F = table.shape[1]
    for n in prange(N):
        for e in range(E):
            d, i0, i1, i2, w0, w1, w2, d0, d1, d2 = _setup(xn, n, e, ndim, axes, res, scale, offset)
            base = row_off[e]
            for c in range(1 << d):
                b0, b1, b2, t0, t1, t2 = _corner(c, d, w0, w1, w2)
                wt = t0 * t1 * t2
                D0, D1, D2 = _dweights(d, 1.0 if b0 else -1.0, 1.0 if b1 else -1.0, 1.0 if b2 else -1.0,
                                       t0, t1, t2, d0, d1, d2)
                r = base + vertex_row(hashed[e], rows[e], i0 + b0, i1 + b1, i2 + b2,
                                      stride[e, 0], stride[e, 1], stride[e, 2])
                s0 = 1.0 if b0 else -1.0
                s1 = 1.0 if b1 else -1.0
                s2 = 1.0 if b2 else -1.0
                H01 = d0 * d1 * s0 * s1 * t2
                H02 = d0 * d2 * s0 * t1 * s2
                H12 = d1 * d2 * t0 * s1 * s2
                for f in range(F):
                    v = table[r, f]
                    out[n, e, f] += wt * v
                    jac[n, e, f, axes[e, 0]] += D0 * v
                    if d > 1:
                        jac[n, e, f, axes[e, 1]] += D1 * v
                        hess[n, e, f, _pair(axes[e, 0], axes[e, 1])] += H01 * v
                    if d > 2:
                        jac[n, e, f, axes[e, 2]] += D2 * v
                        hess[n, e, f, _pair(axes[e, 0], axes[e, 2])] += H02 * v
                        hess[n, e, f, _pair(axes[e, 1], axes[e, 2])] += H12 * v


@njit(inline="always", cache=True)
def _corner_grad(g, gj, n, e, f, wt, D0, D1, D2, a0, a1, a2):
    """∂L/∂T[r_c, f] of one point and corner: w_c g[n,e,f] + Σ_k D_k gj[n,e,f,a_k]."""
    return wt * g[n, e, f] + D0 * gj[n, e, f, a0] + D1 * gj[n, e, f, a1] + D2 * gj[n, e, f, a2]


@njit(parallel=True, cache=True, fastmath=False)
def interp_backward_table_jac_dense(xn, g, gj, ndim, axes, res, scale, offset, stride, hashed, rows, row_off, grad):
    """grad[r_c] += w_c g[n,e] + Σ_k ∂w_c/∂p̂_{a_k} gj[n,e,:,a_k] into a pre-zeroed dense (M,F) array (parallel over
    entries, points in order)."""
    N = xn.shape[0]
    E = ndim.shape[0]
    F = grad.shape[1]
    for ie in prange(E):
        e = balanced_entry(ie, E)
        base = row_off[e]
        for n in range(N):
            d, i0, i1, i2, w0, w1, w2, d0, d1, d2 = _setup(xn, n, e, ndim, axes, res, scale, offset)
            for c in range(1 << d):
                b0, b1, b2, t0, t1, t2 = _corner(c, d, w0, w1, w2)
                D0, D1, D2 = _dweights(d, 1.0 if b0 else -1.0, 1.0 if b1 else -1.0, 1.0 if b2 else -1.0,
                                       t0, t1, t2, d0, d1, d2)
                r = base + vertex_row(hashed[e], rows[e], i0 + b0, i1 + b1, i2 + b2,
                                      stride[e, 0], stride[e, 1], stride[e, 2])
                for f in range(F):
                    grad[r, f] += _corner_grad(g, gj, n, e, f, t0 * t1 * t2, D0, D1, D2, axes[e, 0], axes[e, 1],
                                               axes[e, 2])


@njit(parallel=True, cache=True, fastmath=False)
def interp_backward_table_jac_sparse(xn, g, gj, ndim, axes, res, scale, offset, stride, hashed, rows, row_off,
                                     slot, cap_off, out_rows, out_vals, counts):
    """As ``interp_backward_table_sparse`` (unique touched rows per entry, first-touch order, ``slot`` all −1 on
    entry and exit) for the gradient w_c g[n,e] + Σ_k ∂w_c/∂p̂_{a_k} gj[n,e,:,a_k]; a corner is touched when its
    weight or one of its derivative weights is non-zero."""
    N = xn.shape[0]
    E = ndim.shape[0]
    F = out_vals.shape[1]
    for ie in prange(E):
        e = balanced_entry(ie, E)
        base = row_off[e]
        cb = cap_off[e]
        cnt = 0
        for n in range(N):
            d, i0, i1, i2, w0, w1, w2, d0, d1, d2 = _setup(xn, n, e, ndim, axes, res, scale, offset)
            for c in range(1 << d):
                b0, b1, b2, t0, t1, t2 = _corner(c, d, w0, w1, w2)
                wt = t0 * t1 * t2
                D0, D1, D2 = _dweights(d, 1.0 if b0 else -1.0, 1.0 if b1 else -1.0, 1.0 if b2 else -1.0,
                                       t0, t1, t2, d0, d1, d2)
                if wt == 0.0 and D0 == 0.0 and D1 == 0.0 and D2 == 0.0:
                    continue
                r = base + vertex_row(hashed[e], rows[e], i0 + b0, i1 + b1, i2 + b2,
                                      stride[e, 0], stride[e, 1], stride[e, 2])
                s = slot[r]
                if s < 0:  # first touch: write (out_vals need not be zeroed)
                    s = cnt
                    slot[r] = cnt
                    out_rows[cb + cnt] = r
                    cnt += 1
                    for f in range(F):
                        out_vals[cb + s, f] = _corner_grad(g, gj, n, e, f, wt, D0, D1, D2, axes[e, 0], axes[e, 1],
                                                           axes[e, 2])
                else:
                    for f in range(F):
                        out_vals[cb + s, f] += _corner_grad(g, gj, n, e, f, wt, D0, D1, D2, axes[e, 0], axes[e, 1],
                                                            axes[e, 2])
        counts[e] = cnt
        for k in range(cnt):
            slot[out_rows[cb + k]] = -1
