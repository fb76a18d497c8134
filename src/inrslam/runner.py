"""`run_slam` / `resume_slam`: the plain functions behind `inrslam run` (scripts, notebooks and the benchmark call
them too). They sit above `slam` and `eval`: run SLAM, then evaluate the run directory it wrote."""

from __future__ import annotations

import os
from pathlib import Path

from inrslam.config.loader import load_config
from inrslam.errors import ConfigError

RUN_FILES = ("log.jsonl", "metrics.json", "trajectory.txt", "trajectory_gt.txt", "mesh.ply", "run_info.json",
             "keyframes.json", "checkpoints/latest.pt", "config.yaml")
RUN_DIRS = ("tensorboard", "meshes")


def run_slam(cfg, out_dir: str | os.PathLike, progress=None, overwrite: bool = False) -> Path:
    """Run SLAM with a resolved `RunConfig`, write the run directory `out_dir` and evaluate it.

    Args:
        cfg: `RunConfig` (from `inrslam.config.load_config`).
        out_dir: run directory; must not hold a run unless `overwrite`.
        progress: optional callable(frame_index, n_frames, info) called after every frame.
    """
    from inrslam.data.open import open_dataset
    from inrslam.fields.kernels.threads import resolve_threads, thread_scope
    from inrslam.slam.system import SlamSystem

    out = Path(out_dir)
    if (out / "config.yaml").exists() and not overwrite:
        raise ConfigError(f"{out} already holds a run: continue it with --resume {out}, or pass --overwrite")
    if overwrite:
        import shutil

        for name in RUN_FILES:
            if (out / name).exists():
                (out / name).unlink()
        for name in RUN_DIRS:
            shutil.rmtree(out / name, ignore_errors=True)
    dataset = open_dataset(cfg.data)
    threads = resolve_threads(cfg.threads)
    with thread_scope(threads):
        system = SlamSystem(cfg, dataset, out, progress=progress, threads=threads)
        system.run(resume=False)
        return _evaluate(system)


def resume_slam(run_dir: str | os.PathLike, progress=None) -> Path:
    """Continue an interrupted run from its last checkpoint, with the run's own resolved `config.yaml`."""
    from inrslam.data.open import open_dataset
    from inrslam.fields.kernels.threads import resolve_threads, thread_scope
    from inrslam.slam.system import SlamSystem

    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.yaml"
    if not cfg_path.is_file():
        raise ConfigError(f"{run_dir}: not a run directory (no config.yaml)")
    cfg = load_config(cfg_path, preset=None)
    dataset = open_dataset(cfg.data)
    threads = _recorded_threads(run_dir) if not cfg.threads else None
    threads = threads or resolve_threads(cfg.threads)
    with thread_scope(threads):
        system = SlamSystem(cfg, dataset, run_dir, progress=progress, threads=threads)
        system.run(resume=True)
        return _evaluate(system)


def _recorded_threads(run_dir: Path) -> int | None:
    """The thread count an interrupted run used (`run_info.json`), so its resumed part sums in the same order."""
    import json

    try:
        n = json.loads((run_dir / "run_info.json").read_text()).get("threads")
    except (OSError, ValueError, AttributeError):
        return None
    return int(n) if isinstance(n, int) and n > 0 else None


def _evaluate(system) -> Path:
    """Held-out renders with the final map and estimated poses, then every result metric (docs/metrics.md)."""
    import json

    from inrslam.eval.heldout import heldout_metrics
    from inrslam.eval.run import evaluate_run
    from inrslam.io.atomic import write_json

    ev = system.cfg.eval
    out = system.out
    if ev.enabled:
        if ev.heldout_every:
            metrics = json.loads((out / "metrics.json").read_text())
            # frames between keyframes (offset by half the mapping period), rendered without jitter
            render = lambda c2w, intr: system.model.render_image(c2w, intr, n_coarse=ev.heldout_samples)
            metrics.update(heldout_metrics(render, system.dataset, system.est, ev.heldout_every, ev.heldout_max,
                                           offset=system.cfg.slam.map_every // 2))
            write_json(out / "metrics.json", metrics)
        evaluate_run(out, ev)
    system.write_run_info("complete")
    return out
