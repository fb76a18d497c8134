"""Pairing two streams of timestamps one-to-one (colour with depth in a reader, an estimate with the ground truth in
the evaluation): the TUM benchmark's `associate.py` rule."""

from __future__ import annotations

import numpy as np


def associate(ts_a: np.ndarray, ts_b: np.ndarray, max_diff: float = 0.02, offset: float = 0.0
              ) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest-timestamp association (the TUM benchmark's `associate.py` rule).

    All pairs (i, j) with |ts_a[i] − (ts_b[j] + offset)| <= max_diff are candidates (max_diff = 0: equal times);
    they are accepted greedily in order of increasing time difference, each index used at most once. Runs in
    O((N + M) log(N + M) + P) for P candidate pairs (the original benchmark code was O(N²) per call, docs/spec.md
    §13.20).

    Args:
        ts_a: (N,) seconds.  ts_b: (M,) seconds.
        max_diff: seconds, largest |Δt| paired.
        offset: seconds added to ts_b.
    Returns:
        (K,) indices into a and (K,) indices into b, sorted by index into a.
    """
    a = np.asarray(ts_a, dtype=np.float64).ravel()
    b = np.asarray(ts_b, dtype=np.float64).ravel() + offset
    if a.size == 0 or b.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order_b = np.argsort(b, kind="stable")
    bs = b[order_b]
    lo = np.searchsorted(bs, a - max_diff, side="left")
    hi = np.searchsorted(bs, a + max_diff, side="right")
    counts = hi - lo
    ia = np.repeat(np.arange(a.size), counts)
    starts = np.repeat(lo - np.cumsum(counts) + counts, counts)  # position of first candidate of each a
    jb_sorted = np.arange(ia.size) + starts
    diff = np.abs(a[ia] - bs[jb_sorted])
    keep = diff <= max_diff
    ia, jb_sorted, diff = ia[keep], jb_sorted[keep], diff[keep]
    order = np.lexsort((jb_sorted, ia, diff))  # by diff, ties broken by index (deterministic)
    used_a = np.zeros(a.size, dtype=bool)
    used_b = np.zeros(b.size, dtype=bool)
    out_a, out_b = [], []
    for k in order:
        i, j = ia[k], jb_sorted[k]
        if used_a[i] or used_b[j]:
            continue
        used_a[i] = used_b[j] = True
        out_a.append(i)
        out_b.append(order_b[j])
    idx_a = np.asarray(out_a, dtype=np.int64)
    idx_b = np.asarray(out_b, dtype=np.int64)
    srt = np.argsort(idx_a, kind="stable")
    return idx_a[srt], idx_b[srt]
