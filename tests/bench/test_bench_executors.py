"""Sweep orchestration with a cheap fake run function: local pool, failures, crashes, resume, submitit, Ray."""

from __future__ import annotations

import csv
import json
import logging
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from polling import wait_for

import inrslam
from inrslam.bench.executors import EXECUTORS
from inrslam.bench.sweep import run_sweep
from inrslam.bench.testing import executed_runs, fake_run
from inrslam.bench.worker import run_one
from inrslam.io.rundir import RunDir

FAKE = "inrslam.bench.testing:fake_run"


def spec(*encodings, renders=("density", "direct")):
    return {"encodings": list(encodings), "renders": list(renders), "scenes": ["builtin:room"], "presets": ["quick"]}


def metrics_of(out, name):
    return json.loads((out / name / "metrics.json").read_text())


def test_registry_has_three_executors(tmp_path):
    assert EXECUTORS.names() == ["local", "ray", "slurm"]
    with pytest.raises(KeyError, match="did you mean 'slurm'"):
        run_sweep(spec("dense"), tmp_path / "unused", executor="slrum", run_fn=FAKE, validate=False, quiet=True)


def test_worker_records_failure_without_raising(tmp_path):
    run = {"name": "r__fail__g__p__s0", "scene": "r", "scene_path": "builtin:r", "encoding": "fail", "render": "g",
           "preset": "p", "seed": 0, "overrides": {}}
    res = run_one(run, str(tmp_path), run_fn=FAKE, threads=1)
    assert res["status"] == "failed" and res["error"] == "RuntimeError: fake failure of r__fail__g__p__s0"
    assert "Traceback" in (tmp_path / run["name"] / "error.txt").read_text()
    assert json.loads((tmp_path / run["name"] / "bench.json").read_text()) == run


def test_local_pool_records_failures_crashes_and_resumes(tmp_path, capsys):
    out = tmp_path / "sweep"
    s = spec("dense", "fail", "crash", "hash")
    res = run_sweep(s, out, jobs=2, run_fn=FAKE, validate=False)
    assert len(res.runs) == 8
    # printed as it goes: a first line, one line per finished run (ATE, time, counts, ETA), the summary
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "bench: 8 runs to do, 2 at a time on the local executor"
    per_run = [ln for ln in lines if ln.startswith("[")]
    assert [ln.split("]")[0] for ln in per_run] == [f"[{k}/8" for k in range(1, 9)]
    for ln in per_run:
        name = ln.split()[2].rstrip(":")
        if "__fail__" in name or "__crash__" in name:
            assert " failed " in ln
        else:
            assert f"ATE {metrics_of(out, name)['ate_rmse_m'] * 100:.2f} cm" in ln
    assert all("ETA" in ln for ln in per_run[:-1]) and per_run[-1].endswith("done 8, running 0, failed 4, waiting 0")
    assert lines[-1].startswith("bench: 8 runs in")
    assert res.count("complete") == 4 and res.count("failed") == 4 and not res.interrupted
    status = json.loads((out / "sweep_status.json").read_text())
    assert status["state"] == "finished" and status["counts"]["complete"] == 4 and status["counts"]["failed"] == 4
    assert status["runs"]["room__fail__direct__quick__s0"]["error"].startswith("RuntimeError: fake failure")
    assert "died" in status["runs"]["room__crash__density__quick__s0"]["error"]
    for name in ("room__fail__density__quick__s0", "room__crash__direct__quick__s0"):
        assert (out / name / "error.txt").read_text().strip()
    for name in ("room__dense__density__quick__s0", "room__hash__direct__quick__s0"):
        assert RunDir(out / name).is_complete()
    # the leaderboard has the 4 complete runs with their own values
    rows = list(csv.DictReader(open(out / "report" / "leaderboard.csv")))
    assert len(rows) == 4
    for r in rows:
        m = metrics_of(out, f"room__{r['encoding']}__{r['render']}__quick__s0")
        assert float(r["ate_cm_mean"]) == m["ate_rmse_m"] * 100
    # resume: completed runs are skipped, the failed ones are tried again
    n_before = len(executed_runs(out))
    res2 = run_sweep(s, out, jobs=2, run_fn=FAKE, validate=False, quiet=True, report=False)
    again = executed_runs(out)[n_before:]
    assert res2.count("skipped") == 4 and res2.count("complete") == 0
    assert not any(n.startswith(("room__dense", "room__hash")) for n in again)
    assert {n for n in again} == {n for n in res2.failed}


