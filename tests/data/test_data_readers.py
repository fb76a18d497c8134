"""Each reader on a fixture in its exact public layout: counts, arrays, units, intrinsics, pose conventions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from data_layouts import H, W, green, make_7scenes, make_neuralrgbd, make_replica, make_scannet, make_tum, write_rgb

from inrslam.data import DATASETS, DataConfig, Frame, RGBDDataset, open_folder
from inrslam.data.config import NeuralRgbdConfig, SevenScenesConfig, TumConfig
from inrslam.data.neuralrgbd import FOCAL
from inrslam.data.timestamps import associate
from inrslam.errors import ConfigError, DataError, InrslamWarning

JPEG_TOL = 3 / 255


def test_common_contract(layout):
    name, lay = layout
    # Replica / NeuralRGBD / TUM have fixed cameras (1200x680, 640x480): the 32x24 fixtures need an override
    cfg = DataConfig(intrinsics=[20.0, 21.0, 15.5, 11.5]) if name in ("replica", "neuralrgbd", "tum") else None
    ds = DATASETS.get(name)(lay.root, cfg)
    assert isinstance(ds, RGBDDataset)
    assert ds.name == name and len(ds) == lay.n
    frames = list(ds)
    assert len(frames) == lay.n
    for k, f in enumerate(frames):
        assert isinstance(f, Frame) and f.index == k
        assert f.rgb.shape == (H, W, 3) and f.rgb.dtype == np.float32
        assert f.depth.shape == (H, W) and f.depth.dtype == np.float32
        assert f.intrinsics.width == W and f.intrinsics.height == H
        assert 0.0 <= f.rgb.min() and f.rgb.max() <= 1.0
        np.testing.assert_allclose(f.rgb[5, 5], np.array([200, green(k), 100]) / 255, atol=JPEG_TOL)
        # depth in metres: 1000 (k + 1) raw units; raw 0 stays 0; raw 40000 (> 32767) read exactly
        assert f.depth[5, 5] == pytest.approx(1000 * (k + 1) / lay.depth_scale, rel=1e-6)
        assert f.depth[0, 0] == 0.0
        assert f.depth[1, 2] == pytest.approx(40000 / lay.depth_scale, rel=1e-6)
        assert f.c2w.dtype == np.float64 and f.c2w.shape == (4, 4)
        assert f.pose_valid == lay.valid[k]
        if lay.valid[k]:
            np.testing.assert_allclose(f.c2w, lay.poses[k], atol=1e-6)
        else:
            assert np.all(np.isnan(f.c2w))
        assert f.timestamp == pytest.approx(lay.timestamps[k], abs=1e-6)
    np.testing.assert_array_equal(ds.pose_valid, lay.valid)
    assert ds[-1].index == lay.n - 1
    with pytest.raises(IndexError):
        ds[lay.n]


def test_replica_defaults_bounds_mesh(tmp_path):
    lay = make_replica(tmp_path, scene="office2")
    with pytest.raises(DataError, match="1200x680"):  # the 32x24 fixture does not match the Replica camera
        open_folder(lay.root)
    ds = open_folder(lay.root, DataConfig(intrinsics=[16.0, 16.0, 15.5, 11.5]))
    assert ds.intrinsics.fx == 16.0 and ds.intrinsics.width == W
    np.testing.assert_array_equal(ds.bounds, [[-4.0, 3.6], [-3.4, 5.9], [-1.8, 2.1]])
    assert ds.gt_mesh == tmp_path / "office2_mesh.ply"
    other = make_replica(tmp_path / "x", scene="myscan", mesh=False)
    ds2 = open_folder(other.root, DataConfig(intrinsics=[16.0, 16.0, 15.5, 11.5]))
    assert ds2.bounds is None and ds2.gt_mesh is None


def test_replica_true_and_faithful_intrinsics(tmp_path, monkeypatch):
    from inrslam.data import replica

    lay = make_replica(tmp_path)
    # pretend the images were 1200x680 so the default camera applies
    monkeypatch.setattr("inrslam.data.base.image_size", lambda p: (1200, 680))
    ds = replica.ReplicaDataset(lay.root)
    assert (ds.intrinsics.fx, ds.intrinsics.fy, ds.intrinsics.cx, ds.intrinsics.cy) == (600, 600, 599.5, 339.5)
    ds = replica.ReplicaDataset(lay.root, DataConfig(faithful_intrinsics=True))
    assert (ds.intrinsics.cx, ds.intrinsics.cy) == (599.0, 339.0)


def test_neuralrgbd_prefers_the_benchmarks_pre_culled_gt_mesh(tmp_path):
    lay = make_neuralrgbd(tmp_path, n=3)
    (lay.root / "gt_mesh.ply").write_text("ply\n")
    cfg = DataConfig(intrinsics=[20.0, 20.0, 16.0, 12.0])
    assert open_folder(lay.root, cfg).gt_mesh == lay.root / "gt_mesh.ply"
    (lay.root / "gt_mesh_cull_virt_cams.ply").write_text("ply\n")
    assert open_folder(lay.root, cfg).gt_mesh == lay.root / "gt_mesh_cull_virt_cams.ply"


def test_neuralrgbd_opengl_converted_and_nan_invalid(tmp_path, monkeypatch):
    lay = make_neuralrgbd(tmp_path, n=3, nan_frame=1)
    ds = open_folder(lay.root, DataConfig(intrinsics=[20.0, 20.0, 16.0, 12.0]))
    T = ds[0].c2w
    # the file holds T_cv @ diag(1,-1,-1,1); the reader must undo it: camera y points down, z forward
    np.testing.assert_allclose(T, lay.poses[0], atol=1e-9)
    assert not ds[1].pose_valid and np.all(np.isnan(ds[1].c2w))
    np.testing.assert_array_equal(ds.bounds, [[-2.4, 2.0], [-0.6, 2.9], [-1.8, 3.1]])
    # the unfiltered depth folder is selectable and differs by one raw unit (1 mm)
    raw_cfg = DataConfig(intrinsics=[20.0, 20.0, 16.0, 12.0], neuralrgbd=NeuralRgbdConfig(depth_dir="depth"))
    ds_raw = open_folder(lay.root, raw_cfg)
    assert ds_raw[0].depth[5, 5] - ds[0].depth[5, 5] == pytest.approx(0.001, abs=1e-6)


def test_neuralrgbd_default_intrinsics(tmp_path, monkeypatch):
    from inrslam.data.neuralrgbd import NeuralRGBDDataset

    lay = make_neuralrgbd(tmp_path)
    monkeypatch.setattr("inrslam.data.base.image_size", lambda p: (640, 480))
    ds = NeuralRGBDDataset(lay.root)
    assert (ds.intrinsics.fx, ds.intrinsics.cx, ds.intrinsics.cy) == (FOCAL, 320.0, 240.0)
    assert NeuralRGBDDataset(lay.root, DataConfig(faithful_intrinsics=True)).intrinsics.fx == 554.0


def test_neuralrgbd_natural_sort(tmp_path):
    lay = make_neuralrgbd(tmp_path, n=12, nan_frame=None)
    ds = open_folder(lay.root, DataConfig(intrinsics=[20.0, 20.0, 16.0, 12.0]))
    assert [ds._rgb[k].name for k in (1, 2, 10)] == ["img1.png", "img2.png", "img10.png"]
    np.testing.assert_allclose(ds[10].c2w, lay.poses[10], atol=1e-9)


def test_scannet_resizes_colour_and_reads_intrinsic_depth(tmp_path):
    lay = make_scannet(tmp_path)
    ds = open_folder(lay.root)
    assert (ds.intrinsics.fx, ds.intrinsics.fy, ds.intrinsics.cx, ds.intrinsics.cy) == (28.5, 29.5, 15.5, 11.5)
    assert ds[0].rgb.shape == (H, W, 3)  # colour was 64 x 48 on disk
    assert not ds[2].pose_valid and np.all(np.isnan(ds[2].c2w))  # -inf in the file


def test_scannet_numeric_sort(tmp_path):
    lay = make_scannet(tmp_path, n=11, inf_frame=None)
    ds = open_folder(lay.root)
    assert [p.name for p in ds._rgb[:3]] == ["0.jpg", "1.jpg", "2.jpg"] and ds._rgb[10].name == "10.jpg"
    np.testing.assert_allclose(ds[10].c2w, lay.poses[10], atol=1e-9)


def test_tum_association(tmp_path):
    lay = make_tum(tmp_path, n=4)
    K = [20.0, 20.0, 16.0, 12.0]
    ds = open_folder(lay.root, DataConfig(intrinsics=K))
    assert len(ds) == 4 and ds.dropped_unpaired == 1  # the extra colour frame has no depth
    assert [p.name for p in ds._depth] == [f"{t + 0.005:.6f}.png" for t in lay.timestamps]
    # the ground truth is 3 ms off the colour stamps: matched; the last frame has none within 0.02 s
    assert list(ds.pose_valid) == [True, True, True, False]
    # a tighter pose tolerance invalidates them
    assert not open_folder(lay.root, DataConfig(intrinsics=K, tum=TumConfig(max_dt_pose=0.001))).pose_valid.any()
    # depth is 5 ms after colour: a 1 ms tolerance pairs nothing -> error naming the lists
    with pytest.raises(DataError, match="rgb.txt"):
        open_folder(lay.root, DataConfig(intrinsics=K, tum=TumConfig(max_dt_depth=0.001)))


def test_tum_default_intrinsics_by_sequence(tmp_path, monkeypatch):
    monkeypatch.setattr("inrslam.data.base.image_size", lambda p: (640, 480))
    fr1 = open_folder(make_tum(tmp_path / "a").root).intrinsics
    assert (fr1.fx, fr1.fy, fr1.cx, fr1.cy, fr1.width) == (517.3, 516.5, 318.6, 255.3, 640)
    fr3 = open_folder(make_tum(tmp_path / "b", scene="rgbd_dataset_freiburg3_office").root).intrinsics
    assert (fr3.fx, fr3.fy) == (535.4, 539.2)


def test_tum_camera_named_by_the_sequence_folder_itself(tmp_path, monkeypatch):
    """A parent folder's or a symlink's name does not choose the camera; the folder's own name does (as given,
    else the symlink target's), and no name at all warns before taking freiburg1."""
    monkeypatch.setattr("inrslam.data.base.image_size", lambda p: (640, 480))
    fr3 = open_folder(make_tum(tmp_path / "freiburg2_runs", scene="rgbd_dataset_freiburg3_office").root).intrinsics
    assert (fr3.fx, fr3.fy) == (535.4, 539.2)  # was freiburg2's: the parent folder's name matched first
    target = make_tum(tmp_path / "store", scene="rgbd_dataset_freiburg2_desk").root
    (tmp_path / "rgbd_dataset_freiburg3_walking").symlink_to(target)
    fr3 = open_folder(tmp_path / "rgbd_dataset_freiburg3_walking").intrinsics  # the name as given
    assert (fr3.fx, fr3.fy) == (535.4, 539.2)
    (tmp_path / "mine").symlink_to(target)
    fr2 = open_folder(tmp_path / "mine").intrinsics  # the given name names none: the target's
    assert (fr2.fx, fr2.fy) == (520.9, 521.0)
    plain = make_tum(tmp_path / "c", scene="kitchen").root
    with pytest.warns(InrslamWarning, match=r"kitchen: the folder name names no TUM camera .* data\.intrinsics"):
        fr1 = open_folder(plain).intrinsics
    assert (fr1.fx, fr1.fy) == (517.3, 516.5)


