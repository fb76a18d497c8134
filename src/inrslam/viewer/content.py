"""What the viewer shows of one finished run, gathered from a `LoadedRun` without a server: the paths of its mesh,
intermediate meshes and held-out pictures, its trajectories as segments, its keyframe poses and camera, and a note
for each thing the run directory does not hold."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from inrslam.io.rundir import RunDir
from inrslam.viewer.shapes import camera_fov, frustum_scale, polyline_segments, valid_poses

if TYPE_CHECKING:
    from inrslam.runner.loaded import LoadedRun

_NUMBERED = re.compile(r"(?:frame|mesh)_(\d+)\.(?:png|ply)")


@dataclass
class RunContent:
    """One run, ready to draw. Poses (N, 4, 4) c2w OpenCV axes, metres; segments (M, 2, 3) float32.

    Attributes:
        label: short name (folder, F x G); est, gt: the poses (gt None without ground truth);
        est_segments, gt_segments: the paths (gt_segments None without ground truth);
        keyframes: {frame id: c2w} of the keyframes with a pose; fov_y [rad], aspect (W / H): the camera;
        frustum_scale [m]; mesh: mesh.ply or None; meshes: {frame: intermediate mesh path} (meshes/);
        renders: {frame: held-out picture path} (renders/, observed | render | depth | error);
        metrics: metrics.json or None; notes: one line per thing left out.
    """

    label: str
    root: Path
    est: np.ndarray
    gt: np.ndarray | None
    est_segments: np.ndarray
    gt_segments: np.ndarray | None
    keyframes: dict[int, np.ndarray]
    fov_y: float
    aspect: float
    frustum_scale: float
    mesh: Path | None
    meshes: dict[int, Path] = field(default_factory=dict)
    renders: dict[int, Path] = field(default_factory=dict)
    metrics: dict | None = None
    notes: list[str] = field(default_factory=list)


def numbered_files(folder: Path, suffix: str) -> dict[int, Path]:
    """{frame: path} of frame_NNNNNN.png / mesh_NNNNNN.ply files in `folder` (empty if it is missing), sorted."""
    if not folder.is_dir():
        return {}
    found = {}
    for p in folder.iterdir():
        m = _NUMBERED.fullmatch(p.name)
        if m and p.suffix == suffix:
            found[int(m.group(1))] = p
    return dict(sorted(found.items()))


def run_label(run: LoadedRun) -> str:
    """`folder (encoding x render)`, e.g. `room (dense x density)`."""
    cfg = run.config
    return f"{run.root.name} ({cfg.field.encoding} x {cfg.render.name})"


def gather(run: LoadedRun) -> RunContent:
    """Everything `inrslam view` shows of `run`; what is missing becomes a note instead of an error."""
    rd = RunDir(run.root)
    notes = []
    gt = run.gt if run.gt is not None and valid_poses(run.gt).any() else None
    if gt is None:
        notes.append("no ground-truth trajectory")
    mesh = rd.mesh if rd.mesh.is_file() else None
    if mesh is None:
        notes.append("no mesh.ply")
    renders = numbered_files(rd.renders, ".png")
    if not renders:
        notes.append("no held-out renders (renders/)")
    if run.metrics is None:
        notes.append("no metrics.json (the run is unfinished)")
    intrinsics = run.run_info.get("intrinsics")
    try:
        fov_y, aspect = camera_fov(intrinsics)
        if not intrinsics:
            notes.append("no camera intrinsics in run_info.json: frusta drawn with a 60 degree field of view")
    except ValueError as e:
        fov_y, aspect = camera_fov(None)
        notes.append(f"run_info.json: {e}: frusta drawn with a 60 degree field of view")
    ok = valid_poses(run.est)
    keyframes = {int(k): run.est[k] for k in run.keyframes if 0 <= k < len(run.est) and ok[k]}
    gt_segments = None if gt is None else polyline_segments(gt)
    return RunContent(label=run_label(run), root=run.root, est=run.est, gt=gt,
                      est_segments=polyline_segments(run.est), gt_segments=gt_segments,
                      keyframes=keyframes, fov_y=fov_y, aspect=aspect, frustum_scale=frustum_scale(run.est),
                      mesh=mesh, meshes=numbered_files(rd.meshes, ".ply"), renders=renders, metrics=run.metrics,
                      notes=notes)


def panel_views(picture: np.ndarray) -> np.ndarray:
    """The observed colour, the first of the four side-by-side views of a held-out picture (H, 4W, 3) -> (H, W, 3),
    shown on the frame's frustum."""
    return picture[:, : picture.shape[1] // 4]
