"""Subnormal floats in the fused kernels' backward passes.

Volume rendering makes gradients far below float32's smallest normal number (1.2e-38): samples well behind the
surface get weights below exp(-87), and so do their colour and SDF gradients. x86 CPUs compute with such subnormal
operands tens of times slower than with normal ones; in a `paper` tracking iteration about 2.6 % of the decoders'
output gradients are subnormal, and the decoder's backward took 1.4-4x longer than with them set to zero
(docs/speed.md, "Subnormal gradients in the fused kernels"). The fused backward kernels therefore count a
subnormal gradient as zero where it enters (and the decoders' input gradient where it leaves). Such a gradient moves
no float32 parameter of magnitude above about 1e-30 in an optimiser step, so results change in their last bits at
most — as the fused kernels' rounding already does — and the reference path (`paper`) is untouched.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def tiny_of(dtype) -> float:
    """The smallest normal number of a numpy float dtype: 1.2e-38 for float32, 2.2e-308 for float64."""
    return float(np.finfo(dtype).tiny)


@njit(inline="always", cache=True)
def flushed(v, tiny):  # pragma: no cover - numba
    """v, or zero if it is subnormal (0 < |v| < tiny); NaN and infinities stay."""
    if abs(v) < tiny:
        return v * 0.0
    return v


@njit(inline="always", cache=True)
def flush_inplace(a, tiny):  # pragma: no cover - numba
    """a (m, n) <- 0 where subnormal (NaN and infinities stay)."""
    for k in range(a.shape[0]):
        for j in range(a.shape[1]):
            if abs(a[k, j]) < tiny:
                a[k, j] = 0.0
