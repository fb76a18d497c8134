"""Fused CPU kernels (numba, ``parallel=True``) specialised to trilinear grid levels (every entry D = 3 over axes
(x, y, z)): forward with the input Jacobian, its contraction, and the dense, row-slot and accumulator table
backwards. Same maths and summation order as ``generic.py`` (see ``layout.py``).

The 8 corner rows come from per-axis terms,
r = base + (i + c_x) + (j + c_y)·s_y + (k + c_z)·s_z   or   ((i+c_x) ⊕ (j+c_y)·P1 ⊕ (k+c_z)·P2) mod rows,
and corners are summed in the same order as the generic kernel / reference (bit 0 = x).
The kernels work in blocks of points: rows and weights first (structure-of-arrays, vectorised), then a prefetch
of each corner's cache line (``prefetch.py``), then the gathers / scatters, which find them in cache. When the
input gradient is needed, the forward also stores ∂out/∂p̂ so that the input backward is a contraction instead of
a second lookup. The table backwards are race-free as the generic one's: work items own disjoint rows (a level,
or for the few huge levels of a dense grid an interleaved row part of a level) and sum points in order.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from inrslam.fields.kernels.indexing import P1, P2, balanced_entry, vertex_row
from inrslam.fields.kernels.prefetch import prefetch_row, prefetch_row_w

_u = np.uint64  # an unsigned index: no negative-index wrap-around code (see ``_tri_block``)


@njit(inline="always", cache=True)
def _axis_lean(p, scale, offset, lo, hi, res):
    """``_axis`` with its two clamps merged into one of u to [lo, hi] (``TableLayout.lo/hi``); same results."""
    u = p * scale + offset
    du = scale
    if not u >= lo:  # (NaN lands here: a defined row, never an out-of-range one)
        u = lo
        du = 0.0
    elif u > hi:
        u = hi
        du = 0.0
    i = np.int64(u)  # u ≥ 0: truncation is the floor
    if i > res - 2:
        i = res - 2
    return i, u - i, du


@njit(inline="always", cache=True)
def _tri(px, py, pz, e, res, scale, offset, lo, hi, stride, hashed, rows, row_off):
    """Corner rows r0..r7, weights and du/dp̂ of point p̂ = (px, py, pz) (float64) in level e."""
    ix, wx, dx = _axis_lean(px, scale[e, 0], offset[e, 0], lo[e, 0], hi[e, 0], res[e, 0])
    iy, wy, dy = _axis_lean(py, scale[e, 1], offset[e, 1], lo[e, 1], hi[e, 1], res[e, 1])
    iz, wz, dz = _axis_lean(pz, scale[e, 2], offset[e, 2], lo[e, 2], hi[e, 2], res[e, 2])
    base = row_off[e]
    if hashed[e]:
        mask = rows[e] - 1
        y0 = iy * P1
        y1 = y0 + P1
        z0 = iz * P2
        z1 = z0 + P2
        x1 = ix + 1
        r0 = base + ((ix ^ y0 ^ z0) & mask)
        r1 = base + ((x1 ^ y0 ^ z0) & mask)
        r2 = base + ((ix ^ y1 ^ z0) & mask)
        r3 = base + ((x1 ^ y1 ^ z0) & mask)
        r4 = base + ((ix ^ y0 ^ z1) & mask)
        r5 = base + ((x1 ^ y0 ^ z1) & mask)
        r6 = base + ((ix ^ y1 ^ z1) & mask)
        r7 = base + ((x1 ^ y1 ^ z1) & mask)
    else:
        sy = stride[e, 1]
        sz = stride[e, 2]
        r0 = base + ix + iy * sy + iz * sz
        r1 = r0 + 1
        r2 = r0 + sy
        r3 = r2 + 1
        r4 = r0 + sz
        r5 = r4 + 1
        r6 = r4 + sy
        r7 = r6 + 1
    return r0, r1, r2, r3, r4, r5, r6, r7, wx, wy, wz, dx, dy, dz


@njit(inline="always", cache=True)
def _tri_weights(wx, wy, wz):
    """Trilinear corner weights in corner order c = x + 2y + 4z: w_c = prod_a (w_a if bit a of c else 1 - w_a)."""
    ux = 1.0 - wx
    uy = 1.0 - wy
    uz = 1.0 - wz
    return (ux * uy * uz, wx * uy * uz, ux * wy * uz, wx * wy * uz,
            ux * uy * wz, wx * uy * wz, ux * wy * wz, wx * wy * wz)


#: Public names of the corner rule (rows, weights, du/dp̂ of a point in one entry) and of the corner weights, for
#: kernels that fuse a trilinear lookup with other work (`inrslam.slam.ehe.sdf_kernel`).
tri_corners = _tri
tri_weights = _tri_weights


#: Points per block of the two-pass trilinear kernels: pass 1 computes the rows and weights of a block of points
#: (arithmetic only), pass 2 gathers / scatters with independent loads, so many cache misses are in flight at once.
_BLOCK = 64


@njit(inline="always", cache=True)
def _prefetch8(pf, mode, r0, r1, r2, r3, r4, r5, r6, r7):
    """Prefetch rows r0..r7 of pf for reading (mode 1) or writing (mode 2); mode 0: nothing."""
    if mode == 1:
        prefetch_row(pf, r0)
        prefetch_row(pf, r1)
        prefetch_row(pf, r2)
        prefetch_row(pf, r3)
        prefetch_row(pf, r4)
        prefetch_row(pf, r5)
        prefetch_row(pf, r6)
        prefetch_row(pf, r7)
    elif mode == 2:
        prefetch_row_w(pf, r0)
        prefetch_row_w(pf, r1)
        prefetch_row_w(pf, r2)
        prefetch_row_w(pf, r3)
        prefetch_row_w(pf, r4)
        prefetch_row_w(pf, r5)
        prefetch_row_w(pf, r6)
        prefetch_row_w(pf, r7)


#: Entries with fewer rows than this are not prefetched (their rows stay in L2 cache anyway).
_PREFETCH_MIN_ROWS = 1 << 14


@njit(inline="always", cache=True)
def _tri_block(xn, n0, n1, e0, e1, res, scale, offset, lo, hi, stride, hashed, rows, row_off, X, I, R, W, pf, mode):
    """Pass 1 of points n0 + j < n1 and entries e0 .. e1−1, structure-of-arrays so that it vectorises:
    R[e−e0, c, j] = r_c and W[e−e0, :, j] = (wx, wy, wz, dx, dy, dz). X (3,B) float64 and I (3,B) int64 are
    scratch. The corner rows of ``pf`` are then prefetched (``_prefetch8`` mode; entries of fewer than
    ``_PREFETCH_MIN_ROWS`` rows skipped), so that the gathers / scatters of pass 2 find them in cache.
    Indices are cast to unsigned so that numba emits no negative-index wrap-around (which blocks vectorisation)."""
    m = n1 - n0
    for j in range(m):
        X[0, _u(j)] = np.float64(xn[_u(n0 + j), 0])
        X[1, _u(j)] = np.float64(xn[_u(n0 + j), 1])
        X[2, _u(j)] = np.float64(xn[_u(n0 + j), 2])
    for e in range(e0, e1):
        k = _u(e - e0)
        for a in range(3):  # vectorised over the points
            s = scale[e, a]
            o = offset[e, a]
            lo_a = lo[e, a]
            hi_a = hi[e, a]
            r = res[e, a]
            for j in range(m):
                i, w, du = _axis_lean(X[_u(a), _u(j)], s, o, lo_a, hi_a, r)
                I[_u(a), _u(j)] = i
                W[k, _u(a), _u(j)] = w
                W[k, _u(a + 3), _u(j)] = du
        base = row_off[e]
        h = hashed[e]
        n_rows = rows[e]
        sx = stride[e, 0]
        sy = stride[e, 1]
        sz = stride[e, 2]
        for c in range(8):
            bx = c & 1
            by = (c >> 1) & 1
            bz = c >> 2
            for j in range(m):
                R[k, _u(c), _u(j)] = base + vertex_row(h, n_rows, I[0, _u(j)] + bx, I[1, _u(j)] + by, I[2, _u(j)] + bz,
                                                 sx, sy, sz)
    if mode == 0:
        return
    for e in range(e0, e1):
        if rows[e] < _PREFETCH_MIN_ROWS:
            continue
        k = _u(e - e0)
        for j in range(m):
            _prefetch8(pf, mode, R[k, 0, _u(j)], R[k, 1, _u(j)], R[k, 2, _u(j)], R[k, 3, _u(j)], R[k, 4, _u(j)],
                       R[k, 5, _u(j)], R[k, 6, _u(j)], R[k, 7, _u(j)])


@njit(inline="always", cache=True)
def _block_scratch(K):
    """(X, I, R, W) scratch of ``_tri_block`` for K entries."""
    return (np.empty((3, _BLOCK), np.float64), np.empty((3, _BLOCK), np.int64), np.empty((K, 8, _BLOCK), np.int64),
            np.empty((K, 6, _BLOCK), np.float64))


@njit(inline="always", cache=True)
def _acc_dense(grad, r, wt, g, n, e, F):
    for f in range(F):
        grad[r, f] += wt * g[n, e, f]


@njit(parallel=True, cache=True, fastmath=False)
def tri_backward_table_dense(xn, g, res, scale, offset, lo, hi, stride, hashed, rows, row_off, grad):
    """grad[r_c] += w_c g[n,e] into a pre-zeroed dense (M,F) array (parallel over levels)."""
    N = xn.shape[0]
    E = res.shape[0]
    F = grad.shape[1]
    for ie in prange(E):
        e = balanced_entry(ie, E)
        for n in range(N):
            r0, r1, r2, r3, r4, r5, r6, r7, wx, wy, wz, _a, _b, _c = _tri(
                np.float64(xn[n, 0]), np.float64(xn[n, 1]), np.float64(xn[n, 2]), e, res, scale, offset, lo, hi,
                stride, hashed, rows, row_off)
            w = _tri_weights(wx, wy, wz)
            _acc_dense(grad, r0, w[0], g, n, e, F)
            _acc_dense(grad, r1, w[1], g, n, e, F)
            _acc_dense(grad, r2, w[2], g, n, e, F)
            _acc_dense(grad, r3, w[3], g, n, e, F)
            _acc_dense(grad, r4, w[4], g, n, e, F)
            _acc_dense(grad, r5, w[5], g, n, e, F)
            _acc_dense(grad, r6, w[6], g, n, e, F)
            _acc_dense(grad, r7, w[7], g, n, e, F)


@njit(inline="always", cache=True)
def _acc_sparse(slot, out_rows, out_vals, cb, cnt, r, wt, g, n, e, F):
    if wt == 0.0:  # zero-weight corner (e.g. a clamped point on the box face): not touched
        return cnt
    s = slot[r]
    if s < 0:  # first touch: write (out_vals need not be zeroed)
        slot[r] = cnt
        out_rows[cb + cnt] = r
        for f in range(F):
            out_vals[cb + cnt, f] = wt * g[n, e, f]
        return cnt + 1
    for f in range(F):
        out_vals[cb + s, f] += wt * g[n, e, f]
    return cnt


@njit(parallel=True, cache=True, fastmath=False)
def tri_backward_table_sparse(xn, g, res, scale, offset, lo, hi, stride, hashed, rows, row_off,
                              slot, n_parts, part_log2, cap_off, out_rows, out_vals, counts):
    """Sparse table gradient of trilinear levels, split into E·P work items (entry e, row part p): item
    i = p·E + e owns the rows r of entry e with ((r − row_off[e]) >> part_log2) % P == p (blocks of rows dealt
    round-robin, so every part spreads over the whole entry) and writes its touched rows and summed gradients
    to out_rows / out_vals[cap_off[i] : cap_off[i] + counts[i]] (unique, first-touch order; out_vals written on
    first touch, so never pre-zeroed). Items own disjoint rows, so they run in parallel without races even when
    one fine level holds nearly all the work (dense grids, P > 1). ``slot`` (M,) and ``out_rows`` are int32 or int64
    (``function.row_index_dtype``); ``slot`` is all −1 on entry and exit.
    Each item scans all N points of its entry (rows are cheap arithmetic) and prefetches the slots it owns."""
    N = xn.shape[0]
    E = res.shape[0]
    F = out_vals.shape[1]
    P = n_parts
    for it in prange(E * P):
        p = it // E
        e = balanced_entry(it % E, E)
        item = p * E + e
        base = row_off[e]
        cb = cap_off[item]
        cnt = 0
        X, I, R, W = _block_scratch(1)
        for n0 in range(0, N, _BLOCK):
            n1 = min(N, n0 + _BLOCK)
            _tri_block(xn, n0, n1, e, e + 1, res, scale, offset, lo, hi, stride, hashed, rows, row_off, X, I, R, W,
                       slot, 2 if P == 1 else 0)
            if P > 1:
                for j in range(n1 - n0):
                    for c in range(8):
                        r = R[0, c, j]
                        if ((r - base) >> part_log2) % P == p:
                            prefetch_row_w(slot, r)
                        else:
                            R[0, c, j] = -1  # not this item's row
            for n in range(n0, n1):
                j = n - n0
                w = _tri_weights(W[0, 0, j], W[0, 1, j], W[0, 2, j])
                for c in range(8):
                    if R[0, c, j] >= 0:
                        cnt = _acc_sparse(slot, out_rows, out_vals, cb, cnt, R[0, c, j], w[c], g, n, e, F)
        counts[item] = cnt
        for k in range(cnt):
            slot[out_rows[cb + k]] = -1


@njit(inline="always", cache=True)
def _acc_sparse_jac(slot, out_rows, out_vals, cb, cnt, r, wt, Dx, Dy, Dz, g, gj, n, e, F):
    """``_acc_sparse`` of the gradient wt·g[n,e] + Dx·gj[n,e,:,0] + Dy·gj[n,e,:,1] + Dz·gj[n,e,:,2]."""
    if wt == 0.0 and Dx == 0.0 and Dy == 0.0 and Dz == 0.0:  # not touched
        return cnt
    s = slot[r]
    if s < 0:  # first touch: write (out_vals need not be zeroed)
        slot[r] = cnt
        out_rows[cb + cnt] = r
        for f in range(F):
            out_vals[cb + cnt, f] = wt * g[n, e, f] + Dx * gj[n, e, f, 0] + Dy * gj[n, e, f, 1] + Dz * gj[n, e, f, 2]
        return cnt + 1
    for f in range(F):
        out_vals[cb + s, f] += wt * g[n, e, f] + Dx * gj[n, e, f, 0] + Dy * gj[n, e, f, 1] + Dz * gj[n, e, f, 2]
    return cnt


@njit(parallel=True, cache=True, fastmath=False)
def tri_backward_table_jac_sparse(xn, g, gj, res, scale, offset, lo, hi, stride, hashed, rows, row_off,
                                  slot, n_parts, part_log2, cap_off, out_rows, out_vals, counts):
    """``tri_backward_table_sparse`` for the table gradient of a lookup that also output its Jacobian (the second-
    order backward of ``function.MultilinearJacFn``): corner c of point n gets w_c g[n,e] + Σ_a ∂w_c/∂p̂_a gj[n,e,:,a],
    ∂w_c/∂p̂_x = du_x/dp̂ s_x t_y t_z (s = ±1 the corner's side, t its per-axis weights) and likewise; a corner is
    touched when its weight or a derivative weight is non-zero. Same work items, rows and outputs."""
    N = xn.shape[0]
    E = res.shape[0]
    F = out_vals.shape[1]
    P = n_parts
    for it in prange(E * P):
        p = it // E
        e = balanced_entry(it % E, E)
        item = p * E + e
        base = row_off[e]
        cb = cap_off[item]
        cnt = 0
        X, I, R, W = _block_scratch(1)
        for n0 in range(0, N, _BLOCK):
            n1 = min(N, n0 + _BLOCK)
            _tri_block(xn, n0, n1, e, e + 1, res, scale, offset, lo, hi, stride, hashed, rows, row_off, X, I, R, W,
                       slot, 2 if P == 1 else 0)
            if P > 1:
                for j in range(n1 - n0):
                    for c in range(8):
                        r = R[0, c, j]
                        if ((r - base) >> part_log2) % P == p:
                            prefetch_row_w(slot, r)
                        else:
                            R[0, c, j] = -1  # not this item's row
            for n in range(n0, n1):
                j = n - n0
                wx = W[0, 0, j]
                wy = W[0, 1, j]
                wz = W[0, 2, j]
                dx = W[0, 3, j]
                dy = W[0, 4, j]
                dz = W[0, 5, j]
                for c in range(8):
                    if R[0, c, j] < 0:
                        continue
                    tx = wx if c & 1 else 1.0 - wx
                    ty = wy if (c >> 1) & 1 else 1.0 - wy
                    tz = wz if c >> 2 else 1.0 - wz
                    sx = 1.0 if c & 1 else -1.0
                    sy = 1.0 if (c >> 1) & 1 else -1.0
                    sz = 1.0 if c >> 2 else -1.0
                    cnt = _acc_sparse_jac(slot, out_rows, out_vals, cb, cnt, R[0, c, j], tx * ty * tz,
                                          dx * sx * ty * tz, dy * tx * sy * tz, dz * tx * ty * sz, g, gj, n, e, F)
        counts[item] = cnt
        for k in range(cnt):
            slot[out_rows[cb + k]] = -1


@njit(parallel=True, cache=True, fastmath=False)
def tri_forward(xn, table, res, scale, offset, lo, hi, stride, hashed, rows, row_off, out, jac):
    """Trilinear multi-level lookup: out[n,e,:] = Σ_c w_c T[r_c, :]  ((N,E,F), written, not accumulated).
    Unless ``jac`` is empty (shape (0,E,F,3)), also writes the input Jacobian jac[n,e,f,a] = ∂out[n,e,f]/∂p̂_a
    ((N,E,F,3), clamped axes 0), so that the input backward is the contraction ``tri_backward_x_jac`` instead of
    a second lookup."""
    N = xn.shape[0]
    E = res.shape[0]
    F = table.shape[1]
    want_jac = jac.shape[0] > 0
    nb = (N + _BLOCK - 1) // _BLOCK
    for b in prange(nb):
        X, I, R, W = _block_scratch(E)
        n0 = b * _BLOCK
        n1 = min(N, n0 + _BLOCK)
        _tri_block(xn, n0, n1, 0, E, res, scale, offset, lo, hi, stride, hashed, rows, row_off, X, I, R, W, table, 1)
        for n in range(n0, n1):
            j = _u(n - n0)
            for e in range(E):
                wx = W[e, 0, j]
                wy = W[e, 1, j]
                wz = W[e, 2, j]
                dx = W[e, 3, j]
                dy = W[e, 4, j]
                dz = W[e, 5, j]
                ux = 1.0 - wx
                uy = 1.0 - wy
                uz = 1.0 - wz
                w0, w1, w2, w3, w4, w5, w6, w7 = _tri_weights(wx, wy, wz)
                r0 = _u(R[e, 0, j])
                r1 = _u(R[e, 1, j])
                r2 = _u(R[e, 2, j])
                r3 = _u(R[e, 3, j])
                r4 = _u(R[e, 4, j])
                r5 = _u(R[e, 5, j])
                r6 = _u(R[e, 6, j])
                r7 = _u(R[e, 7, j])
                for f in range(F):
                    out[n, e, f] = (w0 * table[r0, f] + w1 * table[r1, f] + w2 * table[r2, f]
                                    + w3 * table[r3, f] + w4 * table[r4, f] + w5 * table[r5, f]
                                    + w6 * table[r6, f] + w7 * table[r7, f])
                    if not want_jac:
                        continue
                    q0 = np.float64(table[r0, f])
                    q1 = np.float64(table[r1, f])
                    q2 = np.float64(table[r2, f])
                    q3 = np.float64(table[r3, f])
                    q4 = np.float64(table[r4, f])
                    q5 = np.float64(table[r5, f])
                    q6 = np.float64(table[r6, f])
                    q7 = np.float64(table[r7, f])
                    jac[n, e, f, 0] = dx * (uy * uz * (q1 - q0) + wy * uz * (q3 - q2) + uy * wz * (q5 - q4)
                                            + wy * wz * (q7 - q6))
                    jac[n, e, f, 1] = dy * (ux * uz * (q2 - q0) + wx * uz * (q3 - q1) + ux * wz * (q6 - q4)
                                            + wx * wz * (q7 - q5))
                    jac[n, e, f, 2] = dz * (ux * uy * (q4 - q0) + wx * uy * (q5 - q1) + ux * wy * (q6 - q2)
                                            + wx * wy * (q7 - q3))


@njit(parallel=True, cache=True, fastmath=False)
def tri_forward_jac_hess(xn, table, res, scale, offset, lo, hi, stride, hashed, rows, row_off, out, jac, hess):
    """``tri_forward`` with its Jacobian always, and the mixed second derivatives hess[n,e,f,p] = ∂²out[n,e,f]/∂p̂_a∂p̂_b
    for the pairs p = (xy, xz, yz) ((N,E,F,3); the pure ones are 0, trilinear is linear along each axis):
    ∂²/∂p̂_x∂p̂_y = du_x/dp̂ du_y/dp̂ ((1−w_z)(T3 − T2 − T1 + T0) + w_z(T7 − T6 − T5 + T4)) and likewise, corners
    c = x + 2y + 4z."""
    N = xn.shape[0]
    E = res.shape[0]
    F = table.shape[1]
    nb = (N + _BLOCK - 1) // _BLOCK
    for b in prange(nb):
        X, I, R, W = _block_scratch(E)
        n0 = b * _BLOCK
        n1 = min(N, n0 + _BLOCK)
        _tri_block(xn, n0, n1, 0, E, res, scale, offset, lo, hi, stride, hashed, rows, row_off, X, I, R, W, table, 1)
        for n in range(n0, n1):
            j = _u(n - n0)
            for e in range(E):
                wx = W[e, 0, j]
                wy = W[e, 1, j]
                wz = W[e, 2, j]
                dx = W[e, 3, j]
                dy = W[e, 4, j]
                dz = W[e, 5, j]
                ux = 1.0 - wx
                uy = 1.0 - wy
                uz = 1.0 - wz
                w0, w1, w2, w3, w4, w5, w6, w7 = _tri_weights(wx, wy, wz)
                for f in range(F):
                    q0 = np.float64(table[_u(R[e, 0, j]), f])
                    q1 = np.float64(table[_u(R[e, 1, j]), f])
                    q2 = np.float64(table[_u(R[e, 2, j]), f])
                    q3 = np.float64(table[_u(R[e, 3, j]), f])
                    q4 = np.float64(table[_u(R[e, 4, j]), f])
                    q5 = np.float64(table[_u(R[e, 5, j]), f])
                    q6 = np.float64(table[_u(R[e, 6, j]), f])
                    q7 = np.float64(table[_u(R[e, 7, j]), f])
                    out[n, e, f] = (w0 * q0 + w1 * q1 + w2 * q2 + w3 * q3 + w4 * q4 + w5 * q5 + w6 * q6 + w7 * q7)
                    jac[n, e, f, 0] = dx * (uy * uz * (q1 - q0) + wy * uz * (q3 - q2) + uy * wz * (q5 - q4)
                                            + wy * wz * (q7 - q6))
                    jac[n, e, f, 1] = dy * (ux * uz * (q2 - q0) + wx * uz * (q3 - q1) + ux * wz * (q6 - q4)
                                            + wx * wz * (q7 - q5))
                    jac[n, e, f, 2] = dz * (ux * uy * (q4 - q0) + wx * uy * (q5 - q1) + ux * wy * (q6 - q2)
                                            + wx * wy * (q7 - q3))
                    hess[n, e, f, 0] = dx * dy * (uz * (q3 - q2 - q1 + q0) + wz * (q7 - q6 - q5 + q4))
                    hess[n, e, f, 1] = dx * dz * (uy * (q5 - q4 - q1 + q0) + wy * (q7 - q6 - q3 + q2))
                    hess[n, e, f, 2] = dy * dz * (ux * (q6 - q4 - q2 + q0) + wx * (q7 - q5 - q3 + q1))


@njit(parallel=True, cache=True, fastmath=False)
def hess_backward_x(hess, gj, gx):
    """gx[n,b] += Σ_e Σ_f Σ_{a≠b} gj[n,e,f,a] · hess[n,e,f,pair(a,b)]: the input gradient through the Jacobian
    output, hess (N,E,F,3) the mixed second derivatives (xy, xz, yz), gj (N,E,F,3) (gx (N,3) float64, accumulated)."""
    N = hess.shape[0]
    E = hess.shape[1]
    F = hess.shape[2]
    for n in prange(N):
        ax = 0.0
        ay = 0.0
        az = 0.0
        for e in range(E):
            for f in range(F):
                hxy = np.float64(hess[n, e, f, 0])
                hxz = np.float64(hess[n, e, f, 1])
                hyz = np.float64(hess[n, e, f, 2])
                jx = np.float64(gj[n, e, f, 0])
                jy = np.float64(gj[n, e, f, 1])
                jz = np.float64(gj[n, e, f, 2])
                ax += jy * hxy + jz * hxz
                ay += jx * hxy + jz * hyz
                az += jx * hxz + jy * hyz
        gx[n, 0] += ax
        gx[n, 1] += ay
        gx[n, 2] += az


@njit(parallel=True, cache=True, fastmath=False)
def tri_backward_x_jac(jac, g, gx):
    """gx[n,a] = Σ_e Σ_f g[n,e,f] · jac[n,e,f,a]   (gx (N,3), written; summed in float64, rounded once to gx's
    dtype)."""
    N = jac.shape[0]
    E = jac.shape[1]
    F = jac.shape[2]
    for n in prange(N):
        ax = 0.0
        ay = 0.0
        az = 0.0
        for e in range(E):
            for f in range(F):
                gf = np.float64(g[n, e, f])
                ax += gf * jac[n, e, f, 0]
                ay += gf * jac[n, e, f, 1]
                az += gf * jac[n, e, f, 2]
        gx[n, 0] = ax
        gx[n, 1] = ay
        gx[n, 2] = az


# ---------------------------------------------------------------------------------------------------------------
# Sparse table gradient through a dense accumulator (tables small enough to keep an (M,F) scratch array):
# no per-row slot indirection or first-touch bookkeeping in the hot loop, rows come out sorted (coalesced) by
# ``sparse_rows.drain_marked_rows``.
# ---------------------------------------------------------------------------------------------------------------


@njit(parallel=True, cache=True)
def level_major(g, out):
    """out[e, n, f] = g[n, e, f]: (N,E,F) -> (E,N,F), in blocks of points (parallel)."""
    N = g.shape[0]
    E = g.shape[1]
    F = g.shape[2]
    nb = (N + 255) // 256
    for b in prange(nb):
        n0 = b * 256
        n1 = min(N, n0 + 256)
        for e in range(E):
            for n in range(n0, n1):
                for f in range(F):
                    out[e, n, f] = g[n, e, f]


@njit(parallel=True, cache=True, fastmath=False)
def tri_backward_table_acc(xn, gT, res, scale, offset, lo, hi, stride, hashed, rows, row_off, mark_off, acc, mark):
    """acc[r_c] += w_c gT[e,n] and set the touched bit of r_c for every non-zero-weight corner (parallel over levels,
    points serially in order). gT (E,N,F) is the output gradient level-major, so that a level reads it
    contiguously. acc (M,F) all zero on entry; mark: one bit per row, level e's rows at bytes
    mark_off[e] + (r − row_off[e]) // 8 (bit (r − row_off[e]) % 8; levels never share a byte), all zero on entry
    (a bitmap is 1/64 of an (M,2) float32 table, so it stays in cache; ``sparse_rows.marked_runs`` counts it)."""
    N = xn.shape[0]
    E = res.shape[0]
    F = acc.shape[1]
    for ie in prange(E):
        e = balanced_entry(ie, E)
        base = row_off[e]
        mo = mark_off[e]
        X, I, R, W = _block_scratch(1)
        for n0 in range(0, N, _BLOCK):
            n1 = min(N, n0 + _BLOCK)
            _tri_block(xn, n0, n1, e, e + 1, res, scale, offset, lo, hi, stride, hashed, rows, row_off, X, I, R, W,
                       acc, 2)
            for n in range(n0, n1):
                j = _u(n - n0)
                w = _tri_weights(W[0, 0, j], W[0, 1, j], W[0, 2, j])
                for c in range(8):
                    if w[c] != 0.0:  # zero-weight corner (e.g. a clamped point on the box face): not touched
                        k = R[0, c, j] - base
                        mark[_u(mo + (k >> 3))] |= np.uint8(1 << (k & 7))
                for f in range(F):
                    gv = np.float64(gT[e, _u(n), f])
                    for c in range(8):
                        if w[c] != 0.0:
                            acc[_u(R[0, c, j]), f] += w[c] * gv


@njit(parallel=True, cache=True, fastmath=False)
def tri_backward_table_jac_acc(xn, gT, gj, res, scale, offset, lo, hi, stride, hashed, rows, row_off, mark_off, acc,
                               mark):
    """``tri_backward_table_acc`` for the table gradient of a lookup that also output its Jacobian (second-order
    backward of ``function.MultilinearJacFn``): acc[r_c] += w_c gT[e,n] + Σ_a ∂w_c/∂p̂_a gj[n,e,:,a] (∂w_c/∂p̂_x =
    du_x/dp̂ s_x t_y t_z, s = ±1 the corner's side, t its per-axis weights, and likewise); a corner is touched (its bit
    set) when its weight or a derivative weight is non-zero. Same scratch and bitmap."""
    N = xn.shape[0]
    E = res.shape[0]
    F = acc.shape[1]
    for ie in prange(E):
        e = balanced_entry(ie, E)
        base = row_off[e]
        mo = mark_off[e]
        X, I, R, W = _block_scratch(1)
        for n0 in range(0, N, _BLOCK):
            n1 = min(N, n0 + _BLOCK)
            _tri_block(xn, n0, n1, e, e + 1, res, scale, offset, lo, hi, stride, hashed, rows, row_off, X, I, R, W,
                       acc, 2)
            for n in range(n0, n1):
                j = _u(n - n0)
                wx = W[0, 0, j]
                wy = W[0, 1, j]
                wz = W[0, 2, j]
                dx = W[0, 3, j]
                dy = W[0, 4, j]
                dz = W[0, 5, j]
                for c in range(8):
                    tx = wx if c & 1 else 1.0 - wx
                    ty = wy if (c >> 1) & 1 else 1.0 - wy
                    tz = wz if c >> 2 else 1.0 - wz
                    wt = tx * ty * tz
                    Dx = dx * (1.0 if c & 1 else -1.0) * ty * tz
                    Dy = dy * tx * (1.0 if (c >> 1) & 1 else -1.0) * tz
                    Dz = dz * tx * ty * (1.0 if c >> 2 else -1.0)
                    if wt == 0.0 and Dx == 0.0 and Dy == 0.0 and Dz == 0.0:
                        continue
                    r = R[0, c, j]
                    k = r - base
                    mark[_u(mo + (k >> 3))] |= np.uint8(1 << (k & 7))
                    for f in range(F):
                        acc[_u(r), f] += (wt * np.float64(gT[e, _u(n), f]) + Dx * np.float64(gj[n, e, f, 0])
                                          + Dy * np.float64(gj[n, e, f, 1]) + Dz * np.float64(gj[n, e, f, 2]))
