"""The OpenMP wait policy chosen at `import inrslam` (fresh interpreters: the policy only counts before torch loads)
and the guard that adapts it to the machine's load while a run computes (`inrslam.omp_env`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import pytest
import torch

from inrslam import omp_env
from inrslam.omp_env import CpuSample, LoadGuard, next_state, other_load, parse_proc_stat

PROBE = ("import json, os, sys\n{pre}import inrslam\nfrom inrslam.omp_env import wait_policy\n"
         "print(json.dumps([os.environ.get('OMP_WAIT_POLICY'), wait_policy()]))")
LIBGOMP = sys.platform.startswith("linux") and omp_env._torch_runtime_is_libgomp()


def probe(pre: str = "", **env: str) -> list:
    e = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "INRSLAM_OMP_WAIT")} | env
    out = subprocess.run([sys.executable, "-c", PROBE.format(pre=pre)], env=e, capture_output=True, text=True,
                         check=True).stdout
    return json.loads(out)


def test_import_adapts_where_torch_uses_libgomp_and_waits_passively_elsewhere():
    env, info = probe()
    if LIBGOMP:
        assert env is None and info["set_by"] == "inrslam (adaptive)" and info["adaptive"] is True
    else:
        assert env == "PASSIVE" and info["set_by"] == "inrslam" and info["adaptive"] is False


def test_passive_on_request():
    env, info = probe(INRSLAM_OMP_WAIT="passive")
    assert env == "PASSIVE" and info["policy"] == "PASSIVE" and info["set_by"] == "inrslam" and not info["adaptive"]


def test_a_users_policy_is_kept_and_not_adapted():
    env, info = probe(OMP_WAIT_POLICY="ACTIVE")
    assert env == "ACTIVE" and info["policy"] == "ACTIVE" and info["set_by"] == "user" and not info["adaptive"]


def test_torch_loaded_first_keeps_the_runtime_default_says_so_and_still_adapts():
    env, info = probe(pre="import torch\n")
    assert env is None and info["policy"] is None and "torch imported before inrslam" in info["set_by"]
    assert info["adaptive"] is True


def test_the_runtime_default_on_request_is_never_throttled():
    env, info = probe(INRSLAM_OMP_WAIT="runtime")
    assert env is None and info["policy"] is None and info["set_by"] == "runtime default (INRSLAM_OMP_WAIT=runtime)"
    assert info["adaptive"] is False


STAT = """cpu  900 0 300 5000 10 0 0 0 0 0
cpu0 100 5 50 2000 7 3 2 1 0 0
cpu1 200 0 60 2000 3 0 4 0 0 0
cpu2 400 0 90 1000 0 0 0 0 0 0
intr 12345
ctxt 678
"""


def test_proc_stat_busy_time_of_the_allowed_cores_only():
    # cpu0: user 100 + nice 5 + system 50 + irq 3 + softirq 2 + steal 1 = 161 ticks (idle and iowait excluded)
    assert parse_proc_stat(STAT, {0}, 100.0) == pytest.approx(1.61)
    assert parse_proc_stat(STAT, {0, 1}, 100.0) == pytest.approx(1.61 + 2.64)
    assert parse_proc_stat(STAT, {1, 2}, 50.0) == pytest.approx((264 + 490) / 50)
    assert parse_proc_stat(STAT, {7}, 100.0) is None
    assert parse_proc_stat("garbage\n", {0}, 100.0) is None


def test_other_processes_load_is_busy_time_minus_our_own_per_second():
    a = CpuSample(wall=10.0, busy=100.0, own=40.0)
    # 2 s: the cores were busy 3.5 s, 1.5 of them ours: others used 2.0 s, i.e. 1.0 core
    assert other_load(a, CpuSample(12.0, 103.5, 41.5)) == pytest.approx(1.0)
    assert other_load(a, CpuSample(12.0, 101.0, 41.5)) == 0.0  # accounting jitter: never negative
    assert other_load(a, CpuSample(10.0, 105.0, 40.0)) == 0.0  # no time elapsed


def test_hysteresis_engages_at_once_and_releases_after_calm_samples():
    state, seen = (False, 0), []
    loads = [0.1, 0.6, 0.3, 0.1, 0.1, 0.1, 0.4, 0.1, 0.1, 0.1, 0.1, 0.2, 0.9]
    for load in loads:
        state = next_state(*state, load)
        seen.append(state[0])
    # 0.6 engages; 0.3 (between the thresholds) is not calm; 0.4 resets the calm count; 4 calm samples release
    assert seen == [False, True, True, True, True, True, True, True, True, True, False, False, True]
    assert omp_env.RELEASE_SAMPLES == 4 and omp_env.RELEASE_LOAD < omp_env.ENGAGE_LOAD


def _threads() -> int:
    return len(os.listdir("/proc/self/task"))


def _wait_for(cond, timeout=5.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


libgomp_only = pytest.mark.skipif(not LIBGOMP, reason="the ballast acts on GNU libgomp (Linux torch wheels) only")


@libgomp_only
def test_the_ballast_adds_sleeping_threads_to_every_libgomp_and_frees_them():
    torch.ones(1 << 20).sum()  # torch's libgomp has its pool
    libs = omp_env.loaded_libgomp()
    assert libs and all("libgomp" in os.path.basename(p) for p in libs)
    before = _threads()
    ballast = omp_env.Ballast(libs, 3).start()
    assert ballast.held == libs
    # per runtime: a team of 3 started from the ballast's thread = 2 new pool threads; plus the ballast thread
    assert _threads() == before + 1 + 2 * len(libs)
    ballast.stop()
    assert _wait_for(lambda: _threads() == before)


@libgomp_only
def test_the_guard_holds_a_ballast_while_others_load_the_machine():
    torch.ones(1 << 20).sum()
    loads = iter([0.0, 1.0, 1.0, 0.1, 0.1, 0.1, 0.1] + [0.0] * 1000)  # cores of others per interval
    clock = {"t": 0.0, "busy": 0.0}
    engaged_seen = []

    def sample():
        clock["t"] += 1.0
        clock["busy"] += next(loads)
        return CpuSample(clock["t"], clock["busy"], 0.0)

    guard = LoadGuard(sample=sample, interval=0.01)
    orig = guard.engage

    def engage():
        orig()
        engaged_seen.append(guard.throttled)

    guard.engage = engage  # type: ignore[method-assign]
    guard.enter()
    assert _wait_for(lambda: guard.samples >= 20)
    guard.exit()
    # the first reading is the baseline; the loads 1.0, 1.0 engage, then 4 calm samples release
    assert engaged_seen and all(engaged_seen)
    assert guard.switches == 1 and guard.throttled_samples == 5 and not guard.throttled


def test_the_guard_is_a_no_op_without_the_adaptive_policy(monkeypatch):
    monkeypatch.setattr(omp_env, "_adaptive", False)
    before = threading.active_count()
    with omp_env.load_guard() as guard:
        assert threading.active_count() == before and guard._thread is None
