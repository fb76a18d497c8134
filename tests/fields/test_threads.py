"""Thread counts: a run holds one resolved count and gives the caller's back (issue: flaky resume test)."""

from __future__ import annotations

import os

import numba
import pytest

from inrslam.bench.worker import run_one
from inrslam.errors import ConfigError
from inrslam.fields.kernels.threads import available_cores, current_threads, resolve_threads, thread_scope


def test_resolve_threads_zero_means_every_core_and_rejects_negative():
    assert resolve_threads(0) == min(available_cores(), numba.config.NUMBA_NUM_THREADS)
    assert resolve_threads(1) == 1
    assert resolve_threads(10_000) == numba.config.NUMBA_NUM_THREADS  # capped by numba's pool
    with pytest.raises(ConfigError, match="'threads'"):
        resolve_threads(-1)


def test_thread_scope_sets_both_counts_and_restores_them():
    before = current_threads()
    with thread_scope(1):
        assert current_threads() == {"torch": 1, "numba": 1}
    assert current_threads() == before


def test_thread_scope_restores_after_an_exception():
    before = current_threads()
    with pytest.raises(RuntimeError):
        with thread_scope(1):
            raise RuntimeError("boom")
    assert current_threads() == before


def test_sweep_worker_leaves_thread_counts_and_environment_as_it_found_them(tmp_path):
    """The cause of the flaky resume test: `run_one(..., threads=1)` left numba at 1 thread and OMP_NUM_THREADS=1
    in the environment, so later in-process runs (and the subprocesses they start) summed in another order."""
    run = {"name": "r__dense__g__p__s0", "scene": "r", "scene_path": "builtin:r", "encoding": "dense", "render": "g",
           "preset": "p", "seed": 0, "overrides": {}}
    before, env = current_threads(), {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")}
    res = run_one(run, str(tmp_path), run_fn="inrslam.bench.testing:fake_run", threads=1)
    assert res["status"] == "complete"
    assert current_threads() == before
    assert {v: os.environ.get(v) for v in env} == env