def test_interrupted_sweep_resumes_only_missing_runs(tmp_path):
    out = tmp_path / "sweep"
    s = spec("dense", "hash")
    seen = []

    def stop_after_two(result):
        seen.append(result["name"])
        return len(seen) < 2

    res = run_sweep(s, out, jobs=1, run_fn=FAKE, validate=False, on_result=stop_after_two, quiet=True)
    assert res.interrupted and res.count("complete") == 2 and res.count("pending") == 2
    assert json.loads((out / "sweep_status.json").read_text())["state"] == "interrupted"
    assert len(executed_runs(out)) == 2
    first = {n: metrics_of(out, n) for n in seen}
    res2 = run_sweep(s, out, jobs=2, run_fn=FAKE, validate=False, quiet=True)
    assert res2.count("skipped") == 2 and res2.count("complete") == 2
    assert len(executed_runs(out)) == 4 and set(executed_runs(out)[2:]).isdisjoint(seen)
    assert {n: metrics_of(out, n) for n in seen} == first  # untouched
    assert len(list(csv.DictReader(open(out / "report" / "leaderboard.csv")))) == 4


def test_dry_run_writes_nothing(tmp_path, capsys):
    res = run_sweep(spec("dense", "hash+tri"), tmp_path / "x", dry_run=True, run_fn=FAKE, validate=False)
    assert res.count("pending") == 4 and not (tmp_path / "x").exists()
    printed = capsys.readouterr().out
    assert "room__hash-tri__direct__quick__s0" in printed and "4 runs" in printed


def _results(out):
    return {p.name: json.loads((p / "metrics.json").read_text()) for p in sorted(out.iterdir())
            if (p / "metrics.json").is_file()}


@pytest.mark.parametrize("cluster", ["debug", "local"])
def test_submitit_executor(tmp_path, cluster):
    pytest.importorskip("submitit")
    out = tmp_path / cluster
    res = run_sweep(spec("dense", "fail"), out, executor="slurm", cluster=cluster, cpus_per_run=1, run_fn=FAKE,
                    validate=False, quiet=True, report=False)
    assert res.count("complete") == 2 and res.count("failed") == 2
    assert (out / "slurm").is_dir()
    ref = tmp_path / "ref"
    run_sweep(spec("dense", "fail"), ref, jobs=2, run_fn=FAKE, validate=False, quiet=True, report=False)
    assert _results(out) == _results(ref)  # same results whatever the executor


@pytest.mark.slow
def test_ray_executor_local_instance(tmp_path):
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        out = tmp_path / "ray"
        res = run_sweep(spec("dense", "fail", "hash"), out, jobs=2, executor="ray", run_fn=FAKE, validate=False,
                        quiet=True)
        assert res.count("complete") == 4 and res.count("failed") == 2
        assert ray.is_initialized()  # an instance we did not start is left running
        pids = {r["pid"] for r in res.results.values() if r.get("pid")}
        assert pids and all(p != __import__("os").getpid() for p in pids)
        assert len(list(csv.DictReader(open(out / "report" / "leaderboard.csv")))) == 4
        res2 = run_sweep(spec("dense", "fail", "hash"), out, executor="ray", run_fn=FAKE, validate=False, quiet=True,
                         report=False)
        assert res2.count("skipped") == 4 and len(executed_runs(out)) == 8  # 6 + the 2 failed ones again
    finally:
        ray.shutdown()


def test_missing_optional_dependency_message(monkeypatch, tmp_path):
    import sys

    from inrslam.errors import InrslamError

    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(InrslamError, match=r"pip install inrslam\[ray\]"):
        run_sweep(spec("dense"), tmp_path / "o", executor="ray", run_fn=FAKE, validate=False, quiet=True)
    monkeypatch.setitem(sys.modules, "submitit", None)
    with pytest.raises(InrslamError, match=r"pip install inrslam\[slurm\]"):
        run_sweep(spec("dense"), tmp_path / "o", executor="slurm", run_fn=FAKE, validate=False, quiet=True)
    assert not (tmp_path / "o").exists()  # failed before writing anything


