"""The real thing: a tiny sweep (2 encodings x 2 renders x 1 built-in scene, quick preset) with the local executor,
interrupted, one run left half-done with a checkpoint, then resumed; the leaderboard equals the runs' metrics.json."""

from __future__ import annotations

import csv
import json

import pytest

from inrslam.bench.leaderboard import COLUMNS
from inrslam.bench.spec import expand, resolve_config
from inrslam.bench.sweep import run_sweep
from inrslam.errors import ConfigError
from inrslam.io.rundir import RunDir


class Stop(Exception):
    pass


@pytest.mark.slow
def test_tiny_sweep_interrupt_resume_leaderboard(tmp_path):
    from inrslam.runner import run_slam

    out = tmp_path / "tiny"
    runs = expand("tiny")
    assert len(runs) == 4
    seen = []
    # jobs=2: when the hook stops the sweep after 2 results, the third run is killed wherever it is
    res = run_sweep("tiny", out, jobs=2, on_result=lambda r: seen.append(r["name"]) or len(seen) < 2, quiet=True,
                    report=False)
    assert res.interrupted and res.count("complete") == 2 and res.count("pending") == 2, res.results
    assert all(RunDir(out / n).is_complete() for n in seen)
    assert sum(RunDir(out / r.name).is_complete() for r in runs) == 2

    # the last run stopped half-way after a checkpoint: the resumed sweep continues it from there
    partial = next(r for r in runs if not (out / r.name).exists())

    def stop_at_checkpoint(i, n, info):
        if (out / partial.name / "checkpoints" / "latest.pt").exists():
            raise Stop

    with pytest.raises(Stop):
        run_slam(resolve_config(partial), out / partial.name, progress=stop_at_checkpoint)
    assert RunDir(out / partial.name).has_checkpoint() and not RunDir(out / partial.name).is_complete()
    before = {n: (out / n / "metrics.json").read_text() for n in seen}

    res2 = run_sweep("tiny", out, jobs=2, quiet=True)
    assert res2.count("skipped") == 2 and res2.count("complete") == 2, res2.results
    assert res2.results[partial.name].get("resumed") is True
    assert {n: (out / n / "metrics.json").read_text() for n in seen} == before  # completed runs untouched

    rows = list(csv.DictReader(open(out / "report" / "leaderboard.csv")))
    assert len(rows) == 4
    for row in rows:
        run = next(r for r in runs if (r.encoding, r.render) == (row["encoding"], row["render"]))
        d = out / run.name
        m = json.loads((d / "metrics.json").read_text())
        assert row["runs"] == "1"
        for c in COLUMNS:
            v = m.get(c.metric)
            if v is None:
                assert row[f"{c.key}_mean"] == ""
            else:
                assert float(row[f"{c.key}_mean"]) == pytest.approx(v * c.scale, rel=1e-12), (run.name, c.key)
        for f in ("config.yaml", "run_info.json", "trajectory.txt", "log.jsonl", "bench.json"):
            assert (d / f).is_file(), (run.name, f)
        assert any(json.loads(ln).get("type") == "track" for ln in (d / "log.jsonl").read_text().splitlines())
    assert (out / "report" / "plots" / "tradeoff_memory_ate.png").is_file()
    assert (out / "report" / "index.html").is_file()

    # the same --out with a changed config refuses to mix results
    with pytest.raises(ConfigError, match="different config"):
        run_sweep({"encodings": ["dense"], "renders": ["density"], "scenes": ["builtin:room"], "presets": ["quick"],
                   "max_frames": 6, "overrides": {"slam": {"track_iters": 3}}}, out, quiet=True)
