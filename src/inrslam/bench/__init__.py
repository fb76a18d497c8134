"""Benchmarks: sweep specs, executors (local / Ray / SLURM), leaderboards, plots and HTML reports.

    from inrslam.bench import run_sweep, build_report
    run_sweep("tiny", "runs/tiny", jobs=2)        # or a YAML path; writes runs/tiny/<run>/ and runs/tiny/report/
    build_report("runs/tiny")                      # re-aggregate without running anything
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from inrslam.lazy import lazy_attributes

if TYPE_CHECKING:  # loaded on first use (PEP 562): a sweep worker process needs none of the report's plotting
    from inrslam.bench.report import build_report
    from inrslam.bench.spec import RunSpec, SweepSpec, expand, load_spec
    from inrslam.bench.sweep import SweepResult, run_sweep

_SOURCES = {
    "report": ("build_report",),
    "spec": ("RunSpec", "SweepSpec", "expand", "load_spec"),
    "sweep": ("SweepResult", "run_sweep"),
}

__getattr__ = lazy_attributes(__name__, globals(), _SOURCES)

__all__ = ["RunSpec", "SweepResult", "SweepSpec", "build_report", "expand", "load_spec", "run_sweep"]
