"""Sweep orchestration with a cheap fake run function: local pool, failures, crashes, resume, submitit, Ray."""

from __future__ import annotations

import csv
import json
import os

import pytest

from inrslam.bench.executors import EXECUTORS
from inrslam.bench.sweep import run_sweep
from inrslam.bench.testing import executed_runs
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
        busy = rf"another inrslam bench is running into this folder \(pid {os.getpid()}\)"
        with pytest.raises(ConfigError, match=busy):
            run_sweep(spec("dense"), out, run_fn=FAKE, validate=False, quiet=True)
        assert executed_runs(out) == []
    finally:
        held.close()
    res = run_sweep(spec("dense"), out, run_fn=FAKE, validate=False, quiet=True)
    assert not res.failed and len(executed_runs(out)) == len(res.runs)
    _lock_folder(out).close()  # released at the end: taking it again works
