"""`evaluate_run` on a hand-made run directory, the file-level wrappers and the display table."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from rich.console import Console
from scipy.spatial.transform import Rotation

from inrslam.errors import DataError
from inrslam.eval import EvalConfig, eval_mesh_files, eval_trajectory_files, evaluate_run, format_table
from inrslam.eval.run import RESULT_KEYS
from inrslam.eval.trajectory import ate
from inrslam.io.atomic import write_json
from inrslam.io.trajectory import write_tum

N = 20


def _gt_poses() -> np.ndarray:
    """Cameras at z = 0 sliding along x, looking at +z (towards a wall at z = 2), small yaw wobble."""
    T = np.tile(np.eye(4), (N, 1, 1))
    T[:, 0, 3] = np.linspace(-0.1, 0.1, N)
    T[:, 1, 3] = 0.02 * np.sin(np.arange(N))
    T[:, :3, :3] = Rotation.from_euler("y", 2.0 * np.sin(0.5 * np.arange(N))[:, None], degrees=True).as_matrix()
    return T


@pytest.fixture
def run_dir(tmp_path, make_plane, make_box, intr):
    rd = tmp_path / "run"
    rd.mkdir()
    ts = np.arange(N) * 0.1
    gt = _gt_poses()
    rng = np.random.default_rng(0)
    est = gt.copy()
    est[:, :3, 3] += rng.normal(0, 0.01, (N, 3))
    write_tum(rd / "trajectory.txt", ts, est)
    has_gt = np.ones(N, bool)
    has_gt[[3, 4]] = False  # frames without GT are not in trajectory_gt.txt
    write_tum(rd / "trajectory_gt.txt", ts[has_gt], gt[has_gt])
    gt_mesh = make_plane(1.0, 20, z=2.0)  # 1 m x 1 m wall, entirely in view
    gt_mesh.export(tmp_path / "gt_wall.ply")
    rec = trimesh.util.concatenate([make_plane(1.0, 20, z=1.99), make_box((0.4, 0.4, 0.4), (0, 0, 3.0))])
    rec.export(rd / "mesh.ply")  # 1 cm in front of the GT wall + a box hidden behind it (must be culled)
    write_json(rd / "run_info.json", {
        "intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
                       "width": intr.width, "height": intr.height},
        "gt_mesh": str(tmp_path / "gt_wall.ply"),
        "keyframes": [0, 5, 10, 15],
        "timestamps": ts.tolist(),
    })
    write_json(rd / "metrics.json", {"track_ms_per_frame": 12.5, "psnr_process_db": 30.1, "model_size_mb": 3.2,
                                     "ate_rmse_m": 999.0})
    return rd, est, gt, has_gt


FAST = EvalConfig(n_samples=50_000)


def test_evaluate_run_produces_documented_keys(run_dir):
    rd, est, gt, has_gt = run_dir
    out = evaluate_run(rd, FAST)
    for k in RESULT_KEYS:
        assert k in out, k
    assert set(out["protocol"]) >= {"alignment", "association", "culling", "n_samples", "threshold", "icp"}
    assert set(out["protocol"]["culling"]) >= {"every", "eps", "occlusion"}
    assert out["protocol"]["alignment"] == "se3" and out["protocol"]["icp"] is False
    # process metrics are kept, result metrics recomputed
    assert out["track_ms_per_frame"] == 12.5 and out["psnr_process_db"] == 30.1 and out["model_size_mb"] == 3.2
    assert out["frames"] == N
    ref = ate(est[has_gt], gt[has_gt])
    assert out["ate_rmse_m"] == pytest.approx(ref["rmse"], abs=1e-6)  # 9-decimal TUM files
    assert out["ate_max_m"] == pytest.approx(ref["max"], abs=1e-6)
    assert out["ate_n_excluded"] == 2 and out["ate_n_used"] == N - 2
    kf = [0, 5, 10, 15]
    assert out["ate_keyframes_rmse_m"] == pytest.approx(ate(est[kf], gt[kf])["rmse"], abs=1e-6)
    assert out["rpe_trans_m"] > 0 and out["rpe_rot_deg"] < 1e-4  # only translations were perturbed
    # mesh: the hidden box is culled, so the 1 cm offset is all that remains
    assert out["mesh_eval"]["culled_faces"] < out["mesh_eval"]["rec_faces"]
    assert out["acc_m"] == pytest.approx(0.01, abs=2e-3)
    assert out["comp_m"] == pytest.approx(0.01, abs=2e-3)
    assert out["comp_ratio"] == 1.0
    # written back atomically and identical (JSON) to the returned dict
    on_disk = json.loads((rd / "metrics.json").read_text())
    assert on_disk == json.loads(json.dumps(out))
    assert not list(rd.glob(".metrics.json.*"))  # no temporary left behind


def test_evaluate_run_without_gt_mesh_gives_null_mesh_metrics(run_dir):
    rd, *_ = run_dir
    info = json.loads((rd / "run_info.json").read_text())
    info["gt_mesh"] = None
    del info["keyframes"]
    write_json(rd / "run_info.json", info)
    out = evaluate_run(rd, FAST)
    assert out["acc_m"] is None and out["comp_m"] is None and out["comp_ratio"] is None
    assert out["ate_keyframes_rmse_m"] is None
    assert out["ate_rmse_m"] is not None
    assert any("GT mesh" in n for n in out["eval_notes"]) and any("keyframe" in n for n in out["eval_notes"])
    assert json.loads((rd / "metrics.json").read_text())["acc_m"] is None


def test_eval_trajectory_files_associates_by_timestamp(tmp_path):
    gt = _gt_poses()
    est = gt.copy()
    est[:, 2, 3] += 0.03  # constant offset: removed by the SE(3) alignment
    ts = np.arange(N) * 0.1
    write_tum(tmp_path / "est.txt", ts + 0.004, est)  # clocks differ by 4 ms
    write_tum(tmp_path / "gt.txt", ts[:15], gt[:15])
    out = eval_trajectory_files(tmp_path / "est.txt", tmp_path / "gt.txt", max_diff=0.02)
    assert out["n_matched"] == 15 and out["n_est"] == N and out["n_gt"] == 15
    assert out["ate_rmse_m"] < 1e-6
    assert eval_trajectory_files(tmp_path / "est.txt", tmp_path / "gt.txt", align="none")["ate_rmse_m"] == \
        pytest.approx(0.03, abs=1e-6)


def test_eval_mesh_files_with_cameras(tmp_path, make_plane, make_box, intr):
    make_plane(1.0, 20, z=2.0).export(tmp_path / "gt.ply")
    rec = trimesh.util.concatenate([make_plane(1.0, 20, z=2.0), make_box((0.4, 0.4, 0.4), (0, 0, 3.0))])
    rec.export(tmp_path / "rec.ply")
    write_tum(tmp_path / "cams.txt", np.arange(N) * 0.1, _gt_poses())
    out = eval_mesh_files(tmp_path / "rec.ply", tmp_path / "gt.ply", tmp_path / "cams.txt", intr,
                          n_samples=20_000, culled_out=tmp_path / "culled.ply")
    assert out["acc_m"] < 0.01 and out["comp_ratio"] == 1.0
    culled = trimesh.load(tmp_path / "culled.ply", process=False)
    assert len(culled.faces) == out["mesh_eval"]["culled_faces"] < len(rec.faces)
    assert culled.vertices[:, 2].max() < 2.0 + 1e-6  # the hidden box is gone
    unculled = eval_mesh_files(tmp_path / "rec.ply", tmp_path / "gt.ply", n_samples=20_000)
    assert unculled["acc_m"] > 0.1 and unculled["protocol"]["culling"] is None  # the box ruins accuracy


def test_format_table_shows_lengths_in_cm():
    metrics = {"ate_rmse_m": 0.0123, "comp_ratio": 0.875, "rpe_rot_deg": 0.5, "frames": 20, "acc_m": None,
               "protocol": {"alignment": "se3"}, "eval_notes": ["x"]}
    table = format_table(metrics)
    console = Console(width=120, record=True)
    console.print(table)
    text = console.export_text()
    assert "ATE RMSE" in text and "1.2300" in text and "cm" in text
    assert "87.50" in text and "%" in text
    assert "—" in text  # None shown as a dash
    assert "protocol" not in text
    assert [c.header for c in table.columns] == ["metric", "value", "unit"]


def test_evaluate_run_accepts_run_config_eval_section(run_dir):
    """The run config's `eval:` section (other keys, plain-string align) is accepted; unknown keys are ignored."""
    from types import SimpleNamespace

    rd, est, gt, has_gt = run_dir
    section = SimpleNamespace(enabled=True, heldout_every=10, align="sim3", mesh_metrics=False, n_samples=1000)
    out = evaluate_run(rd, section)
    assert out["protocol"]["alignment"] == "sim3" and out["protocol"]["n_samples"] == 1000
    assert out["acc_m"] is None and any("disabled" in n for n in out["eval_notes"])
    assert out["ate_rmse_m"] == pytest.approx(ate(est[has_gt], gt[has_gt], "sim3")["rmse"], abs=1e-6)
    out = evaluate_run(rd, {"align": "none", "mesh_metrics": False}, write=False)
    assert out["ate_rmse_m"] == pytest.approx(ate(est[has_gt], gt[has_gt], "none")["rmse"], abs=1e-6)
    assert json.loads((rd / "metrics.json").read_text())["protocol"]["alignment"] == "sim3"  # write=False


