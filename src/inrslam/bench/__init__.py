"""Benchmarks: sweep specs, executors (local / Ray / SLURM), leaderboards, plots and HTML reports.

    from inrslam.bench import run_sweep, build_report
    run_sweep("tiny", "runs/tiny", jobs=2)        # or a YAML path; writes runs/tiny/<run>/ and runs/tiny/report/
    build_report("runs/tiny")                      # re-aggregate without running anything
"""

from inrslam.bench.report import build_report
from inrslam.bench.spec import RunSpec, SweepSpec, expand, load_spec
from inrslam.bench.sweep import SweepResult, run_sweep

__all__ = ["RunSpec", "SweepResult", "SweepSpec", "build_report", "expand", "load_spec", "run_sweep"]
