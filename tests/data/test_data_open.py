"""Layout detection, forced readers, open_dataset (selection, crop, clamp, bounds) and bounds estimation."""

from __future__ import annotations

import numpy as np
import pytest
from data_layouts import H, W, make_7scenes, make_replica, make_scannet, make_tum

from inrslam.data import DATASETS, DataConfig, DatasetView, detect_layout, estimate_bounds, open_folder
from inrslam.datasets import open_dataset
from inrslam.data.bounds import backproject_world
from inrslam.errors import ConfigError, DataError
from inrslam.scenes import export


def test_registry_names():
    assert set(DATASETS.names()) == {"replica", "neuralrgbd", "scannet", "tum", "7scenes"}


def test_detect_picks_the_right_reader(layout):
    name, lay = layout
    assert detect_layout(lay.root) == name
    others = [n for n in DATASETS.names() if n != name]
    assert not any(DATASETS.get(n).detect(lay.root) for n in others)


def test_forced_reader(tmp_path):
    lay = make_7scenes(tmp_path)
    assert open_dataset(DataConfig(path=str(lay.root), dataset="7scenes", bounds=[[0, 1], [0, 1], [0, 1]])).name == "7scenes"
    with pytest.raises(DataError, match="scannet|color"):  # forcing the wrong reader fails naming what it expected
        open_dataset(DataConfig(path=str(lay.root), dataset="scannet"))
    with pytest.raises(ConfigError, match="did you mean '7scenes'"):
        open_dataset(DataConfig(path=str(lay.root), dataset="7scene"))


def test_unknown_layout_lists_expectations(tmp_path):
    (tmp_path / "stuff.txt").write_text("x")
    with pytest.raises(DataError) as e:
        open_dataset(DataConfig(path=str(tmp_path)))
    msg = str(e.value)
    assert str(tmp_path) in msg
    for expected in ("replica", "traj.txt", "neuralrgbd", "poses.txt", "scannet", "intrinsic_depth.txt", "tum",
                     "rgb.txt", "7scenes", "frame-NNNNNN.depth.png"):
        assert expected in msg
    with pytest.raises(DataError, match="not found"):
        open_dataset(DataConfig(path=str(tmp_path / "missing")))


def test_start_stride_max_frames(tmp_path):
    lay = make_7scenes(tmp_path, n=10)
    ds = open_dataset(DataConfig(path=str(lay.root), start=1, stride=3, max_frames=2))
    assert len(ds) == 2 and ds.indices == [1, 4]
    f = ds[1]
    assert f.index == 1 and f.meta["base_index"] == 4
    np.testing.assert_allclose(f.c2w, lay.poses[4])
    assert f.timestamp == pytest.approx(4 / 30)
    np.testing.assert_allclose(ds.poses, np.stack([lay.poses[1], lay.poses[4]]))
    assert [fr.index for fr in ds] == [0, 1]
    assert len(open_dataset(DataConfig(path=str(lay.root), start=7))) == 3
    with pytest.raises(DataError, match="no frames selected"):
        open_dataset(DataConfig(path=str(lay.root), start=10))
    with pytest.raises(ConfigError, match="stride"):
        open_dataset(DataConfig(path=str(lay.root), stride=0))


def test_crop_edge_and_depth_max(tmp_path):
    lay = make_scannet(tmp_path)
    ds = open_dataset(DataConfig(path=str(lay.root), crop_edge=2, depth_max=1.5))
    f0, f1 = ds[0], ds[1]
    assert f0.rgb.shape == (H - 4, W - 4, 3) and f0.depth.shape == (H - 4, W - 4)
    assert (ds.intrinsics.cx, ds.intrinsics.cy, ds.intrinsics.width) == (13.5, 9.5, W - 4) and f0.intrinsics == ds.intrinsics
    assert f0.depth[3, 3] == pytest.approx(1.0)  # 1 m kept
    assert f1.depth[3, 3] == 0.0  # 2 m beyond depth_max -> invalid


def test_overrides(tmp_path):
    lay = make_7scenes(tmp_path)
    ds = open_dataset(DataConfig(path=str(lay.root), depth_scale=500.0, intrinsics=[10, 11, 12, 13],
                                 bounds=[[-1, 1], [-2, 2], [-3, 3]]))
    assert ds[0].depth[5, 5] == pytest.approx(2.0)
    assert (ds.intrinsics.fx, ds.intrinsics.fy, ds.intrinsics.cx, ds.intrinsics.cy) == (10, 11, 12, 13)
    np.testing.assert_array_equal(ds.bounds, [[-1, 1], [-2, 2], [-3, 3]])
    assert not ds.bounds_estimated
    with pytest.raises(ConfigError, match="data.bounds"):
        open_dataset(DataConfig(path=str(lay.root), bounds=[[1, -1], [0, 1], [0, 1]]))
    with pytest.raises(ConfigError, match="data.intrinsics"):
        open_dataset(DataConfig(path=str(lay.root), intrinsics=[1.0, 2.0]))