def test_virtual_cameras_and_gt_culling(tmp_path, make_plane, make_box, intr):
    """A box behind the wall is invisible to the real cameras; a virtual camera behind the wall sees it.

    GT = wall + box, reconstruction = wall only. Culling the GT with the real cameras removes the hidden box, so the
    reconstruction is complete (Comp% = 1); adding a virtual camera that looks at the box brings it back (Comp% < 1).
    """
    wall = make_plane(1.0, 20, z=2.0)
    gt = trimesh.util.concatenate([wall, make_box((0.4, 0.4, 0.4), (0, 0, 3.0))])
    gt.export(tmp_path / "gt.ply")
    wall.export(tmp_path / "rec.ply")
    write_tum(tmp_path / "cams.txt", np.arange(N) * 0.1, _gt_poses())
    base = dict(n_samples=20_000)
    plain = eval_mesh_files(tmp_path / "rec.ply", tmp_path / "gt.ply", tmp_path / "cams.txt", intr, **base)
    assert plain["comp_ratio"] < 0.9  # the unculled GT box counts as missed
    culled = eval_mesh_files(tmp_path / "rec.ply", tmp_path / "gt.ply", tmp_path / "cams.txt", intr, cull_gt=True,
                             **base)
    assert culled["comp_ratio"] == 1.0 and culled["mesh_eval"]["gt_faces"] < culled["mesh_eval"]["gt_split_faces"]
    assert culled["protocol"]["culling"]["culled"] == "reconstructed and ground-truth meshes"
    virt = np.eye(4)[None].copy()
    virt[0, :3, 3] = [0.0, 0.0, 4.5]  # behind the box, looking back at it (OpenCV: +z forward -> rotate 180° about y)
    virt[0, :3, :3] = np.diag([-1.0, 1.0, -1.0])
    write_tum(tmp_path / "virt.txt", np.zeros(1), virt)
    with_virt = eval_mesh_files(tmp_path / "rec.ply", tmp_path / "gt.ply", tmp_path / "cams.txt", intr, cull_gt=True,
                                virtual_cameras=tmp_path / "virt.txt", **base)
    assert with_virt["mesh_eval"]["cameras_used"] == culled["mesh_eval"]["cameras_used"] + 1
    assert with_virt["comp_ratio"] < culled["comp_ratio"]


