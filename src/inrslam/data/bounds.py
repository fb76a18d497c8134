"""Scene bounds from depth frames spread over the sequence and their ground-truth poses (when no table or config
gives them)."""

from __future__ import annotations

import numpy as np

from inrslam.data.frame import RGBDDataset
from inrslam.errors import DataError
from inrslam.geometry.pinhole import backproject_np


def backproject_world(depth: np.ndarray, K: np.ndarray, c2w: np.ndarray, step: int = 1) -> np.ndarray:
    """Valid depth pixels (every `step`-th row and column) -> (M, 3) world points, metres.

    p_cam = z * ((u - cx) / fx, (v - cy) / fy, 1),  p_world = R p_cam + t  with c2w = [R | t].
    """
    p = backproject_np(depth, K[0, 0], K[1, 1], K[0, 2], K[1, 2], stride=step)
    return p @ c2w[:3, :3].T + c2w[:3, 3]


def estimate_bounds(
    dataset: RGBDDataset,
    n_frames: int = 20,
    margin: float = 0.2,
    percentile: float = 0.5,
    points_per_frame: int = 20000,
) -> np.ndarray:
    """Axis-aligned scene box from `n_frames` frames evenly spread over the sequence (first and last included), so
    a camera that travels still gets a box covering what it will see.

    Back-projects a pixel subsample of each frame's depth with its ground-truth pose (frames with an invalid pose
    are skipped), takes the `percentile` / 100 - `percentile` percentiles per axis (robust to flying pixels), grows
    the box to include the camera centres and adds `margin` on every side. When frame 0 has no pose, the SLAM loop
    starts it at the identity: the box is then in that frame, frame 0 at the identity and the others' poses taken
    relative to the first frame that has one (as if it sat where frame 0 is; the motion between them is the error).

    Returns:
        (3, 2) float64 [[xmin, xmax], [ymin, ymax], [zmin, zmax]], metres.
    """
    pts, centres = [], []
    idx = np.unique(np.linspace(0, len(dataset) - 1, min(max(n_frames, 1), len(dataset))).round().astype(int))
    to_map = np.eye(4)  # ground-truth world -> the frame the SLAM loop maps in
    first = dataset[0]
    if not _has_pose(first):
        k0 = _first_posed(dataset, idx)
        if k0 is not None:
            to_map = np.linalg.inv(dataset[k0].c2w)
            idx = np.union1d(idx, [k0])
    for i in idx.tolist():
        f = first if i == 0 else dataset[i]
        if _has_pose(f):
            c2w = to_map @ f.c2w
        elif i == 0:
            c2w = np.eye(4)
        else:
            continue
        H, W = f.depth.shape
        step = max(1, int(np.sqrt(H * W / max(points_per_frame, 1))))
        pts.append(backproject_world(f.depth, f.intrinsics.K, c2w, step))
        centres.append(c2w[:3, 3])
    allp = np.concatenate(pts) if pts else np.zeros((0, 3))
    if len(allp) == 0:
        raise DataError(
            f"{dataset.root}: cannot estimate scene bounds: no valid depth in {len(idx)} frames spread over the "
            "sequence; set data.bounds"
        )
    lo = np.percentile(allp, percentile, axis=0)
    hi = np.percentile(allp, 100.0 - percentile, axis=0)
    c = np.stack(centres)
    lo, hi = np.minimum(lo, c.min(0)), np.maximum(hi, c.max(0))
    return np.stack([lo - margin, hi + margin], axis=1)


def _has_pose(f) -> bool:
    return bool(f.pose_valid) and bool(np.all(np.isfinite(f.c2w)))


def _first_posed(dataset: RGBDDataset, idx: np.ndarray) -> int | None:
    """The first frame with a ground-truth pose: from the dataset's `pose_valid` table when it has one (no images
    read), else the first of the sampled frames `idx`; None when there is none."""
    valid = getattr(dataset, "pose_valid", None)
    if valid is not None and not callable(valid) and len(valid) == len(dataset):
        for k in np.flatnonzero(np.asarray(valid, dtype=bool)).tolist():
            if _has_pose(dataset[k]):
                return int(k)
        return None
    return next((int(k) for k in idx.tolist() if _has_pose(dataset[k])), None)
