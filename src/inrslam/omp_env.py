"""OpenMP wait policy of the CPU kernels, chosen before torch / numba load their OpenMP runtime.

By default an OpenMP thread that reaches a barrier first *spins* for a while instead of sleeping. Alone on a
machine that saves a wake-up; beside another CPU-bound process it is a collapse: the spinning thread holds a core
the descheduled thread it waits for needs (measured on 2 cores: 2.6x slower per frame with one busy process, 5x
with two). A passive policy sleeps at once (the same beside one busy process: 1.25x; two: 1.5x). The runtime reads
the policy once, when it loads, so it is set here, at `import inrslam`, unless the user set `OMP_WAIT_POLICY`
(respected as given), asked for the runtime's default with `INRSLAM_OMP_WAIT=runtime` (alone on a machine it is
10-25 % faster per frame: benchmarks/bench_contention.py), or torch was imported first (then the runtime's default
stays; `wait_policy()` says so). The policy changes when threads sleep, never how work is split: results are the
same under either.
"""

from __future__ import annotations

import os
import sys

ENV = "OMP_WAIT_POLICY"
OPT_OUT = "INRSLAM_OMP_WAIT"  # "runtime": leave the OpenMP runtime's default (spin, then sleep)
DEFAULT = "PASSIVE"
_origin = "unset"


def apply_wait_policy() -> str:
    """Set OMP_WAIT_POLICY=PASSIVE if nobody chose one and no OpenMP runtime is loaded yet; returns how it was set
    ("inrslam", "user", "runtime default (INRSLAM_OMP_WAIT=runtime)" or "runtime default (torch imported before
    inrslam)")."""
    global _origin
    if ENV in os.environ:
        _origin = "user" if _origin != "inrslam" else _origin
    elif os.environ.get(OPT_OUT, "").lower() == "runtime":
        _origin = f"runtime default ({OPT_OUT}=runtime)"
    elif "torch" in sys.modules or "numba" in sys.modules:
        _origin = "runtime default (torch imported before inrslam)"
    else:
        os.environ[ENV] = DEFAULT
        _origin = "inrslam"
    return _origin


def wait_policy() -> dict:
    """{'policy': the OMP_WAIT_POLICY in effect (None: the runtime's default, spinning), 'set_by': who set it}."""
    return {"policy": os.environ.get(ENV), "set_by": _origin}
