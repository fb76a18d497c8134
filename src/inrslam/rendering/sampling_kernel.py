"""Depth-guided ray samples in one numba pass (CPU): `sampling.sample_depths` without its ~15 small tensor operations
per call (1.5 ms for a tracking batch of 1024 rays x 60 samples, most of it per-operation overhead; 0.8 ms here:
`benchmarks/bench_losses.py`).

Bit-identical to the torch path it replaces (the tests compare with `torch.equal`): every float operation is the
same one in the same dtype and order (torch rounds a Python scalar operand to the tensor's dtype first, so the
constants come in that dtype; no fused multiply-add, numba's default), the two sorted sample sets of a ray are
merged instead of sorted (the same values in the same order; a ray with an infinite depth, whose samples hold a NaN,
is sorted NaN-last as torch sorts), and the jitter's uniforms are drawn by torch from the
caller's generator before the call, so the random stream is unchanged.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(parallel=True, cache=True)
def depth_guided_samples(depth, t_far, lin_free, offs, lin_all, near, far_factor, half, zero, u, jitter,
                         out):  # pragma: no cover - numba
    """Samples out (R, S) of rays with depth (`lin_free` (n_free,) free-space fractions, `offs` (n_surf,) offsets
    around the depth, metres) and without (`t_far` (R,) metres, `lin_all` (S,) fractions); then, with `jitter`, each
    sample moved within its stratum by `u` (R, S) uniforms. Scalars near, far_factor, half (0.5), zero in the dtype
    (a Python constant would widen the arithmetic to float64 and round differently)."""
    R, S = out.shape
    nf, ns = lin_free.shape[0], offs.shape[0]
    for r in prange(R):
        d = depth[r]
        if d > 0:
            span = far_factor * d - near
            if span < zero:
                span = zero  # clamp_min(0.0)
            if not d < np.inf:  # an infinite depth: NaN and inf samples, sorted as torch sorts them (NaN last)
                for k in range(nf):
                    out[r, k] = near + span * lin_free[k]
                for k in range(ns):
                    out[r, nf + k] = max(d + offs[k], near)
                out[r, :] = np.sort(out[r, :])
            else:
                i, j = 0, 0
                a = near + span * lin_free[0] if nf > 0 else np.inf
                b = max(d + offs[0], near) if ns > 0 else np.inf
                for k in range(S):  # merge the two ascending sets
                    if a <= b:
                        out[r, k] = a
                        i += 1
                        a = near + span * lin_free[i] if i < nf else np.inf
                    else:
                        out[r, k] = b
                        j += 1
                        b = max(d + offs[j], near) if j < ns else np.inf
        else:
            for k in range(S):
                out[r, k] = near + (t_far[r] - near) * lin_all[k]
        if jitter:
            lower = out[r, 0]
            for k in range(S):
                upper = half * (out[r, k + 1] + out[r, k]) if k < S - 1 else out[r, k]
                out[r, k] = lower + u[r, k] * (upper - lower)
                lower = upper
