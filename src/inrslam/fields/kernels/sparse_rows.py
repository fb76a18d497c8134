"""Numba kernels on sparse table rows: de-duplication of a gradient's rows (``unique_rows_sum``), the lazy Adam
update of touched rows (``lazy_adam_rows``), and the assembly of the fused backward's per-entry results into one
unique-row gradient (``compact_entries`` for the row-slot kernels, ``drain_marked_rows`` for the accumulator)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from inrslam.fields.kernels.indexing import BIT_CNT, BIT_POS, balanced_entry, count_marked, mark_words, next_marked_byte
from inrslam.fields.kernels.prefetch import prefetch_row_w


@njit(cache=True)
def unique_rows_sum(rows, vals, slot, out_rows, out_vals):
    """Sum duplicate rows: returns k, with out_rows[:k] unique and out_vals[:k] (pre-zeroed) their sums.
    ``slot`` (M,) int32 or int64 (``function.row_index_dtype``) all −1 on entry and exit. O(nnz), no sort."""
    cnt = 0
    F = vals.shape[1]
    for j in range(rows.shape[0]):
        r = rows[j]
        s = slot[r]
        if s < 0:
            s = cnt
            slot[r] = cnt
            out_rows[cnt] = r
            cnt += 1
        for f in range(F):
            out_vals[s, f] += vals[j, f]
    for k in range(cnt):
        slot[out_rows[k]] = -1
    return cnt


#: Rows prefetched ahead by ``lazy_adam_rows``.
_ADAM_AHEAD = 16


@njit(parallel=True, cache=True, fastmath=False)
def lazy_adam_rows(p, m, v, rows, g, step_size, beta1, beta2, eps, bc2_sqrt):
    """Adam on the given (unique) rows only:
    m_r ← β1 m_r + (1−β1) g_r;  v_r ← β2 v_r + (1−β2) g_r²;  p_r ← p_r − step_size · m_r / (√v_r / √bc2 + ε),
    step_size = lr / (1 − β1^t), bc2 = 1 − β2^t (torch.optim.Adam's formula)."""
    F = p.shape[1]
    K = rows.shape[0]
    for k in prange(K):
        if k + _ADAM_AHEAD < K:  # rows are scattered over a large table: fetch a few rows ahead
            q = rows[k + _ADAM_AHEAD]
            prefetch_row_w(p, q)
            prefetch_row_w(m, q)
            prefetch_row_w(v, q)
        r = rows[k]
        for f in range(F):
            gi = np.float64(g[k, f])
            mi = beta1 * m[r, f] + (1.0 - beta1) * gi
            vi = beta2 * v[r, f] + (1.0 - beta2) * gi * gi
            m[r, f] = mi
            v[r, f] = vi
            p[r, f] -= step_size * mi / (math.sqrt(vi) / bc2_sqrt + eps)


@njit(inline="always", cache=True)
def _exclusive_cumsum(counts):
    """(E+1,) int64 offsets: dst[0] = 0, dst[e+1] = dst[e] + counts[e]."""
    dst = np.zeros(counts.shape[0] + 1, np.int64)
    for e in range(counts.shape[0]):
        dst[e + 1] = dst[e] + counts[e]
    return dst


@njit(parallel=True, cache=True)
def compact_entries(cap_off, counts, out_rows, out_vals, rows_dst, vals_dst):
    """Concatenate the per-entry blocks out_rows/out_vals[cap_off[e] : cap_off[e] + counts[e]] into rows_dst /
    vals_dst (of length Σ counts), entries in order (parallel over entries)."""
    E = counts.shape[0]
    F = out_vals.shape[1]
    dst = _exclusive_cumsum(counts)
    for ie in prange(E):
        e = balanced_entry(ie, E)
        src = cap_off[e]
        d0 = dst[e]
        for k in range(counts[e]):
            rows_dst[d0 + k] = out_rows[src + k]
            for f in range(F):
                vals_dst[d0 + k, f] = out_vals[src + k, f]


#: Bitmap bytes per chunk of ``drain_marked_rows`` (8192: 65536 rows; a fine dense level is ~90 chunks).
DRAIN_CHUNK = 8192


@njit(cache=True)
def _bitmap_chunks(rows, mark_off, chunk):
    """(C, 3) int64 (entry, first byte, end byte): each entry's bitmap bytes mark_off[e] .. + ceil(rows[e] / 8) cut
    into runs of at most `chunk` bytes, entries and runs in order."""
    n = 0
    for e in range(rows.shape[0]):
        n += ((rows[e] + 7) // 8 + chunk - 1) // chunk
    out = np.empty((n, 3), np.int64)
    k = 0
    for e in range(rows.shape[0]):
        end = mark_off[e] + (rows[e] + 7) // 8
        for b in range(mark_off[e], end, chunk):
            out[k, 0] = e
            out[k, 1] = b
            out[k, 2] = min(end, b + chunk)
            k += 1
    return out


@njit(parallel=True, cache=True)
def marked_runs(rows, mark_off, mark, chunk=DRAIN_CHUNK):
    """The accumulator's bitmap (layout of ``tri_backward_table_acc``) as runs of at most `chunk` bytes
    (``_bitmap_chunks``) with their marked rows counted in parallel: (runs (C, 3) int64, dst (C + 1,) int64), dst[c]
    the first output slot of run c and dst[C] the number of marked rows (the sparse gradient's length)."""
    runs = _bitmap_chunks(rows, mark_off, chunk)
    C = runs.shape[0]
    counts = np.empty(C, np.int64)
    for c in prange(C):
        counts[c] = count_marked(mark, runs[c, 1], runs[c, 2])
    return runs, _exclusive_cumsum(counts)


@njit(parallel=True, cache=True)
def drain_marked_rows(row_off, mark_off, acc, mark, runs, dst, rows_dst, vals_dst):
    """Move the marked rows of acc (bitmap layout of ``tri_backward_table_acc``) to rows_dst / vals_dst (length
    dst[-1]; ascending row order) and reset acc and mark to zero there, in parallel over the runs of
    ``marked_runs`` (a fine level holds almost every touched row, so one thread per entry would leave the others
    idle), each run into its own slots from dst: the result depends neither on the run length nor on the thread
    count."""
    F = acc.shape[1]
    C = runs.shape[0]
    words = mark_words(mark)
    for c in prange(C):
        e = runs[c, 0]
        k = dst[c]
        base = row_off[e]
        mo = mark_off[e]
        end = runs[c, 2]
        b = next_marked_byte(mark, words, runs[c, 1], end)
        while b < end:
            m = mark[b]
            mark[b] = 0
            r0 = base + (b - mo) * 8
            for i in range(BIT_CNT[m]):  # the set bits of m, no branch per bit
                r = r0 + BIT_POS[m, i]
                rows_dst[k] = r
                for f in range(F):
                    vals_dst[k, f] = acc[r, f]
                    acc[r, f] = 0.0
                k += 1
            b = next_marked_byte(mark, words, b + 1, end)
