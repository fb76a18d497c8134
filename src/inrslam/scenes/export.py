"""Export any `RGBDDataset` to the public Replica (NICE-SLAM) and TUM RGB-D folder layouts.

Replica (NICE-SLAM release)::

    <out>/results/frame000000.jpg   JPEG, quality 95, no chroma subsampling
    <out>/results/depth000000.png   uint16, metres = value / 6553.5
    <out>/traj.txt                  one line per frame: 16 values, row-major 4x4 camera-to-world, OpenCV axes
    <out>/mesh.ply                  ground-truth mesh (copied when the dataset has one)
    <out>/cam_params.json           {"camera": {w, h, fx, fy, cx, cy, scale}} (as the Replica release)

TUM RGB-D::

    <out>/rgb/<t>.png, <out>/depth/<t_d>.png   8-bit colour; uint16 depth, metres = value / 5000
    <out>/rgb.txt, <out>/depth.txt              "timestamp filename" lines after three '#' header lines
    <out>/groundtruth.txt                       "timestamp tx ty tz qx qy qz qw", c2w OpenCV axes, at the rgb times
    <out>/intrinsics.json                       fx, fy, cx, cy, width, height (the TUM layout has no calibration file)

Depth timestamps are the colour ones + `TUM_DEPTH_DT` so readers must associate the two streams. A new or empty
`<out>` is written as a whole (into a temporary folder renamed at the end): an interrupted export leaves no half
dataset behind.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from inrslam.geometry.intrinsics import Intrinsics
from inrslam.io.atomic import atomic_folder, atomic_path, write_json, write_text
from inrslam.io.trajectory import write_tum
from inrslam.scenes.store import encode_depth

REPLICA_DEPTH_SCALE = 6553.5
TUM_DEPTH_SCALE = 5000.0
TUM_DEPTH_DT = 0.005
"""Seconds added to the depth timestamps of a TUM export."""


def _rgb8(rgb: np.ndarray) -> np.ndarray:
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def _save_image(path: Path, img: np.ndarray, **kw) -> None:
    with atomic_path(path) as tmp:
        Image.fromarray(img).save(tmp, **kw)


def _intrinsics_dict(intr: Intrinsics) -> dict:
    return {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy, "width": intr.width, "height": intr.height}


def _copy_mesh(dataset, out: Path) -> None:
    mesh = getattr(dataset, "gt_mesh", None)
    if mesh is not None and Path(mesh).is_file():
        with atomic_path(out / "mesh.ply") as tmp:
            shutil.copyfile(mesh, tmp)


def _whole(write, dataset, out_dir: str | Path) -> Path:
    """write(dataset, folder, name) into `out_dir`: as a whole where it is new or empty, else in place."""
    out = Path(out_dir)
    if out.is_dir() and any(out.iterdir()):
        write(dataset, out, out.name)
        return out
    with atomic_folder(out) as tmp:
        write(dataset, tmp, out.name)
    return out


def export_replica(dataset, out_dir: str | Path) -> Path:
    """Write `dataset` in the NICE-SLAM Replica layout (see module docstring). Returns `out_dir`.

    Poses must be valid (camera-to-world, OpenCV axes); depth is clipped at 65535 / 6553.5 = 10 m.
    """
    return _whole(_write_replica, dataset, out_dir)


def export_tum(dataset, out_dir: str | Path) -> Path:
    """Write `dataset` in the TUM RGB-D layout (see module docstring). Returns `out_dir`.

    Timestamps are the dataset's (seconds); file names use them with 6 decimals. Depth is clipped at 13.1 m.
    """
    return _whole(_write_tum, dataset, out_dir)


def _write_replica(dataset, out: Path, name: str) -> None:
    (out / "results").mkdir(parents=True, exist_ok=True)
    rows = []
    for k, fr in enumerate(dataset):
        _save_image(out / "results" / f"frame{k:06d}.jpg", _rgb8(fr.rgb), quality=95, subsampling=0)
        _save_image(out / "results" / f"depth{k:06d}.png", encode_depth(fr.depth, REPLICA_DEPTH_SCALE))
        rows.append(" ".join(f"{v:.12e}" for v in np.asarray(fr.c2w, dtype=np.float64).reshape(16)))
    write_text(out / "traj.txt", "\n".join(rows) + "\n")
    intr = dataset.intrinsics
    write_json(out / "cam_params.json", {"camera": {"w": intr.width, "h": intr.height, "fx": intr.fx, "fy": intr.fy,
                                                    "cx": intr.cx, "cy": intr.cy, "scale": REPLICA_DEPTH_SCALE}})
    _copy_mesh(dataset, out)


def _write_tum(dataset, out: Path, name: str) -> None:
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    rgb_lines = ["# color images", f"# file: '{name}'", "# timestamp filename"]
    depth_lines = ["# depth maps", f"# file: '{name}'", "# timestamp filename"]
    ts, poses = [], []
    for fr in dataset:
        t_rgb, t_depth = f"{fr.timestamp:.6f}", f"{fr.timestamp + TUM_DEPTH_DT:.6f}"
        _save_image(out / "rgb" / f"{t_rgb}.png", _rgb8(fr.rgb))
        _save_image(out / "depth" / f"{t_depth}.png", encode_depth(fr.depth, TUM_DEPTH_SCALE))
        rgb_lines.append(f"{t_rgb} rgb/{t_rgb}.png")
        depth_lines.append(f"{t_depth} depth/{t_depth}.png")
        ts.append(fr.timestamp)
        poses.append(np.full((4, 4), np.nan) if not fr.pose_valid else np.asarray(fr.c2w, dtype=np.float64))
    write_text(out / "rgb.txt", "\n".join(rgb_lines) + "\n")
    write_text(out / "depth.txt", "\n".join(depth_lines) + "\n")
    write_tum(out / "groundtruth.txt", np.array(ts), np.stack(poses), header="ground truth trajectory (c2w, OpenCV axes)")
    write_json(out / "intrinsics.json", {**_intrinsics_dict(dataset.intrinsics), "depth_scale": TUM_DEPTH_SCALE})
    _copy_mesh(dataset, out)
