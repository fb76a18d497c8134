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
    are skipped, except frame 0 which then uses the identity), takes the `percentile` / 100 - `percentile`
    percentiles per axis (robust to flying pixels), grows the box to include the camera centres and adds `margin`
    on every side.

    Returns:
        (3, 2) float64 [[xmin, xmax], [ymin, ymax], [zmin, zmax]], metres.
    """
    pts, centres = [], []
    idx = np.unique(np.linspace(0, len(dataset) - 1, min(max(n_frames, 1), len(dataset))).round().astype(int))
    for i in idx.tolist():
        f = dataset[i]
        if f.pose_valid and np.all(np.isfinite(f.c2w)):
            c2w = f.c2w
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
