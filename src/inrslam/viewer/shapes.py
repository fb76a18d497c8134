"""What the viewer draws, as plain arrays: trajectory polylines, camera frusta poses and sizes, colours, the world's
up axis. No server and no I/O, so the tests check them on analytic poses.

Poses are (N, 4, 4) camera-to-world in OpenCV axes (x right, y down, z forward), metres, NaN rows where a frame has
none. viser draws a camera frustum in the same OpenCV camera axes, so a frustum's pose is the camera's c2w.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

# the up axis and the overview direction are defined once, with the run directory's mesh picture
from inrslam.eval.mesh_thumbnail import up_direction as up_direction
from inrslam.eval.mesh_thumbnail import view_direction

RGB = tuple[int, int, int]

GT_COLOR: RGB = (110, 110, 110)  # ground-truth trajectories: grey
CURRENT_COLOR: RGB = (230, 40, 40)  # the live camera
RUN_COLORS: tuple[RGB, ...] = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (148, 103, 189), (140, 86, 75),
                               (227, 119, 194), (188, 189, 34), (23, 190, 207))  # matplotlib tab10, less red / grey
DEFAULT_FOV_Y = math.radians(60.0)  # a camera without intrinsics (fake or old run directories)
DEFAULT_ASPECT = 4.0 / 3.0


def run_color(k: int) -> RGB:
    """Colour of run number `k` (estimated trajectory and keyframe frusta); cycles after 8 runs."""
    return RUN_COLORS[k % len(RUN_COLORS)]


def valid_poses(poses: np.ndarray) -> np.ndarray:
    """(N,) bool: rows of (N, 4, 4) `poses` that are finite."""
    return np.isfinite(poses.reshape(len(poses), -1)).all(axis=1)


def polyline_segments(poses: np.ndarray) -> np.ndarray:
    """The camera path as line segments for viser's `add_line_segments`.

    Args: poses: (N, 4, 4) c2w, NaN rows where the frame has no pose.
    Returns: (M, 2, 3) float32 segments from each camera centre to the next frame's, only where both frames have a
        pose: a frame without one breaks the line instead of bridging it. M = 0 for fewer than two such neighbours.
    """
    pos = np.asarray(poses, dtype=np.float64)[:, :3, 3]
    ok = valid_poses(np.asarray(poses))
    both = ok[:-1] & ok[1:]
    return np.stack([pos[:-1][both], pos[1:][both]], axis=1).astype(np.float32)


def frustum_pose(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """viser pose (wxyz (4,), position (3,)) of the frustum of the camera `c2w` (4, 4): viser's frusta use OpenCV
    camera axes, so the rotation is c2w's (as a unit quaternion, scalar first) and the position its centre."""
    c2w = np.asarray(c2w, dtype=np.float64)
    xyzw = Rotation.from_matrix(c2w[:3, :3]).as_quat()
    return np.roll(xyzw, 1), c2w[:3, 3].copy()


def camera_fov(intrinsics: dict | None) -> tuple[float, float]:
    """(vertical field of view [rad], aspect width / height) of a pinhole camera given as run_info.json's
    `intrinsics` dict (fx, fy, cx, cy, width, height); DEFAULT_FOV_Y, DEFAULT_ASPECT when None; ValueError when
    it lacks a positive width, height or fy.

    fov_y = 2 atan(H / (2 fy)).
    """
    if not intrinsics:
        return DEFAULT_FOV_Y, DEFAULT_ASPECT
    try:
        w, h, fy = (float(intrinsics[k]) for k in ("width", "height", "fy"))  # type: ignore[index]
    except (KeyError, TypeError, ValueError, IndexError):
        w = h = fy = float("nan")
    if not all(math.isfinite(x) and x > 0 for x in (w, h, fy)):
        raise ValueError(f"intrinsics {str(intrinsics)[:80]} (expected positive width, height and fy)")
    return 2.0 * math.atan(h / (2.0 * fy)), w / h


def frustum_scale(poses: np.ndarray) -> float:
    """Frustum size [m] for a trajectory: 4 % of the largest extent of the camera centres, within 5-30 cm."""
    pos = np.asarray(poses, dtype=np.float64)[valid_poses(np.asarray(poses)), :3, 3]
    extent = float(np.ptp(pos, axis=0).max()) if len(pos) else 0.0
    return float(np.clip(0.04 * extent, 0.05, 0.3))


def overview_camera(points: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A viewpoint that sees all (K, 3) `points` (NaN rows ignored): (position, look_at) [m], looking at their
    bounding-box centre from 0.9 x its diagonal (at least 1 m) away, 60 degrees above the horizontal of `up`."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if not len(p):
        p = np.zeros((1, 3))
    lo, hi = p.min(axis=0), p.max(axis=0)
    center, diagonal = (lo + hi) / 2.0, max(float(np.linalg.norm(hi - lo)), 1.0)
    return center + 0.9 * diagonal * view_direction(up, 60.0), center

