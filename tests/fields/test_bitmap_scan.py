"""The touched-row bitmap of the accumulator table backward, scanned a uint64 word at a time: `next_marked_byte`,
the count and the drain (in runs of bitmap bytes, counted and drained in parallel) against numpy on random sparse
bitmaps whose ranges start and end off word boundaries."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from inrslam.fields.kernels.indexing import count_marked, mark_words, next_marked_byte
from inrslam.fields.kernels.sparse_rows import drain_marked_rows, marked_runs


@njit(cache=False)
def _marked(mark, b0, b1):
    """Every index `next_marked_byte` visits in [b0, b1), in order."""
    words = mark_words(mark)
    out = []
    b = next_marked_byte(mark, words, b0, b1)
    while b < b1:
        out.append(b)
        b = next_marked_byte(mark, words, b + 1, b1)
    return out


def sparse_bitmap(n: int, density: float, rng: np.random.Generator) -> np.ndarray:
    """n bytes, a `density` share of them non-zero, in short runs (touched rows cluster along rays)."""
    mark = np.zeros(n, np.uint8)
    starts = rng.choice(n, max(1, int(density * n / 3)), replace=False)
    for s in starts:
        run = mark[s:s + int(rng.integers(1, 6))]
        run[:] = rng.integers(1, 256, size=len(run))
    return mark


@pytest.mark.parametrize("seed", range(4))
def test_the_scan_visits_exactly_the_non_zero_bytes_and_counts_their_bits(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 3000))  # not a multiple of 8 in general
    mark = sparse_bitmap(n, float(rng.choice([0.0, 0.01, 0.1, 0.6])), rng)
    for _ in range(20):
        b0, b1 = sorted(int(v) for v in rng.integers(0, n + 1, 2))
        expect = [b for b in range(b0, b1) if mark[b]]
        assert _marked(mark, b0, b1) == expect
        assert count_marked(mark, b0, b1) == int(np.unpackbits(mark[b0:b1]).sum())


@pytest.mark.parametrize("chunk", [1, 3, 8, 4096])
def test_the_drain_moves_every_marked_row_of_each_entry_in_order_and_clears_them(chunk):
    """Any run length: runs of 1 and 3 bytes start and end off the scan's 8-byte words and split entries."""
    rng = np.random.default_rng(7)
    rows = np.array([13, 1, 77, 250], np.int64)  # entries of odd sizes: their bitmaps start mid-word
    row_off = np.concatenate([[0], np.cumsum(rows)[:-1]])
    nbytes = (rows + 7) // 8
    mark_off = np.concatenate([[0], np.cumsum(nbytes)[:-1]])
    mark = np.zeros(int(nbytes.sum()), np.uint8)
    acc = np.zeros((int(rows.sum()), 2), np.float32)
    touched = []
    for e in range(len(rows)):
        for r in rng.choice(rows[e], size=min(rows[e], int(rng.integers(0, 20))), replace=False):
            k = int(r)
            mark[mark_off[e] + k // 8] |= np.uint8(1 << (k % 8))
            acc[row_off[e] + k] = rng.normal(size=2)
            touched.append(int(row_off[e] + k))
    touched.sort()
    expect_vals = acc[touched].copy()
    rows_dst = np.empty(len(touched), np.int64)
    vals_dst = np.empty((len(touched), 2), np.float32)
    runs, dst = marked_runs(rows, mark_off, mark, chunk)
    assert dst[-1] == len(touched) and np.all(np.diff(dst) >= 0)
    drain_marked_rows(row_off, mark_off, acc, mark, runs, dst, rows_dst, vals_dst)
    assert rows_dst.tolist() == touched
    np.testing.assert_array_equal(vals_dst, expect_vals)
    assert not mark.any() and not acc.any()


@pytest.mark.parametrize("threads", [1, 2])
def test_the_drain_of_a_large_sparse_level_is_the_same_on_any_thread_count(threads):
    """A level of many runs (the fine dense level's case): every marked row, ascending, whatever the threads."""
    import numba

    rng = np.random.default_rng(3)
    rows = np.array([40, 300_001], np.int64)
    row_off = np.array([0, 40], np.int64)
    nbytes = (rows + 7) // 8
    mark_off = np.array([0, nbytes[0]], np.int64)
    mark = np.zeros(int(nbytes.sum()), np.uint8)
    acc = np.zeros((int(rows.sum()), 3), np.float64)
    touched = np.unique(rng.integers(0, int(rows.sum()), 20_000))
    for t in touched:
        e = int(t >= 40)
        k = int(t - row_off[e])
        mark[mark_off[e] + k // 8] |= np.uint8(1 << (k % 8))
    acc[touched] = rng.normal(size=(len(touched), 3))
    expect_vals = acc[touched].copy()
    rows_dst = np.empty(len(touched), np.int64)
    vals_dst = np.empty((len(touched), 3), np.float64)
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        runs, dst = marked_runs(rows, mark_off, mark, 512)
        drain_marked_rows(row_off, mark_off, acc, mark, runs, dst, rows_dst, vals_dst)
    finally:
        numba.set_num_threads(before)
    np.testing.assert_array_equal(rows_dst, touched)
    np.testing.assert_array_equal(vals_dst, expect_vals)
    assert not mark.any() and not acc.any()
