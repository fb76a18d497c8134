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
    first touch, so they need not be pre-zeroed). ``slot`` (M,) int32 must be all −1 on
    entry and is restored to −1 on exit; cost is O(N·2^D) per entry, independent of the table size."""
    N = xn.shape[0]
    E = ndim.shape[0]
    F = out_vals.shape[1]
    for ie in prange(E):
        e = balanced_entry(ie, E)
        base = row_off[e]
        cb = cap_off[e]
        cnt = 0
        for n in range(N):
            d, i0, i1, i2, w0, w1, w2, _d0, _d1, _d2 = _setup(xn, n, e, ndim, axes, res, scale, offset)
            for c in range(1 << d):
                b0, b1, b2, t0, t1, t2 = _corner(c, d, w0, w1, w2)
                wt = t0 * t1 * t2
                if wt == 0.0:  # zero-weight corner: not touched
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
                        out_vals[cb + s, f] = wt * g[n, e, f]
                else:
                    for f in range(F):
                        out_vals[cb + s, f] += wt * g[n, e, f]
        counts[e] = cnt
        for k in range(cnt):
            slot[out_rows[cb + k]] = -1
