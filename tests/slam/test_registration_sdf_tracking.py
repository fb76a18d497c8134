"""The accurate preset's geometric pieces on analytic scenes: GICP recovers a known rigid motion and rejects a
single-plane view; the point-to-surface residual, its pose Jacobian and Gauss-Newton steps on a plane and a sphere."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.data.frame import Intrinsics
from inrslam.geometry.angles import rotation_angle_deg_np
from inrslam.geometry.se3 import se3_exp
from inrslam.slam.config import GicpConfig, SdfTrackConfig
from inrslam.slam.sdf_tracking import align_to_sdf, gauss_newton_step, sdf_residuals

small_gicp = pytest.importorskip("small_gicp", reason="the GICP initialiser needs small_gicp (pip install small_gicp)")
from inrslam.slam.registration import (  # noqa: E402
    depth_points,
    hessian_degeneracy,
    moved_beyond,
    pose_information,
    prepare_depth,
    register,
)

INTR = Intrinsics(fx=160.0, fy=160.0, cx=79.5, cy=59.5, width=160, height=120)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """c2w in OpenCV axes (z forward, y down) at `eye` looking at `target`."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def plane_depth(planes, c2w: np.ndarray, intr: Intrinsics = INTR) -> np.ndarray:
    """z-depth image of the nearest of the planes n.x = d (each (n, d)) seen from c2w; 0 where none is hit."""
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    dirs_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1)
    dirs = dirs_cam @ c2w[:3, :3].T
    o = c2w[:3, 3]
    depth = np.full(u.shape, np.inf)
    for n, d in planes:
        n = np.asarray(n, dtype=np.float64)
        den = dirs @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (d - o @ n) / den
        depth = np.where((t > 0.05) & (t < depth), t, depth)
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)


# a room corner with a step: floor z = 0, walls x = 2 and y = 2, a box face x = 1.4 (for rotation about z)
CORNER = [((0, 0, 1), 0.0), ((1, 0, 0), 2.0), ((0, 1, 0), 2.0), ((0, 0, 1), 0.4)]
WALL = [((1, 0, 0), 2.0)]


def relative_motion(rng) -> np.ndarray:
    xi = np.concatenate([rng.uniform(-0.03, 0.03, 3), rng.uniform(-0.02, 0.02, 3)])  # 3 cm, ~1 degree
    return se3_exp(torch.as_tensor(xi)).numpy()


def test_depth_points_back_project_a_fronto_parallel_plane():
    depth = np.full((INTR.height, INTR.width), 2.0, dtype=np.float32)
    depth[0, 0] = 0.0  # invalid
    depth[5, 7] = 9.0  # beyond max_depth
    pts = depth_points(depth, INTR, GicpConfig(pixel_stride=1, max_depth=6.0))
    assert pts.shape == (INTR.height * INTR.width - 2, 3)
    assert np.allclose(pts[:, 2], 2.0)
    assert np.allclose(pts[0], [(1 - INTR.cx) * 2 / INTR.fx, (0 - INTR.cy) * 2 / INTR.fy, 2.0])  # pixel (u=1, v=0)
    strided = depth_points(depth, INTR, GicpConfig(pixel_stride=2, max_depth=np.inf))
    assert np.allclose(strided[0], [(2 - INTR.cx) * 2 / INTR.fx, (0 - INTR.cy) * 2 / INTR.fy, 2.0])


def test_gicp_recovers_a_known_rigid_motion_between_two_synthetic_frames():
    rng = np.random.default_rng(0)
    cfg = GicpConfig(downsample=0.02, pixel_stride=1)
    c2w_a = look_at((0.3, 0.2, 1.2), (1.8, 1.7, 0.3))
    for _ in range(3):
        c2w_b = c2w_a @ relative_motion(rng)  # frame b in frame a's camera: T_ab
        a = prepare_depth(plane_depth(CORNER, c2w_a), INTR, cfg)
        b = prepare_depth(plane_depth(CORNER, c2w_b), INTR, cfg)
        reg = register(a, b, np.eye(4), cfg)
        true = np.linalg.inv(c2w_a) @ c2w_b
        assert reg.ok, reg.reason
        assert np.linalg.norm(reg.T_target_source[:3, 3] - true[:3, 3]) < 1e-3  # 1 mm of a 3-5 cm motion
        dR = reg.T_target_source[:3, :3].T @ true[:3, :3]
        assert rotation_angle_deg_np(dR) < 0.05
        assert reg.fitness > 0.9 and reg.degeneracy > cfg.degeneracy_ratio


