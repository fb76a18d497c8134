"""`run_slam`: the plain function behind `inrslam run` (scripts, notebooks and the benchmark call it too)."""

from __future__ import annotations

import os
from pathlib import Path

from inrslam.config.loader import load_config
from inrslam.errors import ConfigError


def run_slam(cfg, out_dir: str | os.PathLike, progress=None, overwrite: bool = False) -> Path:
    """Run SLAM with a resolved `RunConfig` and write the run directory `out_dir`."""
    from inrslam.data.open import open_dataset
    from inrslam.slam.system import SlamSystem

    out = Path(out_dir)
    if (out / "config.yaml").exists() and not overwrite:
        raise ConfigError(f"{out} already holds a run: continue it with --resume {out}, or pass --overwrite")
    if overwrite and out.exists():
        for name in ("log.jsonl", "metrics.json", "trajectory.txt", "trajectory_gt.txt", "mesh.ply",
                     "run_info.json", "keyframes.json", "checkpoints/latest.pt"):
            p = out / name
            if p.exists():
                p.unlink()
    dataset = open_dataset(cfg.data)
    return SlamSystem(cfg, dataset, out, progress=progress).run(resume=False)


def resume_slam(run_dir: str | os.PathLike, progress=None) -> Path:
    """Continue an interrupted run from its last checkpoint, with the run's own resolved config."""
    from inrslam.data.open import open_dataset
    from inrslam.slam.system import SlamSystem

    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.yaml"
    if not cfg_path.is_file():
        raise ConfigError(f"{run_dir}: not a run directory (no config.yaml)")
    cfg = load_config(cfg_path, preset=None)
    dataset = open_dataset(cfg.data)
    return SlamSystem(cfg, dataset, run_dir, progress=progress).run(resume=True)
