"""Photometric refinement on analytic scenes: a textured wall seen from two poses. The residual vanishes at the true
pose, its Jacobian equals the residual's central differences under a left twist, and Gauss-Newton recovers a known
motion, including the sliding along the wall that leaves depth-only registration degenerate."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.data.frame import Intrinsics
from inrslam.geometry.angles import rotation_angle_deg_np
from inrslam.geometry.se3 import se3_exp
from inrslam.slam.config import PhotoConfig
from inrslam.slam.photometric import (
    align_photometric,
    build_pyramid,
    depth_residuals,
    depth_stack,
    huber_weights,
    jump_kept,
    photometric_residuals,
    reference_points,
    step_bound,
    twist_small,
)

INTR = Intrinsics(fx=200.0, fy=200.0, cx=79.5, cy=59.5, width=160, height=120)
K = (INTR.fx, INTR.fy, INTR.cx, INTR.cy)


def texture(p: np.ndarray) -> np.ndarray:
    """Smooth grey texture in [0, 1] of world points (N, 3) on the wall x = 2 (varies along y and z)."""
    y, z = p[..., 1], p[..., 2]
    return 0.5 + 0.2 * np.sin(9.0 * y) * np.cos(7.0 * z) + 0.15 * np.sin(4.0 * y + 5.0 * z)


def wall_view(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colour (H, W, 3) and z-depth (H, W) of the textured wall x = 2 seen from c2w (OpenCV axes)."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width].astype(np.float64)
    d_cam = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], -1)
    d = d_cam @ c2w[:3, :3].T
    t = (2.0 - c2w[0, 3]) / d[..., 0]  # ray parameter = z-depth (d_cam has z = 1)
    p = c2w[:3, 3] + t[..., None] * d
    g = texture(p)
    return np.repeat(g[..., None], 3, axis=-1), t


# camera at the origin facing +x (the wall), OpenCV axes: z forward = +x, x right = -y, y down = -z
C2W_A = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def motion(xi) -> np.ndarray:
    return se3_exp(torch.tensor(xi, dtype=torch.float64)).numpy()


def pyramids(c2w_b: np.ndarray, levels: int = 3):
    rgb_a, depth_a = wall_view(C2W_A)
    rgb_b, depth_b = wall_view(c2w_b)
    return build_pyramid(rgb_a, depth_a, K, levels), build_pyramid(rgb_b, depth_b, K, levels)


def test_pyramid_levels_halve_the_image_and_the_intrinsics():
    ref, _ = pyramids(C2W_A)
    assert [tuple(lv.gray.shape) for lv in ref] == [(120, 160), (60, 80), (30, 40)]
    fx, fy, cx, cy = ref[1].K
    assert (fx, fy) == (100.0, 100.0) and (cx, cy) == (39.5, 29.5)  # pixel centres stay centres
    assert torch.all(ref[1].depth > 0)  # the wall fills the view: every 2x2 block has four valid depths
    assert torch.allclose(ref[1].gray, 0.25 * (ref[0].gray[0::2, 0::2] + ref[0].gray[1::2, 0::2]
                                               + ref[0].gray[0::2, 1::2] + ref[0].gray[1::2, 1::2]))


def test_residuals_vanish_at_the_true_pose_and_jacobian_equals_finite_differences():
    c2w_b = C2W_A @ motion([0.02, -0.01, 0.03, 0.01, -0.02, 0.015])
    ref, cur = pyramids(c2w_b, levels=1)
    X, I = reference_points(ref[0], 0.005, 4000, torch.Generator().manual_seed(0))
    T_true = torch.as_tensor(np.linalg.inv(c2w_b) @ C2W_A)
    r, J, valid = photometric_residuals(cur[0], X, I, T_true, border=2)
    assert valid.float().mean() > 0.8
    assert r[valid].abs().median() < 2e-3  # bilinear interpolation of a smooth texture
    # J is the derivative of the residual under T <- exp(xi) T at xi = 0 (at a perturbed pose: non-zero residuals)
    T0 = se3_exp(torch.tensor([0.01, 0.0, -0.01, 0.0, 0.01, 0.0], dtype=torch.float64)) @ T_true
    _, J0, valid0 = photometric_residuals(cur[0], X, I, T0, border=2)

    def res(xi):
        return photometric_residuals(cur[0], X, I, se3_exp(xi) @ T0, border=2)[0]

    # central differences of the residual itself (6 directions; the reference for the analytic Jacobian)
    eps = 1e-6
    J_num = torch.stack([(res(eps * e) - res(-eps * e)) / (2 * eps) for e in torch.eye(6, dtype=torch.float64)], 1)
    # ours samples the central-difference image gradient, the residual is the bilinear interpolant: they agree up
    # to the texture's curvature over a pixel
    rel = (J_num[valid0] - J0[valid0]).norm() / J0[valid0].norm()
    assert rel < 0.05


@pytest.mark.parametrize("xi", [[0.03, 0.02, -0.02, 0.0, 0.0, 0.0],  # sliding along the wall + approach
                                [0.01, -0.03, 0.01, 0.02, -0.01, 0.01]])  # ~1.4 degrees and 3 cm
def test_gauss_newton_recovers_a_known_motion_on_a_textured_wall(xi):
    c2w_b = C2W_A @ motion(xi)
    ref, cur = pyramids(c2w_b)
    cfg = PhotoConfig(enabled=True, grad_threshold=0.002, iters=20)
    res = align_photometric(ref, cur, torch.eye(4, dtype=torch.float64), cfg, torch.Generator().manual_seed(0))
    assert res.fallback is None
    est_c2w_b = C2W_A @ np.linalg.inv(res.T_ik.numpy())
    assert np.linalg.norm(est_c2w_b[:3, 3] - c2w_b[:3, 3]) < 1e-3  # 1 mm of a 3-4 cm motion
    dR = est_c2w_b[:3, :3].T @ c2w_b[:3, :3]
    assert rotation_angle_deg_np(dR) < 0.05


def test_an_untextured_view_keeps_the_pose_and_says_so():
    rgb, depth = wall_view(C2W_A)
    flat = build_pyramid(np.full_like(rgb, 0.5), depth, K, 2)
    start = torch.as_tensor(motion([0.01, 0.0, 0.0, 0.0, 0.0, 0.0]))
    res = align_photometric(flat, flat, start, PhotoConfig(enabled=True), torch.Generator().manual_seed(0))
    assert res.fallback == "photo_few_points" and torch.equal(res.T_ik, start)


def test_step_bound_follows_the_recent_moves_above_its_floor():
    cfg = PhotoConfig(max_step=0.01, jump_factor=4.0, weak_max_step=0.05)
    assert step_bound([], False, cfg) == 0.01  # nothing accepted yet: the floor
    assert step_bound([0.001, 0.002, 0.0015], False, cfg) == 0.01  # synthetic depth: mm moves, the floor holds
    assert step_bound([0.004, 0.005, 0.006], False, cfg) == pytest.approx(0.02)  # real sensors: 4 x the median
    assert step_bound([0.004, 0.005, 0.006], True, cfg) == 0.05  # a weak geometric pose


def test_a_move_beyond_the_bound_stands_only_when_the_image_is_explained_as_usual():
    off = PhotoConfig()  # jump_rms_factor 0: never
    assert not jump_kept(0.01, 0.02, off)
    cfg = PhotoConfig(jump_rms_factor=1.5)
    assert jump_kept(0.02, 0.02, cfg) and jump_kept(0.03, 0.02, cfg)  # up to 1.5 x the keyframe's first RMS
    assert not jump_kept(0.0301, 0.02, cfg)  # the residual grew: the refinement is the suspect
    assert not jump_kept(0.01, 0.0, cfg)  # no refinement onto this keyframe yet: no level to compare with
    assert not jump_kept(float("nan"), 0.02, cfg)


def test_a_view_without_gradient_where_the_points_land_is_a_fallback_not_a_crash():
    rgb, depth = wall_view(C2W_A)
    ref = build_pyramid(rgb, depth, K, 1)
    flat = build_pyramid(np.full_like(rgb, 0.5), depth, K, 1)  # the current image: no gradient anywhere
    start = torch.eye(4, dtype=torch.float64)
    res = align_photometric(ref, flat, start, PhotoConfig(enabled=True, grad_threshold=0.002),
                            torch.Generator().manual_seed(0))
    assert res.fallback == "photo_nan" and torch.equal(res.T_ik, start)


def test_twist_small_inverts_se3_exp_to_first_order():
    g = torch.Generator().manual_seed(3)
    for scale in (1e-3, 1e-2):
        xi = (torch.rand(6, generator=g, dtype=torch.float64) - 0.5) * 2 * scale
        err = (twist_small(se3_exp(xi)) - xi).norm()
        assert err < 2 * float(xi.norm()) ** 2  # O(|xi|^2)
    assert torch.equal(twist_small(torch.eye(4, dtype=torch.float64)), torch.zeros(6, dtype=torch.float64))


def test_a_prior_pins_the_directions_it_informs_and_leaves_the_others_to_the_image():
    xi_true = [0.03, 0.02, -0.02, 0.0, 0.0, 0.0]
    c2w_b = C2W_A @ motion(xi_true)
    ref, cur = pyramids(c2w_b)
    cfg = PhotoConfig(enabled=True, grad_threshold=0.002, iters=20)
    T_true = torch.as_tensor(np.linalg.inv(c2w_b) @ C2W_A)
    # the prior's pose is off by 1 cm sideways (x) and 5 mm forward (z) in the current camera ...
    T_p = se3_exp(torch.tensor([0.01, 0.0, 0.005, 0.0, 0.0, 0.0], dtype=torch.float64)) @ T_true
    # ... and informs only the forward translation (as GICP on a wall: depth fixes the distance, not the sliding)
    info = torch.zeros(6, 6, dtype=torch.float64)
    info[2, 2] = 1e14
    start = torch.eye(4, dtype=torch.float64)
    res = align_photometric(ref, cur, start, cfg, torch.Generator().manual_seed(0), (T_p, info, 1.0))
    assert res.fallback is None
    d_true = twist_small(res.T_ik @ torch.linalg.inv(T_true))
    d_prior = twist_small(res.T_ik @ torch.linalg.inv(T_p))
    assert abs(float(d_prior[2])) < 2e-4  # forward: the prior's
    # sideways: the image's, near the truth (1 mm, the image's best fit with the distance held 5 mm off) and not
    # the prior's 1 cm
    assert abs(float(d_true[0])) < 2e-3 and abs(float(d_true[1])) < 2e-3 and abs(float(d_prior[0])) > 8e-3
    # weight 0 = no prior, exactly
    plain = align_photometric(ref, cur, start, cfg, torch.Generator().manual_seed(0))
    zero = align_photometric(ref, cur, start, cfg, torch.Generator().manual_seed(0), (T_p, info, 0.0))
    assert torch.equal(plain.T_ik, zero.T_ik)


def test_affine_light_absorbs_an_exposure_change_that_biases_the_plain_alignment():
    xi_true = [0.01, -0.03, 0.01, 0.02, -0.01, 0.01]
    c2w_b = C2W_A @ motion(xi_true)
    rgb_a, depth_a = wall_view(C2W_A)
    rgb_b, depth_b = wall_view(c2w_b)
    dark = 0.7 * rgb_b + 0.08  # the current frame exposed darker
    ref, cur = build_pyramid(rgb_a, depth_a, K, 3), build_pyramid(dark, depth_b, K, 3)
    start = torch.eye(4, dtype=torch.float64)

    def error_mm(cfg):
        res = align_photometric(ref, cur, start, cfg, torch.Generator().manual_seed(0))
        est = C2W_A @ np.linalg.inv(res.T_ik.numpy())
        return 1e3 * np.linalg.norm(est[:3, 3] - c2w_b[:3, 3]), res

    plain, _ = error_mm(PhotoConfig(enabled=True, grad_threshold=0.002, iters=20, huber=1.0))
    fitted, res = error_mm(PhotoConfig(enabled=True, grad_threshold=0.002, iters=20, huber=1.0, affine_light=True))
    assert fitted < 1.0 < plain  # 1 mm of a 3.7 cm motion; without the brightness model it is off
    assert res.light == pytest.approx((-0.3, 0.08), abs=5e-3)


def test_older_references_join_the_same_steps_and_pull_the_pose_towards_what_they_see():
    c2w_b = C2W_A @ motion([0.01, -0.03, 0.01, 0.02, -0.01, 0.01])  # the current frame
    c2w_c = C2W_A @ motion([-0.02, 0.01, 0.02, -0.01, 0.02, 0.0])  # an older keyframe elsewhere on the wall
    ref, cur = pyramids(c2w_b)
    older = build_pyramid(*wall_view(c2w_c), K, 3)
    cfg = PhotoConfig(enabled=True, grad_threshold=0.002, iters=20)
    # the newest keyframe's pose estimate is 6 mm off (a chain's error); the older one's is right
    c2w_a_est = C2W_A @ motion([0.006, 0.0, 0.0, 0.0, 0.0, 0.0])
    start = torch.eye(4, dtype=torch.float64)  # current frame believed at the newest keyframe's pose
    T_ic = torch.as_tensor(np.linalg.inv(c2w_a_est) @ c2w_c)
    gen = torch.Generator

    def error_mm(res):  # the current frame's world position, placed by the newest keyframe's estimated pose
        est = c2w_a_est @ np.linalg.inv(res.T_ik.numpy())
        return 1e3 * np.linalg.norm(est[:3, 3] - c2w_b[:3, 3])

    alone = align_photometric(ref, cur, start, cfg, gen().manual_seed(0))
    joint = align_photometric(ref, cur, start, cfg, gen().manual_seed(0), others=[(older, T_ic)])
    assert alone.fallback is None and joint.fallback is None
    assert error_mm(alone) == pytest.approx(6.0, abs=0.5)  # alone it inherits the keyframe's error
    assert 1.0 < error_mm(joint) < 0.75 * error_mm(alone)  # the two keyframes' residuals meet between them
    # with no older reference the alignment is the single one, to the bit (the same random draws)
    none = align_photometric(ref, cur, start, cfg, gen().manual_seed(0), others=[])
    assert torch.equal(none.T_ik, alone.T_ik) and none.rms == alone.rms


def test_with_an_older_reference_only_the_newest_sets_the_reported_rms_and_points():
    c2w_b = C2W_A @ motion([0.02, 0.0, 0.01, 0.0, 0.01, 0.0])
    ref, cur = pyramids(c2w_b)
    flat = build_pyramid(np.full((INTR.height, INTR.width, 3), 0.5), wall_view(C2W_A)[1], K, 3)
    cfg = PhotoConfig(enabled=True, grad_threshold=0.002, iters=20)
    start = torch.eye(4, dtype=torch.float64)
    alone = align_photometric(ref, cur, start, cfg, torch.Generator().manual_seed(0))
    # an untextured older reference adds no residual (no gradient): the same alignment, the same report
    joint = align_photometric(ref, cur, start, cfg, torch.Generator().manual_seed(0), others=[(flat, start)])
    assert joint.n_points == alone.n_points and joint.rms == pytest.approx(alone.rms)
    assert torch.allclose(joint.T_ik, alone.T_ik, atol=1e-9)


def test_huber_weights_are_one_inside_the_threshold_and_threshold_over_residual_beyond():
    r = torch.tensor([0.0, 0.03, -0.05, 0.1, -0.2, 0.4], dtype=torch.float64)
    valid = torch.tensor([True, True, True, True, True, False])
    w = huber_weights(r, valid, 0.05)
    assert torch.allclose(w, torch.tensor([1.0, 1.0, 1.0, 0.5, 0.25, 0.0], dtype=torch.float64))
    # w r is the Huber loss's derivative: huber sign(r) beyond the threshold
    assert torch.allclose((w * r)[3:5], torch.tensor([0.05, -0.05], dtype=torch.float64))


def test_depth_residual_of_a_point_in_front_of_a_wall_and_its_jacobian():
    """Analytic: the wall x = 2 faces camera A (z-depth 2 m everywhere); a point at (0.1, 0, 1.99) in A's frame has
    r = 2 - 1.99 = +1 cm, dr/drho = (0, 0, -1) (moving it along z changes its own depth only), dr/domega =
    X x (0, 0, -1) = (0, 0.1, 0): a turn about y moves it along z by -0.1 omega."""
    _, cur = pyramids(C2W_A, levels=1)
    X = torch.tensor([[0.1, 0.0, 1.99]], dtype=torch.float64)
    r, J, valid = depth_residuals(cur[0], X, torch.eye(4, dtype=torch.float64))
    assert bool(valid[0])
    assert float(r[0]) == pytest.approx(0.01, abs=1e-12)
    assert torch.allclose(J[0], torch.tensor([0.0, 0.0, -1.0, 0.0, 0.1, 0.0], dtype=torch.float64), atol=1e-12)


def test_depth_residual_jacobian_equals_autograd_on_a_tilted_plane():
    """On a plane the depth is affine in the pixel, so the sampled central-difference gradient is the bilinear
    interpolant's own: J equals autograd's derivative under a left twist, at fresh random poses and points."""
    g = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    depth = 2.0 + 0.004 * (u - 80) - 0.003 * (v - 60)
    cur = build_pyramid(np.full((120, 160, 3), 0.5), depth, K, 1)[0]
    vv, uu = torch.randint(10, 110, (300,), generator=g), torch.randint(10, 150, (300,), generator=g)
    z = torch.as_tensor(depth)[vv, uu] + 0.02 * torch.randn(300, generator=g, dtype=torch.float64)
    X = torch.stack([(uu - K[2]) / K[0] * z, (vv - K[3]) / K[1] * z, z], -1)
    T = se3_exp(0.02 * torch.randn(6, generator=g, dtype=torch.float64))
    r, J, valid = depth_residuals(cur, X, T)
    assert valid.float().mean() > 0.9
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    r_xi = depth_residuals(cur, X, se3_exp(xi) @ T)[0]
    J_auto = torch.stack([torch.autograd.grad(r_xi[k], xi, retain_graph=True)[0] for k in range(300)])
    assert torch.allclose(r_xi.detach(), r)
    assert torch.allclose(J[valid], J_auto[valid], atol=1e-9)


def test_depth_stack_marks_holes_edges_and_the_border_invalid():
    d = torch.full((8, 10), 2.0, dtype=torch.float64)
    d[4, 4] = 0.0  # a hole
    d[:, 8:] = 3.0  # a 1 m step: an edge between columns 7 and 8
    s = depth_stack(d)
    ok = s[3].bool()
    assert not ok[0].any() and not ok[:, 0].any() and not ok[-1].any() and not ok[:, -1].any()
    assert not ok[4, 4] and not ok[3, 4] and not ok[4, 5]  # the hole and its neighbours
    assert not ok[2, 7] and not ok[2, 8]  # both sides of the edge
    assert ok[2, 2] and ok[6, 6]
    assert float(s[1, 2, 2]) == 0.0 and float(s[0, 2, 2]) == 2.0  # flat: no gradient; the depth kept
    assert torch.all(s[:3][:, ~ok] == 0)


def test_the_depth_residual_corrects_colour_taken_from_a_shifted_camera():
    """Real sensors' colour and depth cameras are not registered: here the current frame's colour is seen from 1 cm
    nearer the wall than its depth. Intensities alone place the frame at the colour's pose (about 1 cm off along
    the view, which the image constrains only by its scale change); with the depth residual, which constrains it
    directly, the pose follows the depth."""
    xi_true = [0.01, -0.02, 0.01, 0.01, -0.01, 0.005]
    c2w_b = C2W_A @ motion(xi_true)
    rgb_a, depth_a = wall_view(C2W_A)
    _, depth_b = wall_view(c2w_b)
    rgb_b, _ = wall_view(c2w_b @ motion([0.0, 0.0, 0.01, 0.0, 0.0, 0.0]))  # colour 1 cm nearer the wall
    ref, cur = build_pyramid(rgb_a, depth_a, K, 3), build_pyramid(rgb_b, depth_b, K, 3)

    def error_mm(depth_weight):
        cfg = PhotoConfig(enabled=True, grad_threshold=0.002, iters=20, depth_weight=depth_weight)
        res = align_photometric(ref, cur, torch.eye(4, dtype=torch.float64), cfg, torch.Generator().manual_seed(0))
        assert res.fallback is None
        est = C2W_A @ np.linalg.inv(res.T_ik.numpy())
        return 1e3 * np.linalg.norm(est[:3, 3] - c2w_b[:3, 3])

    plain, weighted = error_mm(0.0), error_mm(1.0)
    assert plain > 7.0  # the colour's 1 cm
    assert weighted < 1.0
