"""The OpenMP wait policy chosen at `import inrslam` (fresh interpreters: the policy only counts before torch loads)
and the guard that adapts it to the machine's load while a run computes (`inrslam.omp_env`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading

import pytest
import torch
from polling import wait_for

from inrslam import omp_env
from inrslam.omp_env import CpuSample, LoadGuard, next_state, other_load, parse_proc_stat

PROBE = ("import json, os, sys\n{pre}import inrslam\nfrom inrslam.omp_env import wait_policy\n"
         "print(json.dumps([os.environ.get('OMP_WAIT_POLICY'), wait_policy()]))")
LIBGOMP = sys.platform.startswith("linux") and omp_env._torch_runtime_is_libgomp()


def probe(pre: str = "", **env: str) -> list:
    e = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "INRSLAM_OMP_WAIT", omp_env.MARK)} | env
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


def test_a_child_that_inherits_inrslams_own_policy_says_inrslam_set_it():
    # a sweep worker spawned by a process where inrslam set OMP_WAIT_POLICY inherits it with inrslam's mark
    env, info = probe(OMP_WAIT_POLICY="PASSIVE", **{omp_env.MARK: "PASSIVE"})
    assert env == "PASSIVE" and info["set_by"] == "inrslam"
    env, info = probe(OMP_WAIT_POLICY="ACTIVE", **{omp_env.MARK: "PASSIVE"})  # the user changed it since
    assert env == "ACTIVE" and info["set_by"] == "user"


def test_torch_loaded_first_keeps_the_runtime_default_says_so_and_adapts_it_on_libgomp():
    env, info = probe(pre="import torch\n")
    assert env is None and info["policy"] is None and "torch imported before inrslam" in info["set_by"]
    assert info["adaptive"] is LIBGOMP


def test_passive_asked_for_after_torch_loaded_throttles_whole_runs():
    env, info = probe(pre="import torch\n", INRSLAM_OMP_WAIT="passive")
    assert env is None and "throttled for whole runs" in info["set_by"] and info["adaptive"] is LIBGOMP


def test_omp_dynamic_or_a_thread_limit_makes_the_wait_passive():
    for key, value in (("OMP_DYNAMIC", "true"), ("OMP_THREAD_LIMIT", "8")):
        env, info = probe(**{key: value})
        assert env == "PASSIVE" and info["adaptive"] is False, key


def test_an_unknown_choice_warns_and_adapts():
    e = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY",)} | {"INRSLAM_OMP_WAIT": "pasive"}
    res = subprocess.run([sys.executable, "-W", "always", "-c", PROBE.format(pre="")], env=e, capture_output=True,
                         text=True, check=True)
    assert "INRSLAM_OMP_WAIT='pasive' is not one of adaptive, passive, runtime" in res.stderr
    assert json.loads(res.stdout)[1]["adaptive"] is LIBGOMP


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
    # none of the cores listed (a container numbering its own cores from 0): the all-core line, 900 + 300 ticks
    assert parse_proc_stat(STAT, {7}, 100.0) == pytest.approx(12.0)
    assert parse_proc_stat("garbage\n", {0}, 100.0) is None
    assert parse_proc_stat("cpu0 1 2 3 x 5 6 7 8\n", {0}, 100.0) is None


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


def _thread_ids() -> set[str]:
    return set(os.listdir("/proc/self/task"))


libgomp_only = pytest.mark.skipif(not LIBGOMP, reason="the ballast acts on GNU libgomp (Linux torch wheels) only")


@libgomp_only
def test_the_ballast_adds_sleeping_threads_to_every_libgomp_and_frees_them():
    torch.ones(1 << 20).sum()  # torch's libgomp has its pool
    libs = omp_env.loaded_libgomp()
    assert libs and all(os.path.basename(p).startswith("libgomp") for p in libs)
    before = _thread_ids()
    ballast = omp_env.Ballast(libs, 3).start()
    assert ballast.held == libs
    # per runtime: a team of 3 started from the ballast's thread = 2 new pool threads; plus the ballast thread
    new = _thread_ids() - before
    assert len(new) >= 1 + 2 * len(libs)
    ballast.stop()
    assert wait_for(lambda: not (_thread_ids() & new))


SPIN_PROBE = r"""
import json, os, time, torch
from inrslam import omp_env

