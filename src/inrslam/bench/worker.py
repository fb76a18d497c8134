"""The per-run function every executor calls: `run_one(run, out_dir) -> {status, run_dir, error, ...}`.

It never raises but for an interrupt: a failing run writes `<run_dir>/error.txt` (full traceback) and returns status
"failed", so one bad combination cannot stop a sweep; Ctrl-C / SIGTERM (`Terminated`) are recorded the same way and
then raised again (the executor decides: the sweep's own interrupt stops it, a signal to one worker fails its run).
The SLAM work itself is done by a *run function* `fn(run: dict, run_dir: Path)`, by default `slam_run` (fresh
`run_slam`, or `resume_slam` when the directory holds a checkpoint). Tests inject a cheap one by dotted path
(`run_fn="inrslam.bench.testing:fake_run"` or the env var INRSLAM_BENCH_RUN_FN).
"""

from __future__ import annotations

import importlib
import os
import sys
import time
import traceback
from contextlib import ExitStack
from pathlib import Path
from typing import Callable

from inrslam.errors import RunError
from inrslam.interrupts import defer_interrupts_in_jit
from inrslam.io.rundir import RunDir

RUN_FN_ENV = "INRSLAM_BENCH_RUN_FN"
THREADS_ENV = "INRSLAM_BENCH_THREADS"
DEFAULT_RUN_FN = "inrslam.bench.worker:slam_run"


def resolve_run_fn(run_fn: str | Callable | None = None) -> Callable:
    """'pkg.module:function' (or 'pkg.module.function') -> the function; None -> env var or the SLAM run."""
    if callable(run_fn):
        return run_fn
    path = run_fn or os.environ.get(RUN_FN_ENV) or DEFAULT_RUN_FN
    mod, sep, name = path.partition(":")
    if not sep:
        mod, _, name = path.rpartition(".")
    return getattr(importlib.import_module(mod), name)


def fn_path(fn: str | Callable | None) -> str | None:
    """A module-level function -> its 'module:name' path (strings and None pass through)."""
    if fn is None or isinstance(fn, str):
        return fn
    return f"{fn.__module__}:{fn.__qualname__}"


def set_threads(n: int) -> None:
    """Limit torch / numba / OpenMP threads of this process to `n`."""
    n = max(1, int(n))
    os.environ[THREADS_ENV] = str(n)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(n)
    if "numba" in sys.modules:
        import numba

        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    else:
        os.environ["NUMBA_NUM_THREADS"] = str(n)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(n)


_THREAD_VARS = (THREADS_ENV, "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


def _thread_state() -> dict:
    """This process's thread settings: the environment variables `set_threads` changes, torch's and numba's counts."""
    state = {"env": {v: os.environ.get(v) for v in _THREAD_VARS}}
    if "torch" in sys.modules:
        state["torch"] = sys.modules["torch"].get_num_threads()
    if "numba" in sys.modules:
        state["numba"] = sys.modules["numba"].get_num_threads()
    return state


def _restore_thread_state(state: dict) -> None:
    for var, val in state["env"].items():
        if val is None:
            os.environ.pop(var, None)
        else:
            os.environ[var] = val
    if "torch" in state:
        sys.modules["torch"].set_num_threads(state["torch"])
    if "numba" in state:
        sys.modules["numba"].set_num_threads(state["numba"])


def slam_run(run: dict, run_dir: Path) -> dict:
    """Default run function: resume a checkpointed partial run, else start it over (overwrite)."""
    from inrslam import runner as slam
    from inrslam.bench.spec import RunSpec, resolve_config

    if RunDir(run_dir).has_checkpoint():
        slam.resume_slam(run_dir, progress=None)  # at the thread count its run_info.json records
        return {"resumed": True}
    cfg = resolve_config(RunSpec.from_dict(run))
    # the executor's per-job share of the cores, unless the run's config sets its own count
    threads = int(os.environ[THREADS_ENV]) if not cfg.threads and os.environ.get(THREADS_ENV) else None
    slam.run_slam(cfg, run_dir, progress=None, overwrite=True, threads=threads)
    return {"resumed": False}


def run_one(run: dict, out_dir: str, run_fn: str | None = None, threads: int | None = None) -> dict:
    """Run one sweep combination into `out_dir/run['name']`; never raises, but for Ctrl-C / SIGTERM (after recording
    them).

    Returns {name, status ("complete" | "skipped" | "failed"), run_dir, error (one line or None), seconds, pid};
    `busy` True when another process holds the run's folder (`RunDir.lock`), which is then left as it is.
    """
    from inrslam.io.atomic import write_json, write_text

    run_dir = Path(out_dir) / run["name"]
    rd = RunDir(run_dir)
    result = {"name": run["name"], "run_dir": str(run_dir), "error": None, "pid": os.getpid(), "seconds": 0.0}
    if rd.is_complete():
        return {**result, "status": "skipped"}
    t0 = time.perf_counter()
    saved = _thread_state()  # in-process runs give the caller its thread counts and environment back
    try:
        with ExitStack() as stack:
            try:  # before any file is touched: another process may be running this run (the runner re-enters it)
                stack.enter_context(rd.lock())
            except RunError as e:  # its folder is left alone: no bench.json, no error.txt
                return {**result, "status": "failed", "busy": True, "error": str(e)}
            rd.error.unlink(missing_ok=True)
            write_json(rd.bench, run)
            set_threads(threads or os.cpu_count() or 1)
            # in a worker process: Ctrl-C / SIGTERM (the executor stopping its workers) end the frame in progress,
            # which is saved (`inrslam.runner`); a handler already set (the CLI's, a scheduler's) is kept
            stack.enter_context(defer_interrupts_in_jit())
            extra = resolve_run_fn(run_fn)(run, run_dir)
            if not rd.is_complete():
                info = rd.read_run_info() or {}
                raise RuntimeError(f"the run function returned but {run_dir} is not complete "
                                   f"(run_info status {info.get('status')!r}, metrics.json "
                                   f"{'present' if rd.metrics.is_file() else 'missing'})")
            result.update(extra if isinstance(extra, dict) else {})
            result["status"] = "complete"
    except BaseException as e:  # noqa: BLE001 - a sweep records every failure, including KeyboardInterrupt in a worker
        tb = traceback.format_exc()
        try:
            write_text(rd.error, tb)
        except OSError:
            pass
        result.update(status="failed", error=f"{type(e).__name__}: {e}".splitlines()[0][:500])
        if isinstance(e, KeyboardInterrupt):
            raise
    finally:
        _restore_thread_state(saved)
    result["seconds"] = time.perf_counter() - t0
    return result