def test_a_run_another_process_is_running_is_left_alone(tmp_path):
    """A sweep reaching a run whose folder another process holds (`.run.lock`: a job of an earlier sweep, a user's
    `inrslam run --resume`) reports it failed and writes nothing into that folder; the next sweep runs it."""
    from inrslam.io.lock import acquire

    out = tmp_path / "o"
    name = "room__dense__direct__quick__s0"
    (out / name).mkdir(parents=True)
    (out / name / "error.txt").write_text("the other process's\n")
    held = acquire(out / name / RunDir.LOCK_FILE)  # as the other process holds it
    try:
        res = run_sweep(spec("dense", renders=("direct",)), out, run_fn=FAKE, validate=False, quiet=True,
                        report=False)
    finally:
        held.close()
    (result,) = res.results.values()
    assert result["status"] == "failed" and result["busy"]
    assert "another inrslam process is running in this run folder (pid " in result["error"]
    assert sorted(p.name for p in (out / name).iterdir()) == [".run.lock", "error.txt"]  # no bench.json
    assert (out / name / "error.txt").read_text() == "the other process's\n"
    res = run_sweep(spec("dense", renders=("direct",)), out, run_fn=FAKE, validate=False, quiet=True, report=False)
    assert res.count("complete") == 1 and not res.failed


def test_slurm_refuses_a_fraction_of_a_gpu(tmp_path):
    """SLURM gives whole GPUs: gpus_per_run=0.5 was int()-ed to 0, a job without a GPU; now refused up-front."""
    from inrslam.errors import ConfigError

    with pytest.raises(ConfigError, match=r"gpus_per_run=0\.5: SLURM gives whole GPUs"):
        run_sweep(spec("dense"), tmp_path / "o", executor="slurm", run_fn=FAKE, validate=False, quiet=True,
                  gpus_per_run=0.5)
    assert not (tmp_path / "o").exists()


def test_a_second_sweep_into_the_same_folder_is_refused_while_the_first_runs(tmp_path):
    """Two `inrslam bench` on one --out ran every unfinished run twice into the same folders; the folder is now
    locked for the sweep's duration (and free again after it)."""
    from inrslam.bench.sweep import _lock_folder
    from inrslam.errors import ConfigError

    out = tmp_path / "o"
    out.mkdir()
    held = _lock_folder(out)  # what a running sweep holds
    try:
        holder = re.escape(f"(pid {os.getpid()} on {socket.gethostname()})")
        busy = rf"another inrslam bench is running into this folder {holder}"
        with pytest.raises(ConfigError, match=busy):
            run_sweep(spec("dense"), out, run_fn=FAKE, validate=False, quiet=True)
        assert executed_runs(out) == []
    finally:
        held.close()
    res = run_sweep(spec("dense"), out, run_fn=FAKE, validate=False, quiet=True)
    assert not res.failed and len(executed_runs(out)) == len(res.runs)
    _lock_folder(out).close()  # released at the end: taking it again works


# -- SLURM: re-attaching to the jobs a killed driver left in flight -------------------------------------------------

HERE = Path(__file__).resolve().parent
PYTHONPATH = os.pathsep.join([str(Path(inrslam.__file__).resolve().parents[1]), str(HERE.parent), str(HERE)])
GATED = "test_bench_executors:gated_run"  # importable by the job processes through PYTHONPATH
GATE_S = 120.0


def gated_run(run: dict, run_dir: Path) -> dict:
    """Run function of a job that must outlive its driver: waits for `<out>/release` (the test writes it), then
    `fake_run`; fails after GATE_S seconds so a failed test leaves no job behind."""
    if not wait_for((Path(run_dir).parent / "release").exists, GATE_S, 0.05):
        raise RuntimeError(f"{run['name']}: never released")
    return fake_run(run, run_dir)


