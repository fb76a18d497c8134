"""Mapping with given poses (`slam.poses` / `inrslam run --poses`): association, anchoring, errors, end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from interrupted import run_interrupted
from scipy.spatial.transform import Rotation

from inrslam.cli import main
from inrslam.config import load_config
from inrslam.data.given_poses import associate_to_frames, load_given_poses
from inrslam.datasets import open_dataset
from inrslam.errors import DataError
from inrslam.io.trajectory import read_tum, write_tum
from inrslam.runner import resume_slam, run_slam

FRAMES = 6
OVERRIDES = [f"data.max_frames={FRAMES}", "output.tensorboard=false", "slam.checkpoint_every=3", "seed=5",
             "eval.heldout_max=1", "slam.init_iters=30"]


def rigid(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.3).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    return T


@pytest.fixture(scope="module")
def dataset():
    return open_dataset(load_config(preset="quick", overrides=OVERRIDES).data)


def test_association_takes_the_nearest_pose_and_names_a_frame_without_one():
    file_ts = np.array([0.30, 0.10, 0.205, 0.0])  # any order
    idx = associate_to_frames(np.array([0.0, 0.1, 0.2, 0.3]), file_ts, 0.01, Path("p.txt"))
    assert file_ts[idx].tolist() == [0.0, 0.10, 0.205, 0.30]
    with pytest.raises(DataError, match=r"p\.txt: no pose within 0\.01 s of frame 2 \(timestamp 0\.250000"):
        associate_to_frames(np.array([0.0, 0.1, 0.25]), file_ts, 0.01, Path("p.txt"))


def test_gt_poses_are_the_datasets(dataset, monkeypatch):
    monkeypatch.setattr(type(dataset), "__getitem__", lambda self, i: pytest.fail("read a frame's images"))
    given = load_given_poses("gt", dataset)  # from the pose table alone (built-in scenes too)
    assert given.source == {"source": "gt"}
    assert np.array_equal(given.c2w, dataset.poses) and dataset.pose_valid.all()


def test_pose_file_is_anchored_at_frame_zero_unless_asked_not_to(dataset, tmp_path):
    gt, ts = dataset.poses, dataset.timestamps
    A = rigid(np.random.default_rng(0))  # another system's world frame
    path = tmp_path / "other.txt"
    write_tum(path, ts + 0.004, A @ gt)  # timestamps a little off, within the tolerance
    anchored = load_given_poses(str(path), dataset, tolerance=0.01)
    assert anchored.source["anchored"] and anchored.source["source"] == "file"
    assert np.allclose(anchored.c2w, gt, atol=1e-6)
    kept = load_given_poses(str(path), dataset, tolerance=0.01, anchor=False)
    assert not kept.source["anchored"]
    assert np.allclose(kept.c2w, A @ gt, atol=1e-6)
    with pytest.raises(DataError, match="no pose within 0.001 s of frame 0"):
        load_given_poses(str(path), dataset, tolerance=0.001)


def test_pose_file_without_frame0_ground_truth_is_anchored_at_the_identity(dataset, tmp_path):
    """Frame 0 without ground truth: a SLAM run starts it at the identity (and the estimated box is in that frame),
    so a pose file is moved there too instead of staying in its own world."""

    class NoFirstPose:
        timestamps, poses = dataset.timestamps, dataset.poses
        pose_valid = np.r_[False, np.ones(len(dataset.poses) - 1, bool)]

        def __len__(self):
            return len(self.poses)

    gt, ts = dataset.poses, dataset.timestamps
    A = rigid(np.random.default_rng(1))
    path = tmp_path / "other.txt"
    write_tum(path, ts, A @ gt)
    given = load_given_poses(str(path), NoFirstPose(), tolerance=0.01)
    assert given.source["anchored"]
    np.testing.assert_allclose(given.c2w[0], np.eye(4), atol=1e-9)
    expected = np.linalg.inv(gt[0]) @ gt  # the trajectory's own shape, frame 0 at the identity
    np.testing.assert_allclose(given.c2w, expected, atol=1e-6)


def test_bad_pose_files_fail_with_one_line_naming_file_and_line(dataset, tmp_path):
    nan = tmp_path / "nan.txt"
    nan.write_text("0.0 0 0 0 0 0 0 1\n0.1 nan 0 0 0 0 0 1\n")
    with pytest.raises(DataError, match=r"nan\.txt:2: non-finite"):
        load_given_poses(str(nan), dataset)
    binary = tmp_path / "bin.txt"
    binary.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(DataError, match=r"bin\.txt: cannot read"):
        load_given_poses(str(binary), dataset)
    with pytest.raises(DataError, match="not found"):
        load_given_poses(str(tmp_path / "missing.txt"), dataset)


@pytest.fixture(scope="module")
def gt_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("given") / "gt"
    run_slam(load_config(preset="quick", overrides=OVERRIDES + ["slam.poses=gt"]), out)
    return out


def test_a_given_pose_run_keeps_the_given_poses_and_says_where_they_came_from(gt_run, dataset):
    ts, est = read_tum(gt_run / "trajectory.txt")
    assert len(ts) == FRAMES
    assert np.allclose(est, dataset.poses, atol=1e-6)  # float32 poses, TUM text: no tracking, no bundle adjustment
    metrics = json.loads((gt_run / "metrics.json").read_text())
    assert metrics["poses"] == "gt" and metrics["ate_rmse_m"] < 1e-5
    assert metrics["track_ms_per_frame"] is None and metrics["map_ms_per_frame"] > 0
    assert metrics["acc_m"] is not None and metrics["psnr_db"] is not None
    info = json.loads((gt_run / "run_info.json").read_text())
    assert info["poses"] == {"source": "gt"}
    log = [json.loads(line) for line in (gt_run / "log.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in log if r["type"] == "pose"] == list(range(1, FRAMES))
    assert not [r for r in log if r["type"] == "track"]
    assert [r["frame"] for r in log if r["type"] == "map"] == list(range(5, FRAMES, 5))


def test_mapping_every_frame_maps_every_frame_and_a_finished_run_may_drop_its_checkpoint(tmp_path):
    out = tmp_path / "every"
    run_slam(load_config(preset="quick", overrides=OVERRIDES[:1] + ["data.max_frames=4", "slam.poses=gt",
                                                                      "slam.init_iters=10",
                                                                      "slam.map_every=1", "mesh.enabled=false",
                                                                      "eval.enabled=false", "slam.checkpoint_every=2",
                                                                      "output.keep_checkpoint=false"]), out)
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in log if r["type"] == "map"] == [1, 2, 3]
    assert not (out / "checkpoints").exists()
    assert log[-1]["type"] == "checkpoint_removed" and log[-1]["bytes"] > 0
    assert json.loads((out / "run_info.json").read_text())["status"] == "complete"


def test_a_given_pose_run_resumes_to_the_same_map(gt_run, tmp_path):
    out = tmp_path / "cut"

    run_interrupted(load_config(preset="quick", overrides=OVERRIDES + ["slam.poses=gt"]), out, 3)
    assert (out / "checkpoints" / "latest.pt").exists() and not (out / "metrics.json").exists()
    resume_slam(out)
    assert (out / "trajectory.txt").read_bytes() == (gt_run / "trajectory.txt").read_bytes()
    a = json.loads((gt_run / "metrics.json").read_text())
    b = json.loads((out / "metrics.json").read_text())
    assert a["acc_m"] == b["acc_m"] and a["psnr_db"] == b["psnr_db"]


def test_cli_poses_file_without_a_pose_for_a_frame_is_a_one_line_error(dataset, tmp_path, capsys):
    path = tmp_path / "short.txt"
    write_tum(path, dataset.timestamps[:5], dataset.poses[:5])
    rc = main(["run", "--preset", "quick", "--out", str(tmp_path / "r"), "--poses", str(path), "--quiet",
               *OVERRIDES])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and len(err.splitlines()) == 1
    assert "short.txt: no pose within 0.02 s of frame 5" in err