def test_gicp_from_a_scaled_start_returns_a_rigid_pose_unless_told_not_to():
    """small_gicp keeps its start's scale / shear; a constant-velocity prediction of rounded poses has some, and
    frame after frame it compounds, so `rigid_init` projects the start onto SE(3) first."""
    c2w_a = look_at((0.3, 0.2, 1.2), (1.8, 1.7, 0.3))
    c2w_b = c2w_a @ relative_motion(np.random.default_rng(4))
    true = np.linalg.inv(c2w_a) @ c2w_b
    start = np.eye(4)
    start[:3, :3] *= 1.001  # a start 0.1 % off orthonormal
    for rigid in (True, False):
        cfg = GicpConfig(downsample=0.02, pixel_stride=1, rigid_init=rigid)
        a = prepare_depth(plane_depth(CORNER, c2w_a), INTR, cfg)
        b = prepare_depth(plane_depth(CORNER, c2w_b), INTR, cfg)
        reg = register(a, b, start, cfg)
        R = reg.T_target_source[:3, :3]
        off = np.abs(R @ R.T - np.eye(3)).max()
        if rigid:
            assert reg.ok and off < 1e-9
            assert np.linalg.norm(reg.T_target_source[:3, 3] - true[:3, 3]) < 1e-3
        else:
            assert off > 1e-3  # the start's 0.1 % scale, kept


def test_degeneracy_check_rejects_a_single_plane_view():
    cfg = GicpConfig(downsample=0.02, pixel_stride=1)
    c2w_a = look_at((0.0, 0.0, 1.2), (2.0, 0.1, 1.1))
    c2w_b = c2w_a @ relative_motion(np.random.default_rng(1))
    a = prepare_depth(plane_depth(WALL, c2w_a), INTR, cfg)
    b = prepare_depth(plane_depth(WALL, c2w_b), INTR, cfg)
    reg = register(a, b, np.eye(4), cfg)
    assert not reg.ok and reg.reason == "degenerate"
    assert reg.degeneracy < GicpConfig().degeneracy_ratio  # ~1e-3: the floor of GICP's covariance regularisation


def test_gicp_information_of_a_wall_lies_along_its_normal_in_the_source_camera():
    # GICP's information (rho, omega) of the pose of frame b (source) seen 30 degrees turned from frame a (target):
    # a wall fixes the translation along its normal and the rotations about in-plane axes; the normal must be b's
    # (a right increment T exp(delta): delta in the source camera), not a's (cos^2 30 = 0.75 of the trace there)
    cfg = GicpConfig(downsample=0.02, pixel_stride=1)
    c2w_a = look_at((0.0, 0.0, 1.2), (2.0, 0.1, 1.1))
    turn = np.eye(4)
    turn[:3, :3] = se3_exp(torch.tensor([0, 0, 0, 0, np.radians(30.0), 0], dtype=torch.float64)).numpy()[:3, :3]
    c2w_b = c2w_a @ turn
    a = prepare_depth(plane_depth(WALL, c2w_a), INTR, cfg)
    b = prepare_depth(plane_depth(WALL, c2w_b), INTR, cfg)
    info = register(a, b, np.linalg.inv(c2w_a) @ c2w_b, cfg).information
    n_b = c2w_b[:3, :3].T @ np.array([1.0, 0.0, 0.0])
    n_a = c2w_a[:3, :3].T @ np.array([1.0, 0.0, 0.0])
    tt, rr = info[:3, :3], info[3:, 3:]
    assert n_b @ tt @ n_b / np.trace(tt) > 0.99 and n_a @ tt @ n_a / np.trace(tt) < 0.8
    assert n_b @ rr @ n_b / np.trace(rr) < 0.01  # turning about the normal: unconstrained
    assert np.allclose(info, info.T) and np.linalg.eigvalsh(info).min() > -1e-6 * np.trace(info)