class _ReleaseAfter(logging.Handler):
    """Writes `path` once `n` re-attach records were logged, so the gated jobs end only after that decision."""

    def __init__(self, path: Path, n: int):
        super().__init__()
        self.path, self.n = path, n

    def emit(self, record: logging.LogRecord) -> None:
        if record.getMessage().startswith("re-attaching"):
            self.n -= 1
            if self.n == 0:
                self.path.touch()


def _gated_sweep(out: Path, **kw):
    return run_sweep(spec("dense"), out, executor="slurm", cluster="local", cpus_per_run=1, run_fn=GATED,
                     validate=False, quiet=True, report=False, **kw)


def test_slurm_reattaches_to_jobs_a_killed_driver_left_running(tmp_path, monkeypatch, caplog):
    """A SIGKILLed driver leaves its (submitit local) jobs running; running the sweep again waits on them and
    yields their results instead of submitting the runs a second time."""
    pytest.importorskip("submitit")
    from submitit import LocalJob

    from inrslam.bench.slurm_jobs import INFLIGHT_FILE, local_state, read_inflight

    monkeypatch.setenv("PYTHONPATH", PYTHONPATH)
    out = tmp_path / "sweep"
    folder, book = out / "slurm", out / "slurm" / INFLIGHT_FILE
    code = f"from test_bench_executors import _gated_sweep; from pathlib import Path; _gated_sweep(Path({str(out)!r}))"
    err = tmp_path / "driver.err"  # a file, not a pipe: the jobs inherit it and outlive the driver
    with open(err, "w") as f:
        driver = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=f)
    try:
        wait_for(lambda: driver.poll() is not None or len(read_inflight(book)) == 2, 120, 0.05)
        assert driver.poll() is None, err.read_text()[-3000:]
    finally:
        driver.kill()  # SIGKILL: no finally, no cancel
        driver.wait()
    jobs = {r["name"]: r["job_id"] for r in read_inflight(book)}
    assert {r["run_dir"] for r in read_inflight(book)} == {str(out / n) for n in jobs}
    assert all(local_state(folder, j) == "RUNNING" for j in jobs.values())  # the jobs outlive their driver
    submitted = sorted(p.name for p in folder.glob("*_submitted.pkl"))
    assert submitted == sorted(f"{j}_submitted.pkl" for j in jobs.values())

    caplog.set_level(logging.INFO, logger="inrslam.bench.executors")
    release = _ReleaseAfter(out / "release", len(jobs))
    logging.getLogger("inrslam.bench.executors").addHandler(release)
    try:
        res = _gated_sweep(out)
    finally:
        logging.getLogger("inrslam.bench.executors").removeHandler(release)
        (out / "release").touch()  # whatever happened, let the jobs end
    assert res.count("complete") == 2 and not res.failed
    assert sorted(p.name for p in folder.glob("*_submitted.pkl")) == submitted  # no job submitted again
    assert sorted(executed_runs(out)) == sorted(jobs)  # each run executed once, by its first job
    for name, job_id in jobs.items():
        assert res.results[name] == LocalJob(folder, job_id).result()  # the original job's result
        assert any(f"local job {job_id} " in m and name in m for m in caplog.messages if m.startswith("re-attach"))
    assert read_inflight(book) == []  # finished jobs are forgotten


def _call(out: str, name: str) -> dict:
    return {"run": {"name": name}, "out_dir": out, "run_fn": FAKE}


def _rec(job_id: str, out: str, name: str, cluster: str = "slurm") -> dict:
    from inrslam.bench.slurm_jobs import job_record

    return job_record(job_id, cluster, _call(out, name))


