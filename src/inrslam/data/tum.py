"""TUM RGB-D benchmark (Sturm et al. 2012), docs/spec.md §9.4.

Layout::

    <seq>/rgb.txt            "timestamp rgb/NNN.png" per line ('#' comments)
    <seq>/depth.txt          "timestamp depth/NNN.png"; uint16, metres = value / 5000
    <seq>/groundtruth.txt    "timestamp tx ty tz qx qy qz qw" (scalar-last quaternion), c2w of the colour camera,
                             OpenCV axes; optional (also accepted: pose.txt)

Colour and depth frames are paired one-to-one as TUM's associate.py does (`data.timestamps.associate`: every
pair within `data.tum.max_dt_depth`, closest first); colour frames without depth are dropped. The pose is the
nearest ground-truth sample within `data.tum.max_dt_pose`, else invalid.
Intrinsics: `intrinsics.json` (fx, fy, cx, cy, width, height, depth_scale; written by our TUM exporter) if present,
else the published ROS-default calibration of freiburg1/2/3 named by the sequence folder's own name (not its
parents'; freiburg1 with a warning otherwise);
lens distortion is not corrected.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Optional

import numpy as np

from inrslam.data.base import FolderDataset, checked_depth_scale, first_existing, read_camera_json
from inrslam.data.frame import NAN_POSE, Intrinsics
from inrslam.data.posefiles import parse_floats, read_lines
from inrslam.data.registry import DATASETS
from inrslam.data.timestamps import associate
from inrslam.errors import ConfigError, DataError, InrslamWarning
from inrslam.io.trajectory import quat_rotation

TUM_INTRINSICS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
"""fx, fy, cx, cy of the TUM cameras (640 x 480), from the dataset's calibration page."""


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """TUM `rgb.txt` / `depth.txt`: (N,) timestamps (s) and N relative file names."""
    lines = read_lines(path, "file list")
    ts, names = [], []
    for n, s in lines:
        parts = s.split()
        if len(parts) != 2:
            raise DataError(f"{path}:{n}: expected 'timestamp filename', got {s[:80]!r}")
        try:
            t = float(parts[0])
        except ValueError:
            raise DataError(f"{path}:{n}: non-numeric timestamp {parts[0]!r}") from None
        if not np.isfinite(t):
            raise DataError(f"{path}:{n}: timestamp {parts[0]!r} is not a finite number of seconds")
        ts.append(t)
        names.append(parts[1])
    if not ts:
        raise DataError(f"{path}: no entries found (expected lines 'timestamp filename')")
    return np.array(ts), names


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """TUM ground truth: (M,) timestamps and (M, 4, 4) c2w; non-finite lines give NaN poses (kept, flagged later)."""
    lines = read_lines(path, "ground-truth file")
    ts, poses = [], []
    for n, s in lines:
        v = parse_floats(path, n, s, 8, "timestamp tx ty tz qx qy qz qw")
        if not np.isfinite(v[0]):
            raise DataError(f"{path}:{n}: non-finite timestamp")
        T = NAN_POSE.copy()
        if np.all(np.isfinite(v[1:])):
            T = np.eye(4)
            T[:3, :3] = quat_rotation(v[4:8], f"{path}:{n}")
            T[:3, 3] = v[1:4]
        ts.append(v[0])
        poses.append(T)
    if not ts:
        raise DataError(f"{path}: no poses found (expected lines 'timestamp tx ty tz qx qy qz qw')")
    order = np.argsort(ts, kind="stable")
    return np.array(ts)[order], np.stack(poses)[order]