def test_pose_information_scales_the_hessian_by_the_residual_variance_and_reorders_it():
    H = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])  # small_gicp order (omega, rho)
    # error = sum r^T Omega r / 2 = 3 inliers x 3 axes x sigma^2 / 2 with sigma^2 = 0.5
    info = pose_information(H, error=3 * 3 * 0.5 / 2, inliers=3)
    assert np.allclose(np.diag(info), np.array([4.0, 5.0, 6.0, 1.0, 2.0, 3.0]) / 0.5)
    assert pose_information(H, 0.0, 3) is None and pose_information(H, 1.0, 0) is None


def test_keyframe_renewal_rule_on_analytic_motions():
    T = np.eye(4)
    T[:3, 3] = (0.06, 0.08, 0.0)  # 10 cm
    assert moved_beyond(T, 0.09, 10.0) and not moved_beyond(T, 0.11, 10.0)
    T = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, np.radians(12.0)], dtype=torch.float64)).numpy()
    assert moved_beyond(T, 0.1, 10.0) and not moved_beyond(T, 0.1, 13.0)


def test_hessian_degeneracy_of_analytic_blocks():
    H = np.zeros((6, 6))
    H[:3, :3] = np.eye(3)
    H[3:, 3:] = np.diag([0.0, 0.0, 1.0])  # plane: only the normal translation constrained
    assert hessian_degeneracy(H) == 0.0
    H[3:, 3:] = np.diag([1.0, 2.0, 4.0])
    assert np.isclose(hessian_degeneracy(H), 0.25)


def test_registration_without_points_says_so():
    cfg = GicpConfig()
    empty = prepare_depth(np.zeros((INTR.height, INTR.width), np.float32), INTR, cfg)
    full = prepare_depth(plane_depth(CORNER, look_at((0.3, 0.2, 1.2), (1.8, 1.7, 0.3))), INTR, cfg)
    reg = register(full, empty, np.eye(4), cfg)
    assert not reg.ok and reg.reason == "too_few_points" and np.array_equal(reg.T_target_source, np.eye(4))


# -- point-to-surface residual ------------------------------------------------------------------------------------
class AnalyticField(torch.nn.Module):
    """sdf(x) in truncation units of a plane z = h or a sphere |x - c| = R (metric SDF / T)."""

    def __init__(self, kind: str, truncation: float = 0.1, dtype=torch.float64):
        super().__init__()
        self.kind, self.T = kind, truncation
        self.c = torch.tensor([0.1, -0.2, 1.5], dtype=dtype)

    def sdf(self, x):
        if self.kind == "plane":
            return (x[:, 2] - 0.5) / self.T
        return ((x - self.c).norm(dim=1) - 0.6) / self.T


def sphere_points(n, rng, dtype=torch.float64):
    d = torch.as_tensor(rng.normal(size=(n, 3)), dtype=dtype)
    d = d / d.norm(dim=1, keepdim=True)
    return torch.tensor([0.1, -0.2, 1.5], dtype=dtype) + 0.6 * d


def test_sdf_residual_and_gradient_on_a_plane():
    field = AnalyticField("plane")
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 3] = torch.tensor([0.0, 0.0, 0.02])
    pts = torch.as_tensor(np.random.default_rng(2).uniform(-1, 1, (50, 3)), dtype=torch.float64)
    x, r, g = sdf_residuals(field, c2w, pts, field.T)
    assert torch.allclose(x, pts + c2w[:3, 3])
    assert torch.allclose(r, pts[:, 2] + 0.02 - 0.5)  # metric distance to z = 0.5
    assert torch.allclose(g, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(50, 3))


