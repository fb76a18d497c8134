"""The Python API, one call per job (`import inrslam`; the CLI is a thin layer over the same functions):

    import inrslam
    run = inrslam.run("runs/room-fast", preset="fast", overrides=["data.max_frames=50"])   # -> LoadedRun
    run.metrics["ate_rmse_m"]; run.est; run.render(run.est[10])                        # inspect
    other = inrslam.load_run("runs/room-paper")                                        # compare

`run` SLAMs and evaluates one config; `load_config` resolves one; `evaluate` (re)computes a run's metrics;
`sweep` runs a spec of F x G x scenes; `report` writes leaderboards and plots; `load_run` reads a run back.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Sequence

from inrslam.bench.report import build_report as report
from inrslam.bench.sweep import run_sweep as sweep
from inrslam.config import load_config
from inrslam.eval.run import evaluate_run as evaluate
from inrslam.runner import Progress, run_slam
from inrslam.runner.loaded import LoadedRun, load_run

__all__ = ["run", "load_config", "evaluate", "sweep", "report", "load_run", "LoadedRun", "absolute_paths"]


def absolute_paths(cfg):
    """`cfg` with `data.path`, `slam.poses` (a file) and `eval.virtual_cameras` absolute (relative to the current
    directory), so the run's config.yaml and run_info.json still point at them from any directory (`--resume`,
    `eval`)."""
    from inrslam.datasets import absolute_data_config, absolute_path

    cfg = dataclasses.replace(cfg, data=absolute_data_config(cfg.data))
    if cfg.slam.poses and cfg.slam.poses != "gt":
        cfg = dataclasses.replace(cfg, slam=dataclasses.replace(cfg.slam, poses=str(absolute_path(cfg.slam.poses))))
    if cfg.eval.virtual_cameras:
        cfg = dataclasses.replace(cfg, eval=dataclasses.replace(
            cfg.eval, virtual_cameras=str(absolute_path(cfg.eval.virtual_cameras))))
    return cfg


def run(out: str | os.PathLike, config: str | os.PathLike | None = None, preset: str = "paper",
        overrides: Sequence[str] | dict | None = None, overwrite: bool = False,
        progress: Progress | None = None) -> LoadedRun:
    """Run SLAM (or mapping with `slam.poses`) and its evaluation into `out`, as `inrslam run` does.

    Args: config / preset / overrides: as `load_config` (e.g. `["data.path=builtin:thin", "field.encoding=hash"]`);
        overwrite: replace a run already in `out`; progress: callable(frame, n_frames, info) after each frame.
    Returns: the finished run, read back (`load_run`).
    """
    ov = dict(overrides) if isinstance(overrides, dict) else list(overrides or [])
    cfg = absolute_paths(load_config(config, preset=preset, overrides=ov))
    return load_run(run_slam(cfg, Path(out), progress=progress, overwrite=overwrite))