def nearest(query: np.ndarray, ref_sorted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each query time, the index of the nearest time in sorted `ref_sorted` and |difference| (s)."""
    if len(ref_sorted) == 1:
        j = np.zeros(len(query), dtype=np.int64)
    else:
        right = np.clip(np.searchsorted(ref_sorted, query), 1, len(ref_sorted) - 1)
        left = right - 1
        j = np.where(np.abs(query - ref_sorted[left]) <= np.abs(query - ref_sorted[right]), left, right)
    return j, np.abs(query - ref_sorted[j])


@DATASETS.register("tum", help="TUM RGB-D: rgb.txt, depth.txt, groundtruth.txt")
class TUMDataset(FolderDataset):
    """TUM RGB-D sequence with timestamp association."""

    name = "tum"
    layout = "rgb.txt, depth.txt ('timestamp filename' lines) and optionally groundtruth.txt"
    default_depth_scale = 5000.0

    @classmethod
    def detect(cls, root: Path) -> bool:
        root = Path(root)
        return (root / "rgb.txt").is_file() and (root / "depth.txt").is_file()

    def _scan(self) -> Optional[Intrinsics]:
        max_dt_d, max_dt_p = self.cfg.tum.max_dt_depth, self.cfg.tum.max_dt_pose
        if max_dt_d < 0 or max_dt_p < 0:
            raise ConfigError("data.tum.max_dt_depth / data.tum.max_dt_pose: must be >= 0 seconds")
        rgb_list, depth_list = self.root / "rgb.txt", self.root / "depth.txt"
        self.gt_mesh = first_existing([self.root / "mesh.ply"])  # our TUM exports carry one (TUM itself has none)
        t_rgb, rgb_names = read_file_list(rgb_list)
        t_d, d_names = read_file_list(depth_list)
        order_r, order_d = np.argsort(t_rgb, kind="stable"), np.argsort(t_d, kind="stable")
        t_rgb, rgb_names = t_rgb[order_r], [rgb_names[k] for k in order_r]
        t_d, d_names = t_d[order_d], [d_names[k] for k in order_d]
        ri, di = associate(t_rgb, t_d, max_dt_d)
        if not len(ri):
            raise DataError(
                f"{rgb_list} / {depth_list}: no colour and depth timestamps within {max_dt_d} s of each other "
                f"(colour {t_rgb[0]:.3f}..{t_rgb[-1]:.3f} s, depth {t_d[0]:.3f}..{t_d[-1]:.3f} s); "
                "expected the lists of one sequence (or raise data.tum.max_dt_depth)"
            )
        self._timestamps = t_rgb[ri]
        self._rgb = [self.root / rgb_names[i] for i in ri]
        self._depth = [self.root / d_names[d] for d in di]
        self._ids = ri.astype(np.int64)
        for lst, paths in ((rgb_list, self._rgb), (depth_list, self._depth)):
            missing = next((p for p in paths if not p.is_file()), None)
            if missing is not None:
                raise DataError(f"{missing}: image listed in {lst.name} not found")
        self.dropped_unpaired = int(len(t_rgb) - len(ri))  # colour frames without a depth partner
        gt_file = first_existing([self.root / "groundtruth.txt", self.root / "pose.txt"])
        n = len(ri)
        self._c2w = np.repeat(NAN_POSE[None], n, axis=0)
        self._valid = np.zeros(n, dtype=bool)
        if gt_file is not None:
            t_gt, gt = read_groundtruth(gt_file)
            k, dtp = nearest(self._timestamps, t_gt)
            ok = (dtp <= max_dt_p) & np.all(np.isfinite(gt[k]), axis=(1, 2))
            self._c2w[ok] = gt[k[ok]]
            self._valid = ok
        self.gt_file = gt_file
        cam_file = self.root / "intrinsics.json"  # written by inrslam.scenes.export_tum (not part of TUM)
        cam: dict[str, float] | tuple[float, float, float, float]  # the export's JSON, else a TUM_INTRINSICS row
        if cam_file.is_file():
            cam = read_camera_json(cam_file)
            if self.cfg.depth_scale is None and "depth_scale" in cam:
                self.depth_scale = checked_depth_scale(cam["depth_scale"], f"{cam_file}: depth_scale")
            w, h = int(cam.get("width", 640)), int(cam.get("height", 480))
            return Intrinsics(cam["fx"], cam["fy"], cam["cx"], cam["cy"], w, h)
        return Intrinsics(*self._camera_by_name(), 640, 480)

    def _camera_by_name(self) -> tuple[float, float, float, float]:
        """The TUM_INTRINSICS row the sequence folder's own name names (as given, else its symlink target's);
        freiburg1 with a warning when neither names a camera (and data.intrinsics does not say)."""
        for name in (Path(os.path.abspath(self.root)).name, self.root.resolve().name):
            key = next((k for k in TUM_INTRINSICS if k in name.lower()), None)
            if key is not None:
                return TUM_INTRINSICS[key]
        if self.cfg.intrinsics is None:
            warnings.warn(f"{self.root}: the folder name names no TUM camera (freiburg1/2/3) and there is no "
                          "intrinsics.json; using freiburg1's intrinsics (set data.intrinsics for another camera)",
                          InrslamWarning, stacklevel=2)
        return TUM_INTRINSICS["freiburg1"]
