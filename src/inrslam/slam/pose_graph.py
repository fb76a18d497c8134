"""Pose-graph optimisation of keyframe poses (GTSAM, Levenberg-Marquardt): odometry edges between consecutive
keyframes and loop edges, each a relative-pose measurement with a Gaussian noise model (robust Huber kernel where
asked), the first pose fixed.

An edge (i, j, T_ij) measures T_ij = T_i^-1 T_j (camera j in camera i). Its error is Log(T_ij^-1 T_i^-1 T_j), a
6-vector (rotation first, radians; then translation, metres) weighted by 1 / sigma. Numpy in, numpy out; gtsam is
imported on first use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inrslam.errors import ConfigError


@dataclass(frozen=True)
class Edge:
    """A relative-pose measurement between poses i and j (indices into the optimised poses)."""

    i: int
    j: int
    T_ij: np.ndarray  # (4, 4) float64: pose j in the frame of pose i
    sigma_t: float  # metres
    sigma_r: float  # radians
    huber: float = 0.0  # Huber threshold in standard deviations (0 = plain least squares)


def _gtsam():
    try:
        import gtsam
    except ImportError:
        raise ConfigError("config key 'slam.loop_closure': true needs the gtsam package (pip install gtsam; an "
                          "inrslam install brings it)") from None
    return gtsam


def relative(Ti: np.ndarray, Tj: np.ndarray) -> np.ndarray:
    """(4, 4) T_i^-1 T_j."""
    return np.linalg.solve(Ti, Tj)


def odometry_edges(poses: np.ndarray, sigma_t: float, sigma_r: float) -> list[Edge]:
    """Edges (k, k+1) between consecutive poses (K, 4, 4), measured from the poses themselves."""
    return [Edge(k, k + 1, relative(poses[k], poses[k + 1]), sigma_t, sigma_r) for k in range(len(poses) - 1)]


def optimise(poses: np.ndarray, edges: list[Edge], fixed: int = 0, max_iterations: int = 100) -> np.ndarray:
    """Optimise (K, 4, 4) float64 c2w poses under `edges`, pose `fixed` held where it is; returns the new poses."""
    gtsam = _gtsam()
    poses = np.asarray(poses, dtype=np.float64)
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for k, T in enumerate(poses):
        initial.insert(k, gtsam.Pose3(_orthonormal(T)))
    graph.add(gtsam.PriorFactorPose3(fixed, gtsam.Pose3(_orthonormal(poses[fixed])),
                                     gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for e in edges:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([e.sigma_r] * 3 + [e.sigma_t] * 3))
        if e.huber > 0:
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(e.huber), noise)
        graph.add(gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(_orthonormal(e.T_ij)), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    return np.stack([result.atPose3(k).matrix() for k in range(len(poses))])


def _orthonormal(T: np.ndarray) -> np.ndarray:
    """T with its rotation projected onto SO(3) (float32 poses drift off it by ~1e-7; gtsam wants exact)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, T[:3, 3]
    return out
