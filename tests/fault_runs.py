"""Sweep run functions for the fault-injection tests (`tests/test_faults.py`), importable by the worker processes of
a `python -m inrslam.cli bench` subprocess (PYTHONPATH includes tests/; selected with INRSLAM_BENCH_RUN_FN).

Both write a fake complete run (`inrslam.bench.testing.write_fake_run`) for seed 0. For other seeds
`fail_other_seeds` raises and `hang_other_seeds` writes its process id into `<run_dir>/started` and then sleeps
until interrupted. `deaf_to_sigterm` is a worker process that ignores SIGTERM.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from inrslam.bench.testing import write_fake_run

HANG_S = 120.0


def _fake(run: dict, run_dir: Path) -> dict:
    write_fake_run(run_dir, run["encoding"], run["render"], run["scene"], run["seed"])
    return {"fake": True}


def fail_other_seeds(run: dict, run_dir: Path) -> dict:
    if run["seed"] != 0:
        raise RuntimeError(f"injected failure of {run['name']}")
    return _fake(run, run_dir)


def hang_other_seeds(run: dict, run_dir: Path) -> dict:
    if run["seed"] != 0:
        (Path(run_dir) / "started").write_text(f"{os.getpid()}\n")
        end = time.monotonic() + HANG_S
        while time.monotonic() < end:  # short sleeps, as a run computes: a signal the process took on another
            time.sleep(0.05)  # thread runs its Python handler when the main thread next runs Python
    return _fake(run, run_dir)


def deaf_to_sigterm(ready) -> None:
    """A worker that ignores SIGTERM and sleeps (as one blocked in a long call would take it late)."""
    import signal

    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    ready.set()
    time.sleep(HANG_S)