def test_tum_reader_pairs_colour_and_depth_closest_first_one_to_one(tmp_path):
    # the reader pairs colour with depth by the evaluation's association (one rule, `data.timestamps`):
    # colour 1's nearest depth (0.012) goes to colour 0, which is closer; colour 1 still pairs with 0.049
    ia, ib = associate(np.array([0.0, 0.030]), np.array([0.012, 0.049]), 0.02)
    assert ia.tolist() == [0, 1] and ib.tolist() == [0, 1]
    root = make_tum(tmp_path, n=2).root  # the reader on those stamps (relisting its two colour and depth images)
    rgb = [ln.split()[1] for ln in (root / "rgb.txt").read_text().splitlines()[1:3]]
    dep = [ln.split()[1] for ln in (root / "depth.txt").read_text().splitlines()[1:3]]
    (root / "rgb.txt").write_text(f"0.000 {rgb[0]}\n0.030 {rgb[1]}\n")
    (root / "depth.txt").write_text(f"0.012 {dep[0]}\n0.049 {dep[1]}\n")
    ds = open_folder(root, DataConfig(intrinsics=[20, 20, 16, 12]))
    assert len(ds) == 2 and ds.dropped_unpaired == 0 and [p.name for p in ds._depth] == [Path(d).name for d in dep]


