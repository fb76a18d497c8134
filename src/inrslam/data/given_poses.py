"""Camera poses given to a mapping-only run (`slam.poses`): the dataset's ground truth, or a TUM trajectory file
(ours, ORB-SLAM's, COLMAP's converted, ...) associated to the frames by timestamp.

A run maps with these poses instead of tracking (docs/given_poses.md); this module only reads and checks them.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from inrslam.data.frame import RGBDDataset
from inrslam.errors import DataError
from inrslam.io.trajectory import read_tum

GT = "gt"


@dataclass
class GivenPoses:
    """c2w: (N, 4, 4) float64 camera-to-world per dataset frame (OpenCV axes, metres); source: what run_info.json
    records of where they came from."""

    c2w: np.ndarray
    source: dict[str, Any]


def _frame_table(dataset: RGBDDataset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) timestamps, (N, 4, 4) GT poses and (N,) validity, without reading images where the reader can."""
    ts, poses, valid = (getattr(dataset, a, None) for a in ("timestamps", "poses", "pose_valid"))
    if ts is None or poses is None or valid is None:
        frames = [dataset[i] for i in range(len(dataset))]
        ts = np.array([f.timestamp for f in frames], dtype=np.float64)
        poses = np.stack([f.c2w for f in frames])
        valid = np.array([f.pose_valid for f in frames])
    return np.asarray(ts, np.float64), np.asarray(poses, np.float64), np.asarray(valid, bool)


def associate_to_frames(frame_ts: np.ndarray, file_ts: np.ndarray, tolerance: float, path: Path) -> np.ndarray:
    """Index into `file_ts` of the pose nearest in time to each frame; DataError naming the first frame with no pose
    within `tolerance` seconds.

    Args: frame_ts: (N,) frame timestamps, s; file_ts: (M,) pose timestamps, s (any order).
    Returns: (N,) int indices.
    """
    order = np.argsort(file_ts, kind="stable")
    sorted_ts = file_ts[order]
    right = np.clip(np.searchsorted(sorted_ts, frame_ts), 0, len(sorted_ts) - 1)
    left = np.clip(right - 1, 0, len(sorted_ts) - 1)
    pick = np.where(np.abs(sorted_ts[left] - frame_ts) <= np.abs(sorted_ts[right] - frame_ts), left, right)
    dt = np.abs(sorted_ts[pick] - frame_ts)
    bad = np.nonzero(~(dt <= tolerance))[0]
    if bad.size:
        i = int(bad[0])
        raise DataError(f"{path}: no pose within {tolerance:g} s of frame {i} (timestamp {frame_ts[i]:.6f}; nearest "
                        f"{sorted_ts[pick[i]]:.6f}, {dt[i]:.3g} s away); {bad.size} of {len(frame_ts)} frames have "
                        "none (raise slam.poses_tolerance, or give a pose for every frame)")
    return order[pick]


def load_given_poses(spec: str, dataset: RGBDDataset, tolerance: float = 0.02, anchor: bool = True) -> GivenPoses:
    """The poses `spec` names for every frame of `dataset`.

    Args:
        spec: "gt" (the dataset's ground truth: every frame must have one) or a TUM file
            (`timestamp tx ty tz qx qy qz qw` per line, camera-to-world).
        tolerance: seconds; each frame takes the file's pose nearest in time, at most this far.
        anchor: move a file's trajectory rigidly so frame 0 sits where a SLAM run starts it: the dataset's frame-0
            ground-truth pose (so meshes and trajectories compare with the ground truth), or the identity when
            frame 0 has none (where `estimate_bounds` puts it too); skipped when the trajectory already starts there.
    """
    ts, gt, valid = _frame_table(dataset)
    if spec == GT:
        bad = np.nonzero(~valid | ~np.isfinite(gt).all(axis=(1, 2)))[0]
        if bad.size:
            i = int(bad[0])
            raise DataError(f"{getattr(dataset, 'root', 'dataset')}: frame {i} (timestamp {ts[i]:.6f}) has no "
                            f"ground-truth pose ({bad.size} of {len(ts)} frames have none); --poses gt needs one for "
                            "every frame: give a pose file (--poses FILE) or select frames with data.start / "
                            "data.max_frames")
        return GivenPoses(gt.copy(), {"source": GT})
    path = Path(spec).expanduser()
    if path.is_dir():
        raise DataError(f"{path}: is a folder; --poses expects 'gt' or a TUM trajectory file")
    file_ts, file_c2w = read_tum(path)
    c2w = file_c2w[associate_to_frames(ts, file_ts, tolerance, path)]
    source: dict[str, Any] = {"source": "file", "path": str(path.resolve()),
                              "sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "tolerance_s": tolerance,
                              "anchored": False}
    if anchor:  # where a SLAM run starts frame 0: its ground truth, else the identity
        start = gt[0] if valid[0] and np.isfinite(gt[0]).all() else np.eye(4)
        A = start @ np.linalg.inv(c2w[0])
        if not np.allclose(A, np.eye(4), atol=1e-6):
            c2w = A @ c2w
            source["anchored"] = True
    return GivenPoses(c2w, source)