def test_plan_reattach_waits_only_on_live_jobs_of_the_same_run_dir(tmp_path):
    from inrslam.bench.slurm_jobs import plan_reattach

    out, other = str(tmp_path / "o"), str(tmp_path / "other")
    calls = [_call(out, n) for n in ("live", "pending", "done", "cancelled", "unknown", "unsure", "new", "elsewhere")]
    records = [_rec("1", out, "live"), _rec("2", out, "pending"), _rec("3", out, "done"), _rec("4", out, "cancelled"),
               _rec("5", out, "unknown"), _rec("6", out, "unsure"), _rec("7", other, "elsewhere"),
               _rec("8", out, "not-asked-live"), _rec("9", out, "not-asked-unsure"), _rec("10", out, "not-asked-done")]
    states = {"1": "RUNNING", "2": "PENDING", "3": "COMPLETED", "4": "CANCELLED by 1000", "5": "UNKNOWN", "6": None,
              "7": "RUNNING", "8": "REQUEUED", "9": None, "10": "FAILED"}
    plan = plan_reattach(calls, records, states)
    assert [(r["job_id"], c["run"]["name"]) for r, c in plan.attach] == [("1", "live"), ("2", "pending")]
    assert [c["run"]["name"] for c in plan.submit] == ["done", "cancelled", "unknown", "unsure", "new", "elsewhere"]
    assert [r["job_id"] for r in plan.unsure] == ["6"]
    assert sorted(r["job_id"] for r in plan.keep) == ["7", "8", "9"]  # live or unknowable, run not asked for
    # a later record of the same run wins; a run dir given relative matches its absolute record
    again = plan_reattach([_call(os.path.relpath(out), "live")], [_rec("1", out, "live"), _rec("11", out, "live")],
                          {"1": "COMPLETED", "11": "RUNNING"})
    assert [r["job_id"] for r, _ in again.attach] == ["11"] and not again.submit


SACCT = """#!/bin/sh
echo "$@" > "${0%/*}/args"
printf 'JobID|State\\n123_0|RUNNING\\n123_0.batch|RUNNING\\n123_1|CANCELLED by 0\\n123_[2-3]|PENDING\\n'
"""


def test_slurm_plan_reads_states_from_sacct_and_falls_back_to_submitting(tmp_path, monkeypatch, caplog):
    """With a stand-in `sacct` on PATH the recorded array elements still running or pending are re-attached; with
    no sacct every run is submitted again, with a warning naming the job."""
    pytest.importorskip("submitit")
    from inrslam.bench.executors import ExecutorOptions, SlurmExecutor
    from inrslam.bench.slurm_jobs import INFLIGHT_FILE, sacct_states
    from inrslam.io.atomic import write_json

    out, folder, bin_dir = str(tmp_path / "o"), tmp_path / "o" / "slurm", tmp_path / "bin"
    names = ["a", "b", "c", "d"]
    write_json(folder / INFLIGHT_FILE, {"jobs": [_rec(j, out, n) for j, n in zip(["123_0", "123_1", "123_2", "99_0"],
                                                                                 names)]})
    bin_dir.mkdir()
    (bin_dir / "sacct").write_text(SACCT)
    (bin_dir / "sacct").chmod(0o755)
    monkeypatch.setenv("PATH", str(bin_dir))
    assert sacct_states(["123_0", "123_1", "123_3", "99_0"]) == (
        {"123_0": "RUNNING", "123_1": "CANCELLED by 0", "123_3": "PENDING", "99_0": "UNKNOWN"}, None)
    assert (bin_dir / "args").read_text().split() == ["-o", "JobID,State", "--parsable2", "-j", "123", "-j", "99"]
    ex = SlurmExecutor(ExecutorOptions(folder=out, cluster="slurm"))
    caplog.set_level(logging.INFO, logger="inrslam.bench.executors")
    plan = ex._plan("slurm", folder, [_call(out, n) for n in names])
    assert [(r["job_id"], c["run"]["name"]) for r, c in plan.attach] == [("123_0", "a"), ("123_2", "c")]
    assert [c["run"]["name"] for c in plan.submit] == ["b", "d"]
    assert any("slurm job 123_2 (PENDING) of run c" in m for m in caplog.messages)

    (bin_dir / "sacct").unlink()
    caplog.clear()
    plan = ex._plan("slurm", folder, [_call(out, n) for n in names])
    assert not plan.attach and [c["run"]["name"] for c in plan.submit] == names
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 4
    assert warned[0].startswith("cannot tell whether slurm job 123_0 of run a is still running (sacct failed")
    assert warned[0].endswith("; submitting the run again")


SQUEUE = """#!/bin/sh
echo "$@" > "${0%/*}/squeue_args"
printf '99_0|RUNNING\\n123_[2-3]|PENDING\\n'
"""