def test_known_bounds_table_kept(tmp_path):
    lay = make_replica(tmp_path, scene="room1")
    ds = open_dataset(DataConfig(path=str(lay.root), intrinsics=[20, 20, 15.5, 11.5]))
    assert not ds.bounds_estimated
    np.testing.assert_array_equal(ds.bounds, [[-6.0, 1.8], [-3.6, 3.3], [-2.0, 1.9]])


def test_estimated_bounds_contain_points_plus_margin(tmp_path):
    lay = make_7scenes(tmp_path, n=4)
    ds = open_dataset(DataConfig(path=str(lay.root), bounds_frames=4, bounds_margin=0.3))
    assert ds.bounds_estimated and ds.bounds.shape == (3, 2)
    pts = np.concatenate([backproject_world(f.depth, f.intrinsics.K, f.c2w) for f in ds])
    centres = np.stack([T[:3, 3] for T in lay.poses[:4]])
    lo, hi = ds.bounds[:, 0], ds.bounds[:, 1]
    inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    assert inside.mean() > 0.99  # robust percentiles + margin hold essentially all points
    assert not inside[np.linalg.norm(pts, axis=1) > 30].any()  # the 40 m flying pixels are trimmed away
    assert np.all((centres >= lo) & (centres <= hi))
    # without trimming: exactly [min - margin, max + margin] of points and camera centres
    b = estimate_bounds(ds, n_frames=4, margin=0.3, percentile=0.0, points_per_frame=10**9)
    allp = np.concatenate([pts, centres])
    np.testing.assert_allclose(b, np.stack([allp.min(0) - 0.3, allp.max(0) + 0.3], 1), atol=1e-9)


def test_estimate_bounds_skips_invalid_poses(tmp_path):
    lay = make_tum(tmp_path, n=4)  # last frame has no pose
    ds = DatasetView(open_folder(lay.root, DataConfig(intrinsics=[20, 20, 16, 12])))
    b_all = estimate_bounds(ds, n_frames=4, margin=0.0)
    b_valid = estimate_bounds(DatasetView(ds.base, max_frames=3), n_frames=3, margin=0.0)
    np.testing.assert_allclose(b_all, b_valid)


def test_estimate_bounds_identity_for_invalid_frame0(tmp_path):
    from data_layouts import make_neuralrgbd

    lay = make_neuralrgbd(tmp_path, n=2, nan_frame=0)
    ds = DatasetView(open_folder(lay.root, DataConfig(intrinsics=[20, 20, 16, 12])), max_frames=1)
    b = estimate_bounds(ds, n_frames=1, margin=0.0, percentile=0.0)
    f = ds[0]
    pts = backproject_world(f.depth, f.intrinsics.K, np.eye(4))
    np.testing.assert_allclose(b, np.stack([np.minimum(pts.min(0), 0), np.maximum(pts.max(0), 0)], 1), atol=1e-9)


def test_estimate_bounds_without_frame0_pose_are_in_the_frame_slam_maps_in(tmp_path):
    """Frame 0 without a pose starts at the identity in the SLAM loop: the other frames are placed relative to the
    first frame with a pose (before, they stayed in the ground-truth world: a box of two frames' union)."""
    from data_layouts import make_neuralrgbd

    lay = make_neuralrgbd(tmp_path, n=3, nan_frame=0)
    ds = DatasetView(open_folder(lay.root, DataConfig(intrinsics=[20, 20, 16, 12])))
    assert not ds[0].pose_valid and ds[1].pose_valid and ds[2].pose_valid
    b = estimate_bounds(ds, n_frames=3, margin=0.0, percentile=0.0, points_per_frame=10**9)
    to_map = np.linalg.inv(ds[1].c2w)
    poses = [np.eye(4), to_map @ ds[1].c2w, to_map @ ds[2].c2w]
    pts = np.concatenate([backproject_world(ds[i].depth, ds[i].intrinsics.K, poses[i]) for i in range(3)]
                         + [np.stack([T[:3, 3] for T in poses])])
    np.testing.assert_allclose(b, np.stack([pts.min(0), pts.max(0)], 1), atol=1e-9)
    np.testing.assert_allclose(poses[1], np.eye(4), atol=1e-12)  # the first posed frame sits where frame 0 starts
    # sampling frame 2 only (n_frames=2 picks 0 and 2): frame 1, the first posed one, still defines the frame
    b2 = estimate_bounds(ds, n_frames=2, margin=0.0, percentile=0.0, points_per_frame=10**9)
    np.testing.assert_allclose(b2, b, atol=1e-9)


