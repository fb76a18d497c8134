"""The final pose graph of `slam.refine`: the optimum of two disagreeing edges is their weighted mean, exact links
pull a drifted trajectory back, and photometric links between views of a textured wall measure the true motion."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gtsam", reason="the pose graph needs gtsam (pip install gtsam)")

from test_photometric import C2W_A, INTR, motion, wall_view  # noqa: E402

from inrslam.data.frame import Frame  # noqa: E402
from inrslam.slam.config import PhotoConfig, RefineConfig, SlamConfig  # noqa: E402
from inrslam.slam.pose_graph import relative  # noqa: E402
from inrslam.slam.trajectory_graph import frame_pyramid, photometric_links, refine_trajectory  # noqa: E402


def translation(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


@pytest.mark.parametrize("odom_sigma, link_sigma", [(0.005, 0.005), (0.002, 0.004)])
def test_two_disagreeing_edges_meet_at_their_weighted_mean(odom_sigma, link_sigma):
    # the tracked poses put frame 1 10 cm from frame 0; a link measures 12 cm. Least squares with weights 1 / sigma^2
    # puts it at (0.10 / s_o^2 + 0.12 / s_l^2) / (1 / s_o^2 + 1 / s_l^2): 11 cm for equal sigmas, 10.4 cm for 2 / 4 mm
    cfg = RefineConfig(sigma_t=link_sigma, odom_sigma_t=odom_sigma, huber=0.0)
    poses = np.stack([np.eye(4), translation(0.10)])
    out = refine_trajectory(poses, [(0, 1, translation(0.12))], cfg)
    wo, wl = 1 / odom_sigma**2, 1 / link_sigma**2
    assert out[1, 0, 3] == pytest.approx((0.10 * wo + 0.12 * wl) / (wo + wl), abs=1e-7)
    assert np.allclose(out[0], np.eye(4), atol=1e-9)  # frame 0 stays where it was
    assert np.allclose(out[1, :3, :3], np.eye(3), atol=1e-9) and abs(out[1, 1, 3]) + abs(out[1, 2, 3]) < 1e-9
    assert np.array_equal(refine_trajectory(poses, [], cfg), poses)  # no links: unchanged


def test_exact_links_pull_a_drifted_trajectory_back():
    rng = np.random.default_rng(0)
    n = 40
    true = np.stack([motion([0.03 * k, 0.01 * np.sin(k / 5), 0.0, 0.0, 0.02 * k, 0.0]) for k in range(n)])
    drifted = [true[0]]
    for k in range(1, n):  # every tracked step off by ~1 mm and ~0.06 degrees: the error accumulates
        step = relative(true[k - 1], true[k]) @ motion(np.r_[rng.normal(0, 1e-3, 3), rng.normal(0, 1e-3, 3)])
        drifted.append(drifted[-1] @ step)
    drifted = np.stack(drifted)
    links = [(k - g, k, relative(true[k - g], true[k])) for g in (4, 8) for k in range(g, n)]
    out = refine_trajectory(drifted, links, RefineConfig())
    err_before = np.linalg.norm(drifted[:, :3, 3] - true[:, :3, 3], axis=1).max()
    err_after = np.linalg.norm(out[:, :3, 3] - true[:, :3, 3], axis=1).max()
    assert err_before > 0.005 and err_after < err_before / 3


def wall_frames(poses: np.ndarray) -> list[Frame]:
    frames = []
    for k, c2w in enumerate(poses):
        rgb, depth = wall_view(c2w)
        frames.append(Frame(index=k, timestamp=float(k), rgb=rgb.astype(np.float32), depth=depth.astype(np.float32),
                            intrinsics=INTR, c2w=c2w))
    return frames


def test_photometric_links_measure_the_true_motion_and_leave_out_what_moved_too_far():
    rng = np.random.default_rng(1)
    true = np.stack([C2W_A @ motion([0.004 * k, -0.003 * k, 0.01 * k, 0.002 * k, 0.0, -0.003 * k]) for k in range(7)])
    tracked = np.stack([T @ motion(np.r_[rng.normal(0, 2e-3, 3), rng.normal(0, 2e-3, 3)]) if k else T
                        for k, T in enumerate(true)])  # each pose off by ~2 mm and ~0.1 degrees
    frames = wall_frames(true)
    slam = SlamConfig(photo=PhotoConfig(levels=2, iters=30, tol=1e-10))
    links, dropped = photometric_links(lambda k: frame_pyramid(frames[k], slam), tracked, [2, 3], slam.photo, 0.03)
    assert dropped == 0 and sorted((i, j) for i, j, _ in links) == sorted(
        [(j - 2, j) for j in range(2, 7)] + [(j - 3, j) for j in range(3, 7)])
    for i, j, T in links:  # each link is near the true relative pose, not the tracked one it started from
        err = np.linalg.norm(T[:3, 3] - relative(true[i], true[j])[:3, 3])
        start_err = np.linalg.norm(relative(tracked[i], tracked[j])[:3, 3] - relative(true[i], true[j])[:3, 3])
        assert err < 5e-4 and err < start_err / 3  # sub-millimetre (a 160 x 120 image): 1.7-6.7 mm at the start
    none, dropped = photometric_links(lambda k: frame_pyramid(frames[k], slam), tracked, [2, 3], slam.photo, 1e-6)
    assert none == [] and dropped == 9  # every alignment moved its start by more than 1 micrometre
