"""Geometric pose initialiser: GICP between the back-projected depth of two frames (small_gicp, CPU), with a
fitness and a degeneracy check so that a failed or ill-posed registration is never trusted.

Pure numpy in, numpy out (no file I/O). small_gicp is imported on first use; without it a clear error says how to
install it.

Degeneracy: GICP minimises sum_i r_i^T C_i^-1 r_i over a pose increment (omega, rho); its Gauss-Newton Hessian H (6x6,
rotation block first) says how well each direction is constrained. A view of a single plane leaves the two in-plane
translations and the rotation about the normal free: the translation block H_tt then has two eigenvalues ~0. We call a
registration degenerate when  lambda_min(H_tt) / lambda_max(H_tt) < degeneracy_ratio  (or the same on H_rr).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inrslam.errors import ConfigError
from inrslam.geometry.angles import rotation_angle_deg_np
from inrslam.geometry.depth_filter import bilateral_depth, estimate_depth_noise
from inrslam.geometry.pinhole import backproject_np
from inrslam.geometry.se3 import nearest_rigid_np
from inrslam.slam.config import GicpConfig


@dataclass
class Registration:
    """Result of `register`: the relative pose and why it may not be trusted."""

    T_target_source: np.ndarray  # (4, 4) float64: source camera -> target camera
    ok: bool  # passed every check
    reason: str | None  # "too_few_points" / "not_converged" / "low_fitness" / "degenerate" / "jump", or None
    fitness: float  # inlier fraction of the source points, [0, 1]
    degeneracy: float  # min over the rotation / translation blocks of lambda_min / lambda_max, [0, 1]
    iterations: int
    information: np.ndarray | None = None  # (6, 6) H / sigma^2 at the final pose, (rho, omega) (`pose_information`)


def _small_gicp():
    try:
        import small_gicp
    except ImportError:
        raise ConfigError("config key 'slam.init': 'gicp' needs the small_gicp package (pip install small_gicp; "
                          "an inrslam install brings it)") from None
    return small_gicp


def depth_points(depth: np.ndarray, intr, cfg: GicpConfig, noise: float | None = None) -> np.ndarray:
    """A frame's (H, W) depth in metres -> (N, 3) float64 camera-frame points of its valid pixels, every
    `cfg.pixel_stride`-th row and column, depth <= `cfg.max_depth` (`inrslam.geometry.pinhole.backproject_np`),
    after the bilateral filter of `filtered_depth` (`noise`: the depth's noise at 1 m if already known)."""
    depth = filtered_depth(depth, cfg, stride=cfg.pixel_stride, noise=noise)
    return backproject_np(depth, intr.fx, intr.fy, intr.cx, intr.cy, cfg.pixel_stride, cfg.max_depth)


def depth_noise(depth: np.ndarray, cfg: GicpConfig) -> float:
    """The depth noise std at 1 m (metres) the filter assumes: `cfg.depth_noise`, or estimated from `depth` if 0."""
    return cfg.depth_noise if cfg.depth_noise > 0 else estimate_depth_noise(depth)


def filtered_depth(depth: np.ndarray, cfg: GicpConfig, stride: int = 1, noise: float | None = None) -> np.ndarray:
    """`depth` after the bilateral filter of radius `cfg.depth_filter` (every `stride`-th pixel), when that is > 0 and
    the depth's noise (`noise`, else `depth_noise`) is at least `cfg.filter_min_noise`; else unchanged."""
    if cfg.depth_filter <= 0:
        return depth
    s = depth_noise(depth, cfg) if noise is None else noise
    if not s >= cfg.filter_min_noise:  # also nan: no three valid neighbours
        return depth
    return bilateral_depth(depth, cfg.depth_filter, s, stride=stride)


def moved_beyond(T: np.ndarray, dist: float, angle_deg: float) -> bool:
    """Whether a relative pose (4, 4) moves more than `dist` metres or rotates more than `angle_deg` degrees (the
    GICP keyframe renewal rule)."""
    return bool(np.linalg.norm(T[:3, 3]) > dist or float(rotation_angle_deg_np(T[:3, :3])) > angle_deg)


def hessian_degeneracy(H: np.ndarray) -> float:
    """min(lambda_min / lambda_max) over the rotation (H[:3,:3]) and translation (H[3:,3:]) blocks of a 6x6
    Gauss-Newton Hessian; 0 = some direction unconstrained, 1 = isotropic. Example: a plane's points give
    H_tt ~ n n^T, eigenvalues (0, 0, 1): 0."""
    H = np.asarray(H, dtype=np.float64)
    ratios = []
    for blk in (H[:3, :3], H[3:, 3:]):
        ev = np.linalg.eigvalsh(0.5 * (blk + blk.T))
        ratios.append(max(ev[0], 0.0) / ev[-1] if ev[-1] > 0 else 0.0)
    return float(min(ratios))


class PreparedCloud:
    """A downsampled point cloud with covariances and its KD-tree, ready to be a GICP target or source."""

    def __init__(self, points: np.ndarray, cfg: GicpConfig):
        sg = _small_gicp()
        if points.shape[0] < cfg.neighbors + 1:
            self.cloud, self.tree, self.size = None, None, 0
            return
        self.cloud, self.tree = sg.preprocess_points(np.ascontiguousarray(points, dtype=np.float64),
                                                     downsampling_resolution=cfg.downsample,
                                                     num_neighbors=cfg.neighbors, num_threads=cfg.threads)
        self.size = int(self.cloud.size())


def min_points(cfg: GicpConfig) -> int:
    """Fewest points (after downsampling) a cloud needs to be registered or registered onto."""
    return max(50, 3 * cfg.neighbors)


def prepare_depth(depth: np.ndarray, intr, cfg: GicpConfig) -> PreparedCloud:
    """A frame's depth image -> its prepared camera-frame cloud."""
    return PreparedCloud(depth_points(depth, intr, cfg), cfg)


def register(target: PreparedCloud, source: PreparedCloud, init_T: np.ndarray, cfg: GicpConfig) -> Registration:
    """GICP of `source` onto `target` from `init_T` (source -> target, (4, 4)); checks fitness, degeneracy and the
    size of the correction. A failed check still returns GICP's pose, with ok False and the reason. With
    `cfg.rigid_init` the start is projected onto SE(3) first (small_gicp's result keeps its start's scale / shear)."""
    init_T = nearest_rigid_np(init_T) if cfg.rigid_init else np.asarray(init_T, dtype=np.float64)
    min_pts = min_points(cfg)
    if target.size < min_pts or source.size < min_pts:
        return Registration(init_T.copy(), False, "too_few_points", 0.0, 0.0, 0)
    sg = _small_gicp()
    res = sg.align(target.cloud, source.cloud, target.tree, init_T_target_source=init_T, registration_type="GICP",
                   max_correspondence_distance=cfg.max_corr, num_threads=cfg.threads,
                   max_iterations=cfg.max_iterations, rotation_epsilon=cfg.eps_rot,
                   translation_epsilon=cfg.eps_trans)
    T = np.asarray(res.T_target_source, dtype=np.float64)
    fitness = float(res.num_inliers) / max(source.size, 1)
    degeneracy = hessian_degeneracy(np.asarray(res.H))
    reason = None
    if not np.isfinite(T).all():
        reason = "not_converged"
    elif fitness < cfg.min_fitness:
        reason = "low_fitness"
    elif degeneracy < cfg.degeneracy_ratio:
        reason = "degenerate"
    elif np.linalg.norm(T[:3, 3] - init_T[:3, 3]) > cfg.max_step:
        reason = "jump"
    return Registration(T, reason is None, reason, fitness, degeneracy, int(res.iterations),
                        pose_information(np.asarray(res.H), float(res.error), int(res.num_inliers)))


def pose_information(H: np.ndarray, error: float, inliers: int) -> np.ndarray | None:
    """GICP's information matrix of its pose: H / sigma^2, sigma^2 = 2 error / (3 inliers) the residuals' variance
    per axis (error = sum_i r_i^T Omega_i r_i / 2 at the solution, H = sum_i J_i^T Omega_i J_i). small_gicp's H is
    w.r.t. a right increment T exp(delta), delta = (omega, rho); returned re-ordered to (rho, omega). For the
    relative pose T^-1 A of another frame A (a left increment exp(-delta) T^-1 A), the same matrix holds.
    None when there is no residual to scale by."""
    if inliers < 1 or not np.isfinite(error) or error <= 0 or not np.isfinite(H).all():
        return None
    order = [3, 4, 5, 0, 1, 2]
    return np.asarray(H, dtype=np.float64)[np.ix_(order, order)] * (1.5 * inliers / error)