def _builtin(monkeypatch, tmp_path):
    monkeypatch.setenv("INRSLAM_CACHE", str(tmp_path / "cache"))
    cfg = DataConfig(path="builtin:room")
    cfg.builtin.width, cfg.builtin.height, cfg.builtin.frames = 32, 24, 4
    return cfg


def test_builtin_scene(monkeypatch, tmp_path):
    cfg = _builtin(monkeypatch, tmp_path)
    cfg.max_frames = 2
    ds = open_dataset(cfg)
    assert len(ds) == 2 and ds.bounds.shape == (3, 2)
    f = ds[1]
    assert f.rgb.shape == (24, 32, 3) and f.depth.shape == (24, 32) and f.index == 1
    cfg.depth_scale = 1000.0
    with pytest.raises(ConfigError, match="depth_scale"):
        open_dataset(cfg)


@pytest.mark.parametrize("fmt", ["replica", "tum"])
def test_builtin_export_round_trip(monkeypatch, tmp_path, fmt):
    """A built-in scene exported to a public layout reads back as the same frames (scenes x data contract)."""
    cfg = _builtin(monkeypatch, tmp_path)
    src = open_dataset(cfg)
    out = getattr(export, f"export_{fmt}")(src, tmp_path / f"{fmt}_out")
    assert detect_layout(out) == fmt
    back = open_dataset(DataConfig(path=str(out), bounds=[[-1, 1], [-1, 1], [-1, 1]]))
    assert len(back) == len(src) and back.intrinsics == src.intrinsics
    depth_step = 1 / 6553.5 if fmt == "replica" else 1 / 5000
    for a, b in zip(src, back):
        assert b.pose_valid == a.pose_valid
        np.testing.assert_allclose(b.c2w, a.c2w, atol=1e-6)
        assert b.timestamp == pytest.approx(a.timestamp, abs=1e-6)  # both layouts: 30 Hz or the TUM stamps
        clipped = a.depth < (10.0 if fmt == "replica" else 13.0)
        np.testing.assert_allclose(b.depth[clipped], a.depth[clipped], atol=depth_step)
        np.testing.assert_allclose(b.rgb, a.rgb, atol=0.1 if fmt == "replica" else 1 / 255)  # replica colour is JPEG


def test_faithful_intrinsics_floor(tmp_path, monkeypatch):
    monkeypatch.setattr("inrslam.data.base.image_size", lambda p: (640, 480))
    lay = make_tum(tmp_path)
    intr = open_folder(lay.root, DataConfig(faithful_intrinsics=True)).intrinsics
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == (517, 516, 318, 255)
    # an explicit override is never floored
    assert open_folder(lay.root, DataConfig(faithful_intrinsics=True, intrinsics=[1.5, 1.5, 2.5, 2.5])).intrinsics.fx == 1.5


def test_replica_cam_params_json(tmp_path):
    import json

    lay = make_replica(tmp_path, scene="room0")
    (tmp_path / "cam_params.json").write_text(json.dumps(
        {"camera": {"w": W, "h": H, "fx": 30.0, "fy": 31.0, "cx": 15.5, "cy": 11.5, "scale": 1000.0}}))
    ds = open_folder(lay.root)
    assert (ds.intrinsics.fx, ds.intrinsics.fy, ds.intrinsics.width) == (30.0, 31.0, W)
    assert ds[0].depth[5, 5] == pytest.approx(1.0)  # scale 1000 from the file
    (tmp_path / "cam_params.json").write_text("{not json")
    with pytest.raises(DataError, match="cam_params.json"):
        open_folder(lay.root)


def test_estimated_bounds_spread_over_the_sequence(tmp_path):
    """With fewer bounds frames than frames, the frames are spread over the sequence: the last camera is inside."""
    lay = make_7scenes(tmp_path, n=6)
    ds = open_dataset(DataConfig(path=str(lay.root), bounds_frames=2, bounds_margin=0.0, bounds=None))
    lo, hi = ds.bounds[:, 0], ds.bounds[:, 1]
    last = lay.poses[5][:3, 3]
    assert np.all((last >= lo - 1e-9) & (last <= hi + 1e-9))
    b = estimate_bounds(ds, n_frames=2, margin=0.0, percentile=0.0, points_per_frame=10**9)
    used = [0, 5]
    pts = np.concatenate([backproject_world(ds[i].depth, ds[i].intrinsics.K, ds[i].c2w) for i in used]
                         + [np.stack([lay.poses[i][:3, 3] for i in used])])
    np.testing.assert_allclose(b, np.stack([pts.min(0), pts.max(0)], 1), atol=1e-9)
