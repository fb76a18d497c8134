"""What `inrslam bench` prints while a sweep runs: a first line saying what will run, then one line per finished
run with its ATE and time, the counts so far (done / running / failed / waiting) and an ETA.

Plain lines (no terminal control), so they read the same in a terminal, a log file or a SLURM output.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from inrslam.io.rundir import RunDir


def duration_text(seconds: float | None) -> str:
    """'42 s', '3 min 05 s', '2 h 07 min'; '?' for None."""
    if seconds is None:
        return "?"
    s = int(round(max(seconds, 0.0)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


class SweepProgress:
    """Counts a sweep's finished runs and words its lines.

    Args:
        todo: runs this invocation executes (complete ones are skipped before); skipped: runs already complete.
        jobs: runs at a time; executor: 'local' runs exactly `jobs` at once, ray / slurm queue the rest, so their
            count is "running or queued".
        clock: seconds (monotonic); tests pass their own.
    """

    def __init__(self, todo: int, skipped: int, jobs: int, executor: str,
                 clock: Callable[[], float] = time.monotonic):
        self.todo, self.skipped, self.jobs, self.executor = todo, skipped, max(1, int(jobs)), executor
        self.clock = clock
        self.t0 = clock()
        self.done = 0
        self.failed = 0

    def start_line(self) -> str:
        """'bench: 6 runs to do (2 already complete), 2 at a time on the local executor'."""
        text = f"bench: {self.todo} run{'s' if self.todo != 1 else ''} to do"
        if self.skipped:
            text += f" ({self.skipped} already complete)"
        return text + f", {min(self.jobs, max(self.todo, 1))} at a time on the {self.executor} executor"

    def finished(self, result: dict) -> str:
        """Count a run's result (`inrslam.bench.worker.run_one`) and return its line, e.g.
        '[3/6] complete room__dense__density__quick__s0: ATE 1.23 cm, 2 min 10 s | done 3, running 2, failed 0,
        waiting 1, ETA 4 min 20 s'."""
        self.done += 1
        status = result.get("status", "?")
        if status == "failed":
            self.failed += 1
        what = f"[{self.done}/{self.todo}] {status} {result.get('name', '?')}: "
        if status == "failed":
            what += f"{result.get('error') or 'unknown error'}"[:200]
        else:
            what += _ate_text(result.get("run_dir"))
        what += f", {duration_text(result.get('seconds'))}"
        return f"{what} | {self.counts_text()}"

    def counts_text(self) -> str:
        """'done 3, running 2, failed 1, waiting 1, ETA 4 min 20 s' (done counts the failed runs too; the ETA is the
        time per finished run so far, which includes the parallelism, times the runs left)."""
        left = self.todo - self.done
        busy = min(self.jobs, left) if self.executor == "local" else left
        running = f"running {busy}" if self.executor == "local" else f"running or queued {busy}"
        text = f"done {self.done}, {running}, failed {self.failed}"
        if self.executor == "local":
            text += f", waiting {left - busy}"
        if left > 0 and self.done > 0:
            text += f", ETA {duration_text((self.clock() - self.t0) / self.done * left)}"
        return text


def _ate_text(run_dir: str | None) -> str:
    """'ATE 1.23 cm' from the run's metrics.json ('ATE –' when it has none)."""
    metrics = RunDir(Path(run_dir)).read_metrics() if run_dir else None
    ate = (metrics or {}).get("ate_rmse_m")
    return f"ATE {ate * 100:.2f} cm" if isinstance(ate, (int, float)) and not isinstance(ate, bool) else "ATE –"
