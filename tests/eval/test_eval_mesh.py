"""Ray-cast depth, frustum + occlusion culling, Acc/Comp/Comp% and ICP on constructed scenes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from inrslam.eval.mesh import cull_mesh, icp_point_to_point, mesh_metrics, render_mesh_depth, visibility_counts


def test_render_depth_of_tilted_plane_is_analytic(make_plane, intr):
    plane = make_plane(6.0, 6)
    plane.apply_transform(trimesh.transformations.rotation_matrix(np.radians(20), [0, 1, 0]))
    plane.apply_translation([0.1, -0.2, 2.0])
    n = plane.face_normals[0]
    p0 = plane.vertices[0]
    D = render_mesh_depth(plane, np.eye(4), intr)
    v, u = np.mgrid[0:intr.height, 0:intr.width]
    d = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u, float)], -1)
    z_true = (p0 @ n) / (d @ n)  # ray X = z d meets n.X = n.p0
    np.testing.assert_allclose(D, z_true, atol=1e-9)


def test_render_depth_with_camera_pose_and_double_sided(make_plane, intr):
    plane = make_plane(20.0, 2, z=0.0)  # floor z = 0, normal +z
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.from_euler("x", 180, degrees=True).as_matrix()  # OpenCV z forward -> world -z
    c2w[:3, 3] = [0.3, 0.4, 1.5]
    D = render_mesh_depth(plane, c2w, intr)
    np.testing.assert_allclose(D, 1.5, atol=1e-12)  # looking straight down from 1.5 m
    flipped = plane.copy()
    flipped.invert()  # normals now point away from the camera
    np.testing.assert_allclose(render_mesh_depth(flipped, c2w, intr), 1.5, atol=1e-12)  # double-sided: still seen
    assert np.all(render_mesh_depth(flipped, c2w, intr, double_sided=False) == 0)  # single-sided: back face invisible
    c2w_away = c2w.copy()
    c2w_away[:3, :3] = np.eye(3)  # looking up: nothing there
    assert np.all(render_mesh_depth(plane, c2w_away, intr) == 0)


def _culling_scene(make_plane, make_box):
    wall = make_plane(4.0, 40, z=2.0)  # 10 cm cells; frustum half-width at 2 m is 1.28 m
    hidden = make_box((0.5, 0.5, 0.5), (0.0, 0.0, 3.0))  # behind the wall, inside the frustum
    outside = make_box((0.5, 0.5, 0.5), (5.0, 0.0, 2.0))  # outside the frustum
    visible = make_box((0.3, 0.3, 0.3), (0.3, 0.3, 1.0))  # in front of the wall, casts a "shadow" on it
    return trimesh.util.concatenate([wall, hidden, outside, visible])


def test_cull_removes_hidden_and_outside_keeps_visible(make_plane, make_box, intr):
    scene = _culling_scene(make_plane, make_box)
    cams = np.tile(np.eye(4), (3, 1, 1))
    cams[1] = np.nan  # skipped (every=2 drops it anyway), must not crash
    cams[2, 0, 3] = 0.02  # a second, slightly shifted camera
    culled = cull_mesh(scene, cams, intr, every=2, eps=0.03, occlusion=True)
    c = culled.triangles_center
    assert 0 < len(culled.faces) < len(scene.faces)
    assert not np.any(c[:, 2] > 2.1), "faces of the box hidden behind the wall survived"
    assert not np.any(c[:, 0] > 3.0), "faces of the box outside the frustum survived"
    on_wall = np.abs(c[:, 2] - 2.0) < 1e-9
    # wall: nothing kept whose vertices all lie outside the frustum (|x| or |y| > 1.28 m at 2 m)
    assert np.abs(c[on_wall, :2]).max() < 1.3
    # visible wall away from the box is kept, e.g. around (-0.5, -0.5) and (0.9, -0.9)
    for x, y in ((-0.5, -0.5), (0.9, -0.9), (-1.1, 0.2)):
        assert np.any(on_wall & (np.hypot(c[:, 0] - x, c[:, 1] - y) < 0.1)), (x, y)
    # the wall in the box's shadow (rays from the cameras to it cross the box) is removed
    assert not np.any(on_wall & (np.abs(c[:, 0] - 0.6) < 0.12) & (np.abs(c[:, 1] - 0.6) < 0.12))
    # the visible box: its front face (z = 0.85) is kept, the middle of its back face (z = 1.15) is not
    front = np.abs(c[:, 2] - 0.85) < 1e-9
    back_mid = (np.abs(c[:, 2] - 1.15) < 1e-9) & (np.abs(c[:, 0] - 0.3) < 0.08) & (np.abs(c[:, 1] - 0.3) < 0.08)
    assert front.sum() == 128  # all 2 * 4^3 triangles of the subdivided front face
    assert not back_mid.any()
    assert len(culled.vertices) == len(np.unique(culled.faces))  # unreferenced vertices removed


def test_cull_without_occlusion_only_uses_the_frustum(make_plane, make_box, intr):
    scene = _culling_scene(make_plane, make_box)
    culled = cull_mesh(scene, np.eye(4)[None], intr, every=1, occlusion=False)
    c = culled.triangles_center
    assert np.any(c[:, 2] > 2.1)  # hidden box is kept: it is inside the frustum
    assert not np.any(c[:, 0] > 3.0)  # outside box still removed
    n_in, n_obs = visibility_counts(scene.vertices, np.eye(4)[None], intr, mesh=None)
    np.testing.assert_array_equal(n_in, n_obs)


def test_shifted_plane_gives_1cm_accuracy_and_completion(make_plane):
    """A flat 1 m x 1 m plane against a copy shifted 1 cm along its normal.

    Every point of either plane projects orthogonally into the interior of the other (they have the same
    extent and the shift is along the normal), so the true surface-to-surface distance is exactly 1 cm everywhere
    (apart from a measure-zero rim). With point samples the nearest sample also sits ~r off in-plane, giving
    sqrt(1 cm² + r²) ≈ 1 cm + E[r²]/(2 cm); for 100k samples/m², E[r²] = 1/(πρ) ≈ 3.2 mm², i.e. +0.16 mm.
    """
    gt = make_plane(1.0, 2)
    rec = gt.copy()
    rec.apply_translation([0, 0, 0.01])
    m = mesh_metrics(rec, gt, n_samples=100_000, threshold=0.05, seed=0)
    assert m["acc_m"] == pytest.approx(0.01, abs=1e-3)
    assert m["comp_m"] == pytest.approx(0.01, abs=1e-3)
    assert m["comp_ratio"] == 1.0
    assert mesh_metrics(rec, gt, n_samples=20_000, threshold=0.005)["comp_ratio"] == 0.0
    assert m["icp_applied"] is False and m["icp_transform"] is None
    # seeded: identical numbers on a second call
    assert mesh_metrics(rec, gt, n_samples=100_000, seed=0)["acc_m"] == m["acc_m"]


def test_metrics_on_partial_reconstruction(make_plane):
    """A reconstruction covering half the GT: accuracy ~0, completion ratio ~0.5 (threshold 5 cm)."""
    gt = make_plane(1.0, 20)
    keep = gt.triangles_center[:, 0] < 0
    rec = gt.copy()
    rec.update_faces(keep)
    rec.remove_unreferenced_vertices()
    m = mesh_metrics(rec, gt, n_samples=50_000)
    assert m["acc_m"] < 0.005
    assert m["comp_ratio"] == pytest.approx(0.55, abs=0.02)  # x < 0.05 m is within 5 cm
    assert m["comp_m"] > 0.1


def test_icp_recovers_small_offset(make_box):
    gt = trimesh.util.concatenate([make_box((1.0, 0.6, 0.4), (0, 0, 0)), make_box((0.2, 0.2, 0.8), (0.3, 0.1, 0.6))])
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians([1.0, -2.0, 1.5])).as_matrix()
    T[:3, 3] = [0.02, -0.015, 0.01]
    rec = gt.copy()
    rec.apply_transform(T)
    T_icp, info = icp_point_to_point(rec.vertices, gt.vertices, max_corr=0.1)
    np.testing.assert_allclose(T_icp, np.linalg.inv(T), atol=1e-6)
    assert info["fitness"] == 1.0 and info["inlier_rmse"] < 1e-6
    m_off = mesh_metrics(rec, gt, n_samples=30_000)
    m_on = mesh_metrics(rec, gt, n_samples=30_000, icp=True)
    assert m_on["icp_applied"] and np.allclose(m_on["icp_transform"], np.linalg.inv(T), atol=1e-6)
    # after ICP the reconstruction *is* the GT (to 1e-6 m), so the metrics equal those of GT against itself
    # (same seed -> same samples; the residual is only the sampling floor of 30k points)
    m_self = mesh_metrics(gt, gt, n_samples=30_000)
    assert m_on["acc_m"] == pytest.approx(m_self["acc_m"], abs=1e-5)
    assert m_on["comp_m"] == pytest.approx(m_self["comp_m"], abs=1e-5)
    assert m_off["acc_m"] > m_self["acc_m"] + 0.005


def test_icp_reports_the_fit_of_the_transform_it_returns():
    rng = np.random.default_rng(3)
    dst = rng.uniform(-1, 1, (2000, 3))
    src = dst + [0.03, 0.0, 0.0]  # 3 cm off: one step does not close it (nearest neighbours are not the true pairs)
    for iters in (1, 2):
        T, info = icp_point_to_point(src, dst, max_corr=0.1, max_iter=iters)
        d, _ = cKDTree(dst).query(src @ T[:3, :3].T + T[:3, 3], distance_upper_bound=0.1)
        ok = np.isfinite(d)
        assert info["iterations"] == iters
        assert info["fitness"] == ok.mean() and info["inlier_rmse"] == pytest.approx(np.sqrt(np.mean(d[ok] ** 2)))
    assert icp_point_to_point(src, dst, max_corr=0.1, max_iter=1)[1]["inlier_rmse"] < 0.03  # better than the start


def test_icp_without_inliers_reports_no_fit():
    # every point further than max_corr from the target: no pair ever, and the returned (identity) T has no inliers
    dst = np.random.default_rng().uniform(-1, 1, (200, 3))
    T, info = icp_point_to_point(dst + [5.0, 0.0, 0.0], dst, max_corr=0.1)
    assert np.array_equal(T, np.eye(4)) and info["fitness"] == 0.0 and info["inlier_rmse"] == 0.0
