"""Inline numba helpers shared by the kernel families: the table row of a vertex, the order in which parallel
loops deal entries to threads, and the byte tables and scan of the touched-row bitmap (see ``layout.py`` for the maths).

numba's on-disk cache (``cache=True``) is invalidated only by edits to a kernel's own file, not to the helpers it
inlines from here (or from ``prefetch.py``): after editing this file, delete the kernels' cache files
(``__pycache__/{generic,trilinear,sparse_rows}.*.nb[ic]``, and ``slam/ehe/__pycache__/sdf_kernel.*.nb[ic]``, whose
kernels inline the trilinear corner rule and the decoder's ReLU helpers).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: The hash primes of axes y and z (``layout.PRIMES``; axis x's is 1), as int64 constants of the kernels.
P1 = np.int64(2654435761)
P2 = np.int64(805459861)


@njit(inline="always", cache=True)
def vertex_row(hashed, nrows, i0, i1, i2, s0, s1, s2):
    """Row (relative to the entry) of integer vertex (i0, i1, i2)."""
    if hashed:
        return (i0 ^ (i1 * P1) ^ (i2 * P2)) & (nrows - 1)
    return i0 * s0 + i1 * s1 + i2 * s2


@njit(inline="always", cache=True)
def balanced_entry(i, E):
    """Entry handled by iteration i of a ``prange(E)``: 0, E−1, 1, E−2, … so that numba's static contiguous
    chunks give every thread a mix of coarse (cheap) and fine (cache-missing) levels."""
    if i % 2 == 0:
        return i // 2
    return E - 1 - i // 2


#: Set bits of every byte value: BIT_CNT[m] of them, at positions BIT_POS[m, :BIT_CNT[m]] (ascending).
BIT_CNT = np.array([bin(m).count("1") for m in range(256)], np.int64)
BIT_POS = np.array([[b for b in range(8) if (m >> b) & 1] + [0] * (8 - bin(m).count("1")) for m in range(256)],
                    np.int64)


@njit(inline="always", cache=True)
def next_marked_byte(mark, words, b, end):
    """The first index in [b, end) whose bitmap byte mark[i] is non-zero, else end. ``words`` is mark's first
    ⌊len/8⌋·8 bytes viewed as uint64: an 8-aligned all-zero word is passed in one read (a table's touched rows are
    a few per cent of its rows, so most words are zero)."""
    while b < end:
        if (b & 7) == 0 and b + 8 <= end and words[b >> 3] == 0:
            b += 8
            continue
        if mark[b] != 0:
            return b
        b += 1
    return end


@njit(inline="always", cache=True)
def mark_words(mark):
    """mark (uint8, contiguous) as uint64 words over its first ⌊len/8⌋·8 bytes, for ``next_marked_byte``."""
    return mark[: mark.shape[0] - mark.shape[0] % 8].view(np.uint64)


@njit(inline="always", cache=True)
def count_marked(mark, b0, b1):
    """Set bits of the bitmap bytes mark[b0:b1] (zero 8-byte words skipped)."""
    words = mark_words(mark)
    c = 0
    b = next_marked_byte(mark, words, b0, b1)
    while b < b1:
        c += BIT_CNT[mark[b]]
        b = next_marked_byte(mark, words, b + 1, b1)
    return c
