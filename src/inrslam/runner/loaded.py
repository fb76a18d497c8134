"""A finished (or interrupted) run directory, read back for inspection: config, trajectories, keyframes, metrics,
mesh and the trained map, which renders any view. Strictly read-only: nothing in the folder is written, truncated
or touched (unlike `resume_slam`, which cuts `log.jsonl` back to its checkpoint)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import torch

from inrslam.errors import RunError
from inrslam.eval.config import HeldoutDepth
from inrslam.io.rundir import RunDir
from inrslam.io.trajectory import read_tum


@dataclass
class LoadedRun:
    """What `load_run` returns. Poses are (N, 4, 4) float64 camera-to-world in OpenCV axes, metres.

    Attributes:
        root: the run directory; config: its resolved `RunConfig`; run_info / metrics: its JSON files (metrics None
            while the run is unfinished).
        timestamps: (N,) seconds of the processed frames; est: estimated poses; gt: ground truth (None without);
        relative: non-keyframes carried by their keyframes (docs/spec.md §7.6); keyframes: keyframe frame ids.
    """

    root: Path
    config: Any
    run_info: dict
    metrics: dict | None
    timestamps: np.ndarray
    est: np.ndarray
    gt: np.ndarray | None
    relative: np.ndarray | None
    keyframes: list[int]
    _rd: RunDir = field(repr=False, default=None)  # type: ignore[assignment]

    def _info(self, key: str) -> Any:
        """run_info.json's `key`, or a RunError naming the file (a run directory from another version)."""
        if key not in self.run_info:
            raise RunError(f"{self._rd.run_info}: no '{key}' (expected a run directory written by inrslam run)")
        return self.run_info[key]

    def mesh(self, frame: int | None = None):
        """The final `mesh.ply` (or the intermediate mesh after `frame`) as a trimesh; None if the run has none."""
        import trimesh

        path = self._rd.mesh if frame is None else self._rd.mesh_at(frame)
        if not path.is_file():
            return None
        try:
            return trimesh.load(path, process=False)
        except Exception as e:  # trimesh raises many kinds on a damaged file
            raise RunError(f"{path}: unreadable mesh ({type(e).__name__}: {e}); expected a PLY written by inrslam "
                           "run") from None

    @cached_property
    def model(self):
        """The trained scene model F x G from `checkpoints/latest.pt` (CPU, eval mode). RunError without one."""
        from inrslam.runner.checkpoint import load_checkpoint
        from inrslam.slam.systems import model_class

        ckpt = self._rd.checkpoint
        if not ckpt.is_file():
            raise RunError(f"{ckpt}: no checkpoint, so no map to render (runs made with "
                           "output.keep_checkpoint=false keep none)")
        state = load_checkpoint(ckpt)
        model = model_class(self.config)(self.config, np.asarray(self._info("bounds"), dtype=np.float64))
        try:
            model.load_state_dict(state["model"])
        except (KeyError, RuntimeError) as e:
            raise RunError(f"{ckpt}: the checkpoint does not fit the run's config.yaml "
                           f"({str(e).splitlines()[0][:160]})") from None
        return model.eval()

    @property
    def intrinsics(self):
        """The run's camera (`Intrinsics`, from run_info.json)."""
        from inrslam.geometry.intrinsics import Intrinsics

        d = self._info("intrinsics")
        if not isinstance(d, dict) or not all(k in d for k in ("fx", "fy", "cx", "cy", "width", "height")):
            raise RunError(f"{self._rd.run_info}: 'intrinsics' is {str(d)[:60]} (expected fx, fy, cx, cy, width, "
                           "height)")
        return Intrinsics(fx=d["fx"], fy=d["fy"], cx=d["cx"], cy=d["cy"], width=int(d["width"]),
                          height=int(d["height"]))

    def render(self, c2w: np.ndarray, intrinsics=None, samples: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Render the map from camera pose `c2w` (4, 4) without measured depth, as the held-out evaluation does
        (its depth as `eval.heldout_depth` says).

        Args: intrinsics: camera (default: the run's); samples: surface-search samples per ray (default: the
            run's `eval.heldout_samples`).
        Returns: rgb (H, W, 3) in [0, 1] and depth (H, W) in metres, float32 numpy.
        """
        c2w = np.asarray(c2w, dtype=np.float64)
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise ValueError(f"render: c2w must be a finite (4, 4) pose, got shape {c2w.shape}")
        n = int(samples or self.config.eval.heldout_samples)
        with torch.no_grad():
            rgb, depth = self.model.render_image(torch.as_tensor(c2w, dtype=torch.float32),
                                                 intrinsics or self.intrinsics, n_coarse=n,
                                                 depth=HeldoutDepth(self.config.eval.heldout_depth).value,
                                                 refine=self.config.eval.heldout_refine)
        return rgb.numpy(), depth.numpy()


def _tum(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    return read_tum(path) if path.is_file() else None


def load_run(run_dir: str | os.PathLike) -> LoadedRun:
    """Read a run directory (read-only). RunError naming the folder when it holds no run."""
    from inrslam.config import load_config
    from inrslam.eval.run import associated_gt

    rd = RunDir(run_dir)
    if not rd.config.is_file() or not rd.run_info.is_file():
        raise RunError(f"{rd.root}: not a run directory (expected config.yaml and run_info.json)")
    bad = rd.corrupt_files()
    if bad:
        raise RunError(f"{rd.root / bad[0]}: not a JSON object (truncated or edited?); expected the run's record")
    info = rd.read_run_info() or {}
    traj = _tum(rd.trajectory)
    if traj is None:
        raise RunError(f"{rd.root}: no trajectory.txt yet (the run has not finished; inrslam run --resume "
                       f"{rd.root} continues it)")
    ts, est = traj
    cfg = load_config(rd.config, preset=None, check_variants=False)
    gt = _tum(rd.trajectory_gt)
    rel = _tum(rd.trajectory_relative)
    # on the estimate's timestamps (frames without GT: NaN), associated as the evaluation does
    gt_poses = associated_gt(ts, gt[0], gt[1], cfg.eval.max_time_diff) if gt is not None else None
    kf_file = rd.read_json("keyframes") if rd.keyframes.is_file() else None
    kf = kf_file.get("keyframes") if isinstance(kf_file, dict) else None
    kf = [k for k in kf if isinstance(k, int) and not isinstance(k, bool)] if isinstance(kf, list) else []
    return LoadedRun(root=rd.root, config=cfg, run_info=info, metrics=rd.read_metrics(), timestamps=ts, est=est,
                     gt=gt_poses,
                     relative=rel[1] if rel is not None else None, keyframes=list(kf), _rd=rd)
