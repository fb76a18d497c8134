"""Angles of rotations in numpy (no torch: the evaluation's trajectory maths imports this)."""

from __future__ import annotations

import numpy as np


def rotation_angle_deg_np(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation -> (...,) float64 angle in degrees, atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2): exact near
    0, where arccos of the trace reads a 1e-8 rad turn as 0 and a slightly non-orthonormal R as 0 or too large (the
    torch twin is `inrslam.geometry.se3.rotation_angle_deg`). Used by keyframe renewal, loop verification and
    evaluation."""
    R = np.asarray(R, dtype=np.float64)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = 0.5 * np.linalg.norm(w, axis=-1)
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arctan2(sin, cos))
