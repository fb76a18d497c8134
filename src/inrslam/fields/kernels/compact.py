"""The points of a table backward that carry gradient: a table's lazy Adam can update only the rows with a non-zero
gradient contribution (`TouchedRows.GRADIENT`) instead of every row read with a non-zero weight, and the backward
then skips the rest (samples behind a surface that no loss term reaches, e.g. EHE's, docs/ehe.md §5).

The reference is `nonzero_points_torch` (boolean indexing); the kernel gives the same arrays (a gather, no
arithmetic).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit


@njit(cache=True)
def _nonzero_points(xn, g, xn_out, g_out):  # pragma: no cover - numba
    """Copy the points n with any g[n] != 0 (NaN counts as non-zero) to the front of xn_out / g_out, in order;
    returns how many."""
    N = g.shape[0]
    K = g.shape[1]
    D = xn.shape[1]
    m = 0
    for n in range(N):
        keep = False
        for k in range(K):
            if g[n, k] != 0.0:  # NaN != 0: kept, so that a NaN gradient still reaches the table
                keep = True
                break
        if keep:
            for a in range(D):
                xn_out[m, a] = xn[n, a]
            for k in range(K):
                g_out[m, k] = g[n, k]
            m += 1
    return m


def nonzero_points(xn: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(xn[keep], g[keep]) for the points whose output gradient is not all zero, in order.

    Args: xn (N, 3) points (any float dtype), g (N, ...) their output gradient. Returns C-contiguous copies
    (the inputs themselves when every point is kept)."""
    N = g.shape[0]
    if N == 0:
        return xn, g  # nothing to keep (and numpy cannot infer the -1 of an empty reshape)
    g2 = g.reshape(N, -1)
    xn_out = np.empty_like(xn)
    g_out = np.empty_like(g2)
    m = _nonzero_points(xn, g2, xn_out, g_out)
    if m == N:
        return xn, g
    return xn_out[:m], g_out[:m].reshape((m,) + g.shape[1:])


def nonzero_points_torch(xn: torch.Tensor, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference of `nonzero_points`: boolean indexing on the points with any non-zero (or NaN) gradient."""
    keep = (g.reshape(g.shape[0], -1) != 0).any(dim=1)
    return xn[keep], g[keep]