def test_a_ground_truth_mesh_no_camera_sees_gives_null_mesh_metrics_and_a_note(run_dir, make_plane, tmp_path):
    rd, *_ = run_dir
    make_plane(1.0, 20, z=-2.0).export(tmp_path / "gt_wall.ply")  # the GT wall behind every camera
    out = evaluate_run(rd, EvalConfig(n_samples=20_000, cull_gt=True))
    assert out["acc_m"] is None and out["comp_m"] is None and out["comp_ratio"] is None
    assert out["ate_rmse_m"] is not None  # the trajectory metrics are still written
    assert any("ground-truth mesh has no triangles seen by the cameras" in n for n in out["eval_notes"])
    assert json.loads((rd / "metrics.json").read_text())["ate_rmse_m"] == out["ate_rmse_m"]


def test_mesh_files_without_triangles_are_a_one_line_error(tmp_path, make_plane, intr):
    make_plane(1.0, 10, z=2.0).export(tmp_path / "wall.ply")
    trimesh.PointCloud(np.random.default_rng(0).uniform(-1, 1, (50, 3))).export(tmp_path / "points.ply")
    with pytest.raises(DataError, match=r"points\.ply: no triangles with area \(a point cloud\?\)"):
        eval_mesh_files(tmp_path / "wall.ply", tmp_path / "points.ply", n_samples=1000)
    write_tum(tmp_path / "cams.txt", np.arange(N) * 0.1, _gt_poses())
    make_plane(1.0, 10, z=-2.0).export(tmp_path / "behind.ply")
    with pytest.raises(DataError, match="ground-truth mesh has no triangles seen by the cameras"):
        eval_mesh_files(tmp_path / "wall.ply", tmp_path / "behind.ply", tmp_path / "cams.txt", intr, cull_gt=True,
                        n_samples=1000)