def test_7scenes_subfolder_intrinsics_and_65535(tmp_path):
    lay = make_7scenes(tmp_path, numbers=[0, 1, 116])
    ds = open_folder(lay.root)
    assert ds.frame_dir.name == "seq-01"
    assert (ds.intrinsics.fx, ds.intrinsics.cx, ds.intrinsics.cy) == (30.5, 16.25, 12.5)
    f = ds[2]
    assert f.depth[2, 3] == 0.0  # 65535 = no measurement
    assert f.timestamp == pytest.approx(116 / 30) and f.meta["frame_id"] == 116


def test_7scenes_several_sequences_need_choice(tmp_path):
    lay = make_7scenes(tmp_path, sub="seq-01")
    make_7scenes(tmp_path, n=2, sub="seq-02")
    with pytest.raises(DataError, match="seq-01, seq-02"):
        open_folder(lay.root)
    assert len(open_folder(lay.root, DataConfig(sevenscenes=SevenScenesConfig(sequence="seq-02")))) == 2


def test_frames_are_read_lazily(tmp_path):
    """Opening reads no image; a file removed after opening fails only when its frame is read."""
    lay = make_7scenes(tmp_path, n=3)
    ds = open_folder(lay.root)
    victim = lay.root / "seq-01" / "frame-000002.color.png"
    victim.unlink()
    assert ds[0].rgb.shape == (H, W, 3) and ds[1].depth.shape == (H, W)
    with pytest.raises(DataError, match="frame-000002.color.png"):
        ds[2]