def test_jobs_the_accounting_does_not_list_yet_are_looked_up_in_the_queue(tmp_path, monkeypatch):
    """A job sacct does not list (accounting lag) or every job when sacct is missing: `squeue` lists the live ones
    (array ranges expanded); a job it does not list has ended."""
    pytest.importorskip("submitit")
    from inrslam.bench.slurm_jobs import sacct_states

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, text in (("sacct", SACCT), ("squeue", SQUEUE)):
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(0o755)
    monkeypatch.setenv("PATH", str(bin_dir))
    assert sacct_states(["123_0", "99_0", "77_1"]) == ({"123_0": "RUNNING", "99_0": "RUNNING", "77_1": "UNKNOWN"},
                                                       None)
    assert (bin_dir / "squeue_args").read_text().split() == ["-h", "-o", "%i|%T", "-j", "77,99"]
    (bin_dir / "sacct").unlink()  # no accounting at all: the queue alone decides
    assert sacct_states(["123_0", "123_3", "99_0"]) == ({"123_0": "UNKNOWN", "123_3": "PENDING", "99_0": "RUNNING"},
                                                        None)


def test_a_job_alive_in_a_state_submitit_does_not_wait_on_is_neither_attached_nor_called_finished(tmp_path,
                                                                                                  monkeypatch, caplog):
    """CONFIGURING / SUSPENDED jobs: submitit would read them as done at once, so they are not attached; their runs
    are submitted again with a warning saying the state (the new job then finds the folder locked)."""
    pytest.importorskip("submitit")
    import inrslam.bench.executors as executors
    from inrslam.bench.executors import ExecutorOptions, SlurmExecutor
    from inrslam.bench.slurm_jobs import INFLIGHT_FILE, settled
    from inrslam.io.atomic import write_json

    assert [settled(x) for x in ("RUNNING", "CANCELLED by 0", "UNKNOWN", "FINISHED", "CONFIGURING", "SUSPENDED",
                                 None)] == ["RUNNING", "CANCELLED by 0", "UNKNOWN", "FINISHED", None, None, None]
    out, folder = str(tmp_path / "o"), tmp_path / "o" / "slurm"
    write_json(folder / INFLIGHT_FILE, {"jobs": [_rec("7_0", out, "a"), _rec("7_1", out, "b")]})
    monkeypatch.setattr(executors, "sacct_states", lambda ids: ({"7_0": "CONFIGURING", "7_1": "RUNNING"}, None))
    plan = SlurmExecutor(ExecutorOptions(folder=out, cluster="slurm"))._plan("slurm", folder,
                                                                             [_call(out, "a"), _call(out, "b")])
    assert [c["run"]["name"] for c in plan.submit] == ["a"] and [r["job_id"] for r, _ in plan.attach] == ["7_1"]
    assert any("slurm job 7_0 of run a is still running (state CONFIGURING, which submitit does not wait on)" in m
               for m in caplog.messages)


INVALID_ID = """#!/bin/sh
echo "slurm_load_jobs error: Invalid job id specified" >&2
exit 1
"""


def test_a_single_job_id_the_queue_has_forgotten_has_ended(tmp_path, monkeypatch):
    """`squeue -j ID` of one job that left the controller's memory exits 1 ("Invalid job id"): ended, not unknown."""
    pytest.importorskip("submitit")
    from inrslam.bench.slurm_jobs import sacct_states, squeue_states

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "squeue").write_text(INVALID_ID)
    (bin_dir / "squeue").chmod(0o755)
    monkeypatch.setenv("PATH", str(bin_dir))
    assert squeue_states(["55_0"]) == {}
    assert sacct_states(["55_0"]) == ({"55_0": "UNKNOWN"}, None)  # no sacct here: the queue decided


