"""Thread counts of the CPU kernels (torch intra-op and numba parallel regions).

Results are bit-identical only at one thread count: a parallel reduction splits its work by thread, so another
count sums in another order. A run therefore *resolves* its count once (`resolve_threads`), records it, and holds
it for its whole length (`thread_scope`), whatever an earlier caller of the same process left set.
"""

from __future__ import annotations

from contextlib import contextmanager

import torch

from inrslam.errors import ConfigError
from inrslam.omp_env import cpu_set


def available_cores() -> int:
    """Cores this process may run on (the affinity mask where the OS has one, else the CPU count)."""
    return len(cpu_set())


def _numba_max() -> int:
    import numba

    # numba.config sets its NUMBA_* names at import (from the environment), so mypy cannot see them
    return int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]


def resolve_threads(requested: int) -> int:
    """The thread count a run uses: `requested`, or every available core for 0, capped by numba's pool size."""
    if requested < 0:
        raise ConfigError(f"config key 'threads': expected a count >= 0 (0 = every core), got {requested}")
    n = int(requested) if requested else available_cores()
    return max(1, min(n, _numba_max()))


def current_threads() -> dict:
    """{'torch': n, 'numba': n} as set in this thread now."""
    import numba

    return {"torch": torch.get_num_threads(), "numba": int(numba.get_num_threads())}


def set_threads(n: int) -> None:
    """Set torch and numba to `n` threads in the calling thread (numba's count is per calling thread)."""
    import numba

    n = max(1, int(n))
    torch.set_num_threads(n)
    numba.set_num_threads(min(n, _numba_max()))


@contextmanager
def thread_scope(n: int):
    """Run a block at exactly `n` torch / numba threads, then restore the counts found on entry."""
    import numba

    before = current_threads()
    set_threads(n)
    try:
        yield n
    finally:
        torch.set_num_threads(before["torch"])
        numba.set_num_threads(min(before["numba"], _numba_max()))
