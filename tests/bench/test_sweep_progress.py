"""What a sweep prints while it runs (`inrslam.bench.sweep_progress`), with a scripted clock and fake runs."""

from __future__ import annotations

from inrslam.bench.sweep_progress import SweepProgress, duration_text
from inrslam.bench.testing import write_fake_run


def test_duration_text():
    assert [duration_text(s) for s in (0.4, 42, 185, 7620)] == ["0 s", "42 s", "3 min 05 s", "2 h 07 min"]
    assert duration_text(None) == "?"


def test_one_line_per_finished_run_with_ate_time_counts_and_eta(tmp_path):
    now = [100.0]
    p = SweepProgress(todo=4, skipped=1, jobs=2, executor="local", clock=lambda: now[0])
    assert p.start_line() == "bench: 4 runs to do (1 already complete), 2 at a time on the local executor"
    run = write_fake_run(tmp_path / "a", "dense", "density", metrics={"ate_rmse_m": 0.0123})
    now[0] = 160.0
    line = p.finished({"name": "a", "status": "complete", "run_dir": str(run), "seconds": 58.2})
    assert line == ("[1/4] complete a: ATE 1.23 cm, 58 s | done 1, running 2, failed 0, waiting 1, "
                    "ETA 3 min 00 s")  # 60 s per finished run so far, 3 to go
    now[0] = 190.0
    line = p.finished({"name": "b", "status": "failed", "run_dir": str(tmp_path / "b"), "seconds": 3.0,
                       "error": "RuntimeError: out of memory"})
    assert line.startswith("[2/4] failed b: RuntimeError: out of memory, 3 s | done 2, running 2, failed 1, waiting 0")
    assert line.endswith("ETA 1 min 30 s")
    p.finished({"name": "c", "status": "complete", "run_dir": str(tmp_path / "c"), "seconds": 1.0})
    last = p.finished({"name": "d", "status": "complete", "run_dir": None, "seconds": None})
    assert "ATE –, ?" in last and last.endswith("done 4, running 0, failed 1, waiting 0")  # no ETA at the end


def test_queued_executors_count_running_or_queued():
    p = SweepProgress(todo=3, skipped=0, jobs=1, executor="slurm", clock=lambda: 0.0)
    assert p.counts_text() == "done 0, running or queued 3, failed 0"