def test_7scenes_colour_is_resampled_into_the_depth_camera_when_its_intrinsics_are_given(tmp_path):
    lay = make_7scenes(tmp_path, n=2)  # depth camera fx = fy = 30.5, (cx, cy) = (16.25, 12.5), 32 x 24
    img = np.zeros((H, W, 3), dtype=np.uint8)
    img[:, :, 0] = (np.arange(W) * 8)[None, :]  # red rises along columns, green along rows
    img[:, :, 1] = (np.arange(H) * 10)[:, None]
    write_rgb(lay.root / "seq-01" / "frame-000001.color.png", img)
    plain = open_folder(lay.root)[1]
    ds = open_folder(lay.root, DataConfig(color_intrinsics=[20.0, 20.0, 15.5, 11.5]))
    f = ds[1]
    assert f.rgb.shape == plain.rgb.shape and f.intrinsics == plain.intrinsics and np.array_equal(f.depth, plain.depth)
    u = 15.5 + (np.arange(W) - 16.25) * 20.0 / 30.5  # the colour column each depth pixel looks at
    v = 11.5 + (np.arange(H) - 12.5) * 20.0 / 30.5
    np.testing.assert_allclose(f.rgb[5, :, 0], u * 8 / 255, atol=1e-5)
    np.testing.assert_allclose(f.rgb[:, 5, 1], v * 10 / 255, atol=1e-5)
    with pytest.raises(ConfigError, match="data.color_intrinsics"):
        open_folder(lay.root, DataConfig(color_intrinsics=[20.0, 20.0, 15.5]))
    with pytest.raises(DataError, match="data.color_intrinsics"):
        open_folder(lay.root, DataConfig(color_intrinsics=[0.0, 20.0, 15.5, 11.5]))


def test_camera_overrides_on_a_builtin_scene_are_an_error_not_ignored():
    from inrslam.datasets import open_dataset

    for key, value in (("color_intrinsics", [20.0, 20.0, 15.5, 11.5]), ("intrinsics", [20.0, 20.0, 15.5, 11.5]),
                       ("depth_scale", 1000.0)):
        with pytest.raises(ConfigError, match=f"data.{key}.*folder datasets only"):
            open_dataset(DataConfig(path="builtin:room", **{key: value}))


def test_repeated_streams_names_what_repeats_bit_for_bit(tmp_path):
    import dataclasses

    from inrslam.data.frame import repeated_streams

    ds = open_folder(make_7scenes(tmp_path, n=2).root)
    a, b = ds[0], ds[1]
    assert repeated_streams(a, b) is None
    assert repeated_streams(a, dataclasses.replace(b, rgb=a.rgb.copy())) == "colour"
    assert repeated_streams(a, dataclasses.replace(b, depth=a.depth.copy())) == "depth"
    assert repeated_streams(a, dataclasses.replace(a, index=1)) == "both"
    nudged = a.depth.copy()
    nudged[5, 5] += 1e-6  # one pixel differs: a new image
    assert repeated_streams(a, dataclasses.replace(a, depth=nudged)) == "colour"