def test_sim3_alignment_of_an_estimate_that_never_moves(run_dir, tmp_path):
    rd, est, gt, has_gt = run_dir
    still = np.tile(np.eye(4), (N, 1, 1))
    ts = np.arange(N) * 0.1
    write_tum(tmp_path / "still.txt", ts, still)
    write_tum(tmp_path / "gt.txt", ts, gt)
    with pytest.raises(DataError, match="Sim\\(3\\) alignment: the estimated camera positions never move"):
        eval_trajectory_files(tmp_path / "still.txt", tmp_path / "gt.txt", align="sim3")
    se3 = eval_trajectory_files(tmp_path / "still.txt", tmp_path / "gt.txt", align="se3")
    assert se3["ate_rmse_m"] == pytest.approx(ate(still, gt)["rmse"], abs=1e-6)
    write_tum(rd / "trajectory.txt", ts, still)  # a run whose tracking never moved: null keys and a note
    out = evaluate_run(rd, EvalConfig(n_samples=20_000, align="sim3"))
    assert out["ate_rmse_m"] is None and out["rpe_trans_m"] is None and out["acc_m"] is not None
    assert any(n.startswith("no ATE/RPE: Sim(3) alignment") for n in out["eval_notes"])


def test_a_metrics_file_that_is_not_utf8_is_a_one_line_error(run_dir):
    rd, *_ = run_dir
    (rd / "metrics.json").write_bytes(b'{"frames": 1, \xff}')
    with pytest.raises(DataError, match=r"metrics\.json: invalid JSON"):
        evaluate_run(rd, FAST)


def test_evaluation_does_not_write_beside_a_process_running_in_the_folder(run_dir):
    """Another process holding the run folder (a resumed run finishing, a second `inrslam eval`): evaluating it
    for writing is one RunError and metrics.json stays as it was; reading it only (`write=False`) still works."""
    from inrslam.errors import RunError
    from inrslam.io.lock import acquire
    from inrslam.io.rundir import RunDir

    rd = run_dir[0]
    before = (rd / "metrics.json").read_bytes()
    held = acquire(rd / RunDir.LOCK_FILE)  # as the other process holds it
    try:
        with pytest.raises(RunError, match="another inrslam process is running in this run folder"):
            evaluate_run(rd, FAST)
        assert (rd / "metrics.json").read_bytes() == before
        assert evaluate_run(rd, FAST, write=False)["ate_rmse_m"] < 0.1  # computed, not the file's 999
    finally:
        held.close()
    assert (rd / "metrics.json").read_bytes() == before
    assert evaluate_run(rd, FAST)["ate_rmse_m"] < 0.1  # free again
    assert json.loads((rd / "metrics.json").read_text())["ate_rmse_m"] < 0.1