def test_a_signal_to_one_local_worker_fails_its_run_and_the_sweep_goes_on(tmp_path, monkeypatch):
    """`kill PID` of one worker (a memory watchdog): that run is failed (it resumes from its checkpoint next time),
    the other runs complete, and the sweep is not interrupted."""
    import signal
    import threading

    monkeypatch.setenv("PYTHONPATH", PYTHONPATH)  # the spawned workers import fault_runs from tests/
    out = tmp_path / "o"
    spec_ = {**spec("dense", renders=("direct",)), "seeds": [0, 1]}
    started = out / "room__dense__direct__quick__s1" / "started"

    def kill_when_started():
        assert wait_for(lambda: started.is_file() and started.read_text().strip(), 120, 0.02)
        os.kill(int(started.read_text()), signal.SIGTERM)

    killer = threading.Thread(target=kill_when_started)
    killer.start()
    try:
        res = run_sweep(spec_, out, run_fn="fault_runs:hang_other_seeds", jobs=2, validate=False, quiet=True,
                        report=False)
    finally:
        killer.join()
    assert not res.interrupted and res.count("complete") == 1
    (failed,) = res.failed
    assert "the worker was stopped by SIGTERM" in res.results[failed]["error"]


def test_a_worker_that_does_not_stop_is_killed_after_the_grace_period(monkeypatch):
    """Stopping a sweep SIGTERMs its workers (each saves its frame); one still running after the grace period (a
    long call, a signal taken on another thread) is killed, so the sweep's stop is bounded."""
    import multiprocessing as mp
    import signal

    from inrslam.bench.executors import stop_workers

    monkeypatch.setenv("PYTHONPATH", PYTHONPATH)  # the spawned workers import fault_runs from tests/
    import fault_runs

    ctx = mp.get_context("spawn")
    ready = ctx.Event()
    deaf = ctx.Process(target=fault_runs.deaf_to_sigterm, args=(ready,))
    deaf.start()
    assert ready.wait(60)
    stop_workers([deaf], grace_s=0.5)
    deaf.join(60)
    assert not deaf.is_alive() and deaf.exitcode == -signal.SIGKILL  # killed: it ignored the SIGTERM


# -- Ray: CPUs per run from the cluster's nodes ----------------------------------------------------------------------

NODES = [{"Alive": True, "Resources": {"CPU": 8.0, "GPU": 1.0}}, {"Alive": True, "Resources": {"CPU": 4.0}},
         {"Alive": False, "Resources": {"CPU": 64.0}}, {"Alive": True, "Resources": {}}]


@pytest.mark.parametrize("jobs, expected", [(1, 8), (2, 6), (3, 4), (4, 3), (12, 1), (100, 1)])
def test_ray_cpus_per_run_from_alive_nodes(jobs, expected):
    """Total alive CPUs (12) // jobs, never more than the largest node (8); a dead node does not count."""
    from inrslam.bench.executors import ray_cpus_per_run

    assert ray_cpus_per_run(NODES, jobs) == expected


def test_ray_cpus_per_run_refuses_more_than_any_node_has():
    from inrslam.bench.executors import ray_cpus_per_run
    from inrslam.errors import ConfigError

    assert ray_cpus_per_run(NODES, jobs=1, cpus_per_run=8) == 8
    with pytest.raises(ConfigError, match=r"^cpus_per_run=9: no Ray node has that many CPUs \(the largest has 8\)"):
        ray_cpus_per_run(NODES, jobs=1, cpus_per_run=9)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_ray_executor_fits_runs_on_a_node_smaller_than_the_driver(tmp_path):
    """On a 1-CPU Ray instance the runs were asked os.cpu_count() // jobs CPUs of the driver and never scheduled;
    now they get the node's CPU, and a cpus_per_run no node has is refused instead of hanging."""
    ray = pytest.importorskip("ray")
    from inrslam.errors import ConfigError

    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    try:
        res = run_sweep(spec("dense"), tmp_path / "ray", jobs=1, executor="ray", run_fn=FAKE, validate=False,
                        quiet=True, report=False)
        assert res.count("complete") == 2 and len(executed_runs(tmp_path / "ray")) == 2
        with pytest.raises(ConfigError, match=r"cpus_per_run=2: .*the largest has 1\)"):
            run_sweep(spec("hash"), tmp_path / "ray2", executor="ray", cpus_per_run=2, run_fn=FAKE, validate=False,
                      quiet=True, report=False)
        assert executed_runs(tmp_path / "ray2") == [] and ray.is_initialized()
    finally:
        ray.shutdown()