def worker_ticks():
    main, total = os.getpid(), 0
    for tid in os.listdir("/proc/self/task"):
        if int(tid) != main:
            with open(f"/proc/self/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])  # utime + stime of the thread
    return total

x = torch.ones(1 << 18)
def regions():
    t0 = worker_ticks()
    for _ in range(300):
        x.mul_(1.0)  # one parallel region of torch's two threads
        time.sleep(0.002)  # the worker now waits: spinning burns this time, a throttled wait sleeps
    return worker_ticks() - t0

torch.set_num_threads(2)
regions()
spin = regions()
ballast = omp_env.Ballast(omp_env.loaded_libgomp(), len(os.sched_getaffinity(0)) + 1).start()
throttled = regions()
ballast.stop()
print(json.dumps({"spin": spin, "throttled": throttled}))
"""


@libgomp_only
def test_with_the_ballast_waiting_threads_sleep_instead_of_spinning():
    """The mechanism itself, in CPU time (not wall time): between 300 small parallel regions 2 ms apart, torch's
    worker spins through the gaps under the runtime's default and sleeps with the ballast held."""
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("needs 2 cores for a 2-thread team")
    e = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "INRSLAM_OMP_WAIT", "GOMP_SPINCOUNT")}
    out = subprocess.run([sys.executable, "-c", SPIN_PROBE], env=e, capture_output=True, text=True, check=True).stdout
    ticks = json.loads(out)
    # spinning through 300 gaps of >= 2 ms burns >= 0.6 s of the worker's time (60 ticks at 100 Hz) when it runs
    assert ticks["spin"] >= 20 and ticks["throttled"] * 4 < ticks["spin"], ticks


@libgomp_only
def test_the_guard_holds_a_ballast_while_others_load_the_machine(monkeypatch):
    monkeypatch.setattr(omp_env, "_run_threads", lambda: len(omp_env.cpu_set()))  # the run leaves no core free
    torch.ones(1 << 20).sum()
    engaged_seen = []
    guard = LoadGuard(sample=_scripted([0.0, 1.0, 1.0, 0.1, 0.1, 0.1, 0.1]), interval=0.01)  # cores of others
    orig = guard.engage

    def engage():
        orig()
        engaged_seen.append(guard.throttled)

    guard.engage = engage  # type: ignore[method-assign]
    guard.enter()
    assert wait_for(lambda: guard.samples >= 20)
    guard.exit()
    # the first reading is the baseline; the loads 1.0, 1.0 engage, then 4 calm samples release
    assert engaged_seen and all(engaged_seen)
    assert guard.switches == 1 and guard.throttled_samples == 5 and not guard.throttled


def _scripted(loads):
    """A sampler whose successive readings show `loads` cores of other processes per interval (then 0)."""
    it = iter(list(loads) + [0.0] * 100000)
    clock = {"t": 0.0, "busy": 0.0}

    def sample():
        clock["t"] += 1.0
        clock["busy"] += next(it)
        return CpuSample(clock["t"], clock["busy"], 0.0)

    return sample


def test_only_load_beyond_the_cores_a_run_leaves_free_engages(monkeypatch):
    monkeypatch.setattr(omp_env, "cpu_set", lambda: {0, 1, 2, 3})
    monkeypatch.setattr(omp_env, "_run_threads", lambda: 1)  # the run leaves 3 of 4 cores free
    engaged = []
    guard = LoadGuard(sample=_scripted([0.0, 2.9, 2.9, 3.6]), interval=0.01)  # the first reading is the baseline
    monkeypatch.setattr(guard, "engage", lambda: engaged.append(guard.samples))
    guard.enter()
    assert wait_for(lambda: guard.samples >= 5)
    guard.exit()
    assert engaged and engaged[0] == 2  # not at 2.9 cores twice (0 beyond the free 3), at 3.6 (0.6 beyond)


def test_nested_blocks_share_one_watcher():
    guard = LoadGuard(sample=_scripted([]), interval=0.01)
    guard.enter()
    guard.enter()
    first = guard._thread
    guard.exit()
    assert guard._thread is first and first is not None and first.is_alive()
    guard.exit()
    assert guard._thread is None and not first.is_alive()


@libgomp_only
def test_without_readings_the_guard_throttles_the_whole_block_and_lets_go_at_the_end():
    torch.ones(1 << 20).sum()
    guard = LoadGuard(sample=lambda: None, interval=0.01)
    guard.enter()
    assert wait_for(lambda: guard.samples >= 3)
    assert guard.throttled and guard.switches == 1
    guard.exit()
    assert not guard.throttled and guard.throttled_samples == guard.samples


@libgomp_only
def test_a_failing_reading_stops_the_guard_and_lets_the_ballast_go(monkeypatch):
    monkeypatch.setattr(omp_env, "_run_threads", lambda: len(omp_env.cpu_set()))
    torch.ones(1 << 20).sum()
    readings = iter([CpuSample(0.0, 0.0, 0.0), CpuSample(1.0, 2.0, 0.0)])

    def sample():
        try:
            return next(readings)
        except StopIteration:
            raise RuntimeError("unreadable") from None

    guard = LoadGuard(sample=sample, interval=0.01)
    guard.enter()
    assert wait_for(lambda: guard.failed is not None)
    assert wait_for(lambda: not guard.throttled)
    guard.exit()
    assert guard.switches == 1 and guard.stats()["failed"] == "RuntimeError: unreadable"


def test_thread_headroom_is_a_count_or_unknown():
    room = omp_env.thread_headroom()
    assert room is None or isinstance(room, int)


def test_the_guard_is_a_no_op_without_the_adaptive_policy(monkeypatch):
    monkeypatch.setattr(omp_env, "_adaptive", False)
    before = threading.active_count()
    with omp_env.load_guard() as guard:
        assert threading.active_count() == before and guard._thread is None
