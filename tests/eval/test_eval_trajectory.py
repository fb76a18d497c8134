"""ATE / RPE / alignment / association against known answers and against evo (test-only cross-check)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from inrslam.eval.trajectory import align_umeyama, associate, associate_indices, ate, rpe, select_frames


def random_trajectory(n: int, seed: int) -> np.ndarray:
    """(n, 4, 4) smooth-ish random camera-to-world trajectory (random walk in position and rotation)."""
    rng = np.random.default_rng(seed)
    pos = np.cumsum(rng.normal(0, 0.05, (n, 3)), 0)
    rv = np.cumsum(rng.normal(0, 0.05, (n, 3)), 0)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rv).as_matrix()
    T[:, :3, 3] = pos
    return T


def se3(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def test_umeyama_recovers_known_transform_and_scale():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    R_true = Rotation.from_rotvec([0.3, -0.8, 1.2]).as_matrix()
    t_true = np.array([1.0, -2.0, 0.5])
    dst = 1.7 * src @ R_true.T + t_true
    R, t, s = align_umeyama(src, dst, with_scale=True)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-12)
    assert s == pytest.approx(1.7, abs=1e-12)
    R, t, s = align_umeyama(src, dst, with_scale=False)
    assert s == 1.0
    np.testing.assert_allclose(R, R_true, atol=1e-12)  # rotation is scale-independent


def test_umeyama_is_reflection_corrected():
    """A mirrored point set would be fitted best by a reflection; we must still return a proper rotation."""
    rng = np.random.default_rng(2)
    src = rng.normal(size=(30, 3))
    dst = src * np.array([1.0, 1.0, -1.0])
    R, _, _ = align_umeyama(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def _noisy_transformed(n=300, sigma=0.01, seed=3):
    gt = random_trajectory(n, seed)
    rng = np.random.default_rng(seed + 100)
    A = se3([0.2, -0.4, 0.9], [3.0, -1.0, 2.0])  # est lives in a different world frame
    est = np.linalg.inv(A) @ gt
    noise = rng.normal(0, sigma, (n, 3))
    est[:, :3, 3] += noise
    return est, gt, A, noise


def test_ate_se3_known_transform_plus_noise():
    est, gt, A, noise = _noisy_transformed()
    out = ate(est, gt, align="se3")
    # error under the *true* transform: |R_A noise_i| = |noise_i|
    true_rmse = np.sqrt(np.mean(np.sum(noise**2, 1)))
    # the least-squares alignment can only do better, and with 300 frames only 6 dof of noise are absorbed
    assert out["rmse"] <= true_rmse + 1e-12
    assert out["rmse"] == pytest.approx(true_rmse, rel=0.03)
    np.testing.assert_allclose(out["alignment"]["R"], A[:3, :3], atol=5e-3)
    np.testing.assert_allclose(out["alignment"]["t"], A[:3, 3], atol=5e-3)
    assert out["n_used"] == 300 and out["n_excluded"] == 0
    assert out["errors"].shape == (300,)
    assert out["rmse"] == pytest.approx(np.sqrt(np.mean(out["errors"] ** 2)))
    assert out["min"] <= out["median"] <= out["max"] and out["mean"] <= out["rmse"]


def test_ate_noise_free_is_zero_and_none_alignment_is_not():
    gt = random_trajectory(100, 4)
    est = np.linalg.inv(se3([0, 0, 0.5], [1, 2, 3])) @ gt
    assert ate(est, gt, "se3")["rmse"] < 1e-10
    assert ate(est, gt, "none")["rmse"] > 0.5


def test_ate_matches_evo():
    evo_traj = pytest.importorskip("evo.core.trajectory", reason="evo (GPL, test-only) cross-check not installed")
    from evo.core import metrics as evo_metrics

    est, gt, _, _ = _noisy_transformed(n=200, sigma=0.02, seed=7)
    ref = evo_traj.PosePath3D(poses_se3=list(gt))
    e = evo_traj.PosePath3D(poses_se3=list(est))
    e.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    ours = ate(est, gt, align="se3")
    for k in ("rmse", "mean", "median", "std", "min", "max"):
        assert ours[k] == pytest.approx(ape.get_statistic(getattr(evo_metrics.StatisticsType, k)), abs=1e-6), k
    np.testing.assert_allclose(ours["errors"], ape.error, atol=1e-6)


def test_rpe_matches_evo():
    evo_traj = pytest.importorskip("evo.core.trajectory", reason="evo (GPL, test-only) cross-check not installed")
    from evo.core import metrics as evo_metrics

    est, gt, _, _ = _noisy_transformed(n=120, sigma=0.02, seed=8)
    ours = rpe(est, gt, delta=3)
    ref, e = evo_traj.PosePath3D(poses_se3=list(gt)), evo_traj.PosePath3D(poses_se3=list(est))
    for rel, key in ((evo_metrics.PoseRelation.translation_part, "trans_rmse"),
                     (evo_metrics.PoseRelation.rotation_angle_deg, "rot_rmse")):
        # ours uses every pair (i, i + delta), like the TUM tool: evo's all_pairs=True (its default strides by delta)
        m = evo_metrics.RPE(rel, delta=3, delta_unit=evo_metrics.Unit.frames, all_pairs=True)
        m.process_data((ref, e))
        assert ours[key] == pytest.approx(m.get_statistic(evo_metrics.StatisticsType.rmse), abs=1e-6), key
        m1 = evo_metrics.RPE(rel, delta=1, delta_unit=evo_metrics.Unit.frames)  # delta 1: both conventions agree
        m1.process_data((ref, e))
        assert rpe(est, gt, delta=1)[key] == pytest.approx(m1.get_statistic(evo_metrics.StatisticsType.rmse), abs=1e-6)


def test_ate_sim3_recovers_scale():
    gt = random_trajectory(150, 5)
    A = se3([0.1, 0.2, -0.3], [0.5, 0.0, -1.0])
    est = np.linalg.inv(A) @ gt
    est[:, :3, 3] *= 0.4  # monocular-style scale drift: est = gt scaled by 0.4 (in est's frame)
    out = ate(est, gt, align="sim3")
    assert out["alignment"]["s"] == pytest.approx(2.5, rel=1e-9)
    assert out["rmse"] < 1e-9
    assert ate(est, gt, align="se3")["rmse"] > 0.01  # without scale it cannot fit


def test_ate_excludes_and_counts_nonfinite_gt():
    est, gt, _, _ = _noisy_transformed(n=80, seed=9)
    bad = [0, 5, 6, 40, 79]
    gt_bad = gt.copy()
    gt_bad[bad[:3]] = np.nan
    gt_bad[bad[3:], 0, 3] = np.inf
    out = ate(est, gt_bad)
    keep = np.setdiff1d(np.arange(80), bad)
    assert out["n_excluded"] == 5 and out["n_used"] == 75
    assert not out["used"][bad].any() and out["used"][keep].all()
    ref = ate(est[keep], gt[keep])
    assert out["rmse"] == pytest.approx(ref["rmse"], abs=1e-12)
    assert np.isfinite(out["errors"]).all()


def test_ate_all_excluded_gives_nan_not_crash():
    est = random_trajectory(5, 0)
    out = ate(est, np.full_like(est, np.nan))
    assert out["n_used"] == 0 and out["n_excluded"] == 5 and np.isnan(out["rmse"])


def test_rpe_hand_made():
    """GT: 1 m steps along x. Estimate: step 1->2 is 1.1 m, and frame 3 is yawed by 10 deg.

    Pair (0,1): no error. Pair (1,2): 0.1 m translation error. Pair (2,3): E = inv(trans(1,0,0)) [Rz10, (1,0,0)]
    = [Rz10, 0] -> 0 m, 10 deg. Translation RMSE = sqrt(0.01/3), rotation RMSE = 10/sqrt(3) deg.
    """
    gt = np.tile(np.eye(4), (4, 1, 1))
    gt[:, 0, 3] = [0, 1, 2, 3]
    est = gt.copy()
    est[2:, 0, 3] += 0.1
    est[3, :3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    out = rpe(est, gt, delta=1)
    np.testing.assert_allclose(out["trans_errors"], [0, 0.1, 0], atol=1e-12)
    np.testing.assert_allclose(out["rot_errors"], [0, 0, 10], atol=1e-9)
    assert out["trans_rmse"] == pytest.approx(np.sqrt(0.01 / 3))
    assert out["rot_rmse"] == pytest.approx(10 / np.sqrt(3))
    assert out["n_pairs"] == 3
    # delta 2: pair (0,2): trans(2) vs trans(2.1) -> 0.1 m; pair (1,3): E = [Rz10, (0.1, 0, 0)] -> 0.1 m, 10 deg
    out2 = rpe(est, gt, delta=2)
    np.testing.assert_allclose(out2["trans_errors"], [0.1, 0.1], atol=1e-12)
    assert out2["n_pairs"] == 2
    np.testing.assert_allclose(out2["rot_errors"], [0, 10], atol=1e-9)
    # a missing GT pose removes both pairs that touch it
    gt_bad = gt.copy()
    gt_bad[1] = np.nan
    out3 = rpe(est, gt_bad)
    assert out3["n_pairs"] == 1 and out3["n_excluded"] == 2
    np.testing.assert_array_equal(out3["pairs"], [[2, 3]])


def test_associate_nearest_one_to_one():
    a = np.array([0.0, 0.1, 0.2, 0.3])
    b = np.array([0.31, 0.005, 0.19, 0.5, 0.095, 0.099])
    ia, ib = associate(a, b, max_diff=0.02)
    np.testing.assert_array_equal(ia, [0, 1, 2, 3])
    np.testing.assert_array_equal(ib, [1, 5, 2, 0])  # 0.1 takes 0.099 (closest), 0.095 stays unused
    ia, ib = associate(a, b, max_diff=0.004)
    np.testing.assert_array_equal(ia, [1])
    np.testing.assert_array_equal(ib, [5])
    ia, ib = associate(a, a[::-1].copy(), max_diff=0.0)  # tolerance 0: equal times pair (none did with a strict <)
    np.testing.assert_array_equal(ia, [0, 1, 2, 3])
    np.testing.assert_array_equal(ib, [3, 2, 1, 0])


def test_associate_matches_greedy_brute_force():
    rng = np.random.default_rng(0)
    for _ in range(50):
        a, b = np.sort(rng.uniform(0, 1, 30)), rng.uniform(0, 1, 25)
        pairs = sorted((abs(x - y), i, j) for i, x in enumerate(a) for j, y in enumerate(b) if abs(x - y) <= 0.03)
        used_a, used_b, ref = set(), set(), []
        for _, i, j in pairs:
            if i not in used_a and j not in used_b:
                used_a.add(i), used_b.add(j), ref.append((i, j))
        ia, ib = associate(a, b, 0.03)
        assert sorted(ref) == list(zip(ia.tolist(), ib.tolist()))


def test_associate_indices_and_select_frames():
    ia, ib = associate_indices([0, 2, 4, 6], [4, 0, 5, 6])
    np.testing.assert_array_equal(ia, [0, 2, 3])
    np.testing.assert_array_equal(ib, [1, 0, 3])
    est, gt, _, _ = _noisy_transformed(n=50)
    kf = [0, 10, 20, 30, 40, 49]
    e, g = select_frames(kf, est, gt)
    assert e.shape == (6, 4, 4)
    np.testing.assert_array_equal(g, gt[kf])
    assert ate(e, g)["n_used"] == 6
    with pytest.raises(ValueError):
        select_frames([50], est)


def test_drift_per_100_of_a_linearly_growing_error_and_invariance_to_the_start_pose():
    from inrslam.eval.trajectory import drift_per_100

    n = 51
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 0, 3] = np.linspace(0.0, 1.0, n)  # 2 cm per frame along x
    est = gt.copy()
    est[:, 1, 3] += 0.001 * np.arange(n)  # error grows 1 mm per frame, sideways
    d = drift_per_100(est, gt)
    assert d["drift_m_per_100"] == pytest.approx(0.1) and d["final_m"] == pytest.approx(0.05)
    # the same relative error from another start pose (est is only known up to its first frame)
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T[:3, 3] = (3.0, -2.0, 0.5)
    assert drift_per_100(T @ est, gt)["drift_m_per_100"] == pytest.approx(0.1)
    assert drift_per_100(gt, gt)["drift_m_per_100"] == 0.0
    one = drift_per_100(est[:1], gt[:1])
    assert np.isnan(one["drift_m_per_100"])