def test_gauss_newton_jacobian_equals_autograd_of_the_residual_under_a_left_twist():
    rng = np.random.default_rng(3)
    field = AnalyticField("sphere")
    c2w = torch.as_tensor(se3_exp(torch.as_tensor(rng.normal(size=6) * 0.1)), dtype=torch.float64)
    pts_cam = torch.as_tensor(rng.uniform(-1, 1, (20, 3)), dtype=torch.float64)
    x, r, g = sdf_residuals(field, c2w, pts_cam, field.T)
    J_analytic = torch.cat([g, torch.linalg.cross(x, g)], dim=1)

    def residual(xi):
        T = se3_exp(xi) @ c2w
        return field.sdf(pts_cam @ T[:3, :3].T + T[:3, 3]) * field.T

    J_auto = torch.autograd.functional.jacobian(residual, torch.zeros(6, dtype=torch.float64))
    assert torch.allclose(J_analytic, J_auto, atol=1e-10)


def test_gauss_newton_step_on_an_offset_plane_is_exact():
    rng = np.random.default_rng(4)
    x = torch.as_tensor(np.c_[rng.uniform(-1, 1, (100, 2)), np.full(100, 0.51)], dtype=torch.float64)
    r = x[:, 2] - 0.5
    g = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(100, 3)
    xi, w = gauss_newton_step(x, r, g, huber=0.05, damping=1e-9)
    assert torch.allclose(xi[2], torch.tensor(-0.01, dtype=torch.float64), atol=1e-8)
    assert torch.allclose(w, torch.ones(100, dtype=torch.float64))
    # the unconstrained in-plane directions stay put (damped), the constrained rotations are ~0
    assert float(xi[:2].abs().max()) < 1e-6 and float(xi[3:].abs().max()) < 1e-6


def test_huber_weights_down_weight_outliers():
    x = torch.zeros(3, 3, dtype=torch.float64)
    r = torch.tensor([0.001, 0.02, -0.1], dtype=torch.float64)
    g = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(3, 3)
    _, w = gauss_newton_step(x, r, g, huber=0.01, damping=1e-6)
    assert torch.allclose(w, torch.tensor([1.0, 0.5, 0.1], dtype=torch.float64))


def test_align_to_sdf_recovers_a_perturbed_pose_on_a_sphere():
    rng = np.random.default_rng(5)
    field = AnalyticField("sphere")
    c2w_true = torch.eye(4, dtype=torch.float64)
    c2w_true[:3, 3] = torch.tensor([0.05, 0.1, -0.3], dtype=torch.float64)
    world = sphere_points(2000, rng)
    pts_cam = (world - c2w_true[:3, 3]) @ c2w_true[:3, :3]  # inverse transform (R = I)
    start = torch.as_tensor(se3_exp(torch.tensor([0.02, -0.015, 0.01, 0, 0, 0], dtype=torch.float64)),
                            dtype=torch.float64) @ c2w_true
    cfg = SdfTrackConfig(iters=20, band=5.0, min_points=10, tol_trans=1e-9, tol_rot=1e-9, damping=1e-8)
    res = align_to_sdf(field, start, pts_cam, field.T, cfg)
    assert res.fallback is None and res.converged
    # a sphere fixes translation only (rotation about its centre is free): compare the world points
    moved = pts_cam @ res.c2w[:3, :3].T + res.c2w[:3, 3]
    assert float(((moved - field.c).norm(dim=1) - 0.6).abs().max()) < 1e-7  # every point back on the sphere
    centre_cam = lambda T: T[:3, :3].T @ (field.c - T[:3, 3])  # the sphere centre seen from the camera
    assert torch.allclose(centre_cam(res.c2w), centre_cam(c2w_true), atol=1e-7)


def test_align_to_sdf_keeps_the_pose_without_usable_points():
    field = AnalyticField("plane")
    pts = torch.zeros(5, 3, dtype=torch.float64)
    pts[:, 2] = 10.0  # far outside the band
    start = torch.eye(4, dtype=torch.float64)
    res = align_to_sdf(field, start, pts, field.T, SdfTrackConfig(iters=5))
    assert res.fallback == "sdf_few_points" and torch.equal(res.c2w, start)
