"""Every kind of bad input gives a DataError naming the file (and line / frame) and what was expected.

Structural problems (counts, pose-file format) fail at open time; a broken image fails when its frame is read.
"""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest
from data_layouts import make_7scenes, make_neuralrgbd, make_replica, make_scannet, make_tum, write_png16, write_rgb

from inrslam.data import DataConfig, open_folder
from inrslam.errors import DataError

K = DataConfig(intrinsics=[20.0, 20.0, 16.0, 12.0])


def _rewrite(path, old, new):
    path.write_text(path.read_text().replace(old, new, 1))


def _drop_line(path, k):
    lines = path.read_text().splitlines()
    del lines[k]
    path.write_text("\n".join(lines) + "\n")


def _replica_15_values(r):
    lines = (r / "traj.txt").read_text().splitlines()
    lines[1] = " ".join(lines[1].split()[:15])
    (r / "traj.txt").write_text("\n".join(lines) + "\n")


CAMERA = {"w": 32, "h": 24, "fx": 20.0, "fy": 20.0, "cx": 16.0, "cy": 12.0, "scale": 6553.5}


def _replica_comment_then_nonrigid(r):
    lines = (r / "traj.txt").read_text().splitlines()
    vals = lines[1].split()
    vals[15] = "2"  # bottom row [0, 0, 0, 2], on line 4 of the file below
    (r / "traj.txt").write_text("\n".join(["# c2w, row-major", "", lines[0], " ".join(vals), lines[2]]) + "\n")


def _huge_png_header(path):
    """Rewrite a PNG's size in its IHDR chunk to 20000 x 20000 (CRC recomputed): a decompression bomb's header."""
    data = bytearray(path.read_bytes())
    data[16:24] = struct.pack(">II", 20000, 20000)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    path.write_bytes(bytes(data))


def _replica_nonrigid(r):
    lines = (r / "traj.txt").read_text().splitlines()
    vals = lines[1].split()
    vals[12] = "0.5"  # bottom row [0.5, 0, 0, 1]
    lines[1] = " ".join(vals)
    (r / "traj.txt").write_text("\n".join(lines) + "\n")


# (name, maker, mutate(root), cfg, regex the message must match) — all fail when the dataset is opened
OPEN_CASES = [
    ("replica: traj.txt missing", make_replica, lambda r: (r / "traj.txt").unlink(), DataConfig(dataset="replica"),
     r"traj\.txt"),
    ("replica: one pose too few", make_replica, lambda r: _drop_line(r / "traj.txt", 2), K,
     r"traj\.txt: count mismatch: 2 poses for 3"),
    ("replica: 15 values on a line", make_replica, _replica_15_values, K, r"traj\.txt:2: expected 16 values"),
    ("replica: depth missing for a frame", make_replica, lambda r: (r / "results" / "depth000001.png").unlink(), K,
     r"frame000001\.jpg has no matching depth"),
    ("replica: non-rigid pose", make_replica, _replica_nonrigid, K, r"traj\.txt:2: pose bottom row"),
    ("neuralrgbd: non-numeric pose value", make_neuralrgbd, lambda r: _rewrite(r / "poses.txt", "0.2", "abc"), K,
     r"poses\.txt:\d+: non-numeric"),
    ("neuralrgbd: line count not a multiple of 4", make_neuralrgbd, lambda r: _drop_line(r / "poses.txt", 5), K,
     r"poses\.txt: expected 4 lines of 4 values per pose"),
    ("neuralrgbd: extra image", make_neuralrgbd,
     lambda r: (write_rgb(r / "images" / "img3.png", np.zeros((24, 32, 3))),
                write_png16(r / "depth_filtered" / "depth3.png", np.ones((24, 32)))), K,
     r"poses\.txt: count mismatch: 3 poses for 4"),
    ("neuralrgbd: depth_filtered missing", make_neuralrgbd,
     lambda r: [p.unlink() for p in (r / "depth_filtered").iterdir()] and (r / "depth_filtered").rmdir(), K,
     r"depth_filtered: folder not found"),
    ("scannet: pose file with 3 lines", make_scannet, lambda r: _drop_line(r / "pose" / "1.txt", 3), None,
     r"pose/1\.txt: expected 4 lines"),
    ("scannet: pose file missing", make_scannet, lambda r: (r / "pose" / "1.txt").unlink(), None,
     r"pose/1\.txt: pose file missing for frame 1 \(2 pose files for 3"),
    ("scannet: extra pose file", make_scannet, lambda r: (r / "pose" / "7.txt").write_text((r / "pose" / "0.txt").read_text()),
     None, r"pose: count mismatch: 4 poses for 3"),
    ("scannet: intrinsics missing", make_scannet, lambda r: (r / "intrinsic" / "intrinsic_depth.txt").unlink(), None,
     r"intrinsic_depth\.txt: intrinsics file not found"),
    ("tum: listed image missing", make_tum, lambda r: next((r / "depth").iterdir()).unlink(), K,
     r"depth/[\d.]+\.png: image listed in depth\.txt not found"),
    ("tum: groundtruth line with 7 values", make_tum, lambda r: _rewrite(r / "groundtruth.txt", " 0.2 ", " "), K,
     r"groundtruth\.txt:2: expected 8 values"),
    ("tum: rgb.txt line without file name", make_tum,
     lambda r: (r / "rgb.txt").write_text("# c\n1305031102.0\n"), K, r"rgb\.txt:2: expected 'timestamp filename'"),
    ("7scenes: pose with 3 values on a line", make_7scenes,
     lambda r: (r / "seq-01" / "frame-000001.pose.txt").write_text("1 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"), None,
     r"frame-000001\.pose\.txt:1: expected 4 values"),
    ("7scenes: pose file missing", make_7scenes, lambda r: (r / "seq-01" / "frame-000002.pose.txt").unlink(), None,
     r"frame-000002\.pose\.txt: count mismatch: 2 pose files for 3"),
    ("7scenes: bad intrinsics file", make_7scenes, lambda r: (r / "camera-intrinsics.txt").write_text("585 0 320\n"),
     None, r"camera-intrinsics\.txt: expected 3 lines"),
    ("replica: error line counted with comments", make_replica, _replica_comment_then_nonrigid, K,
     r"traj\.txt:4: pose bottom row"),
    ("replica: zero depth scale in cam_params.json", make_replica,
     lambda r: (r / "cam_params.json").write_text(json.dumps({"camera": CAMERA | {"scale": 0}})), DataConfig(),
     r"cam_params\.json: camera\.scale: depth scale must be a finite number > 0"),
    ("replica: negative depth scale in cam_params.json", make_replica,
     lambda r: (r / "cam_params.json").write_text(json.dumps({"camera": CAMERA | {"scale": -6553.5}})), DataConfig(),
     r"cam_params\.json: camera\.scale: depth scale must be a finite number > 0 .*, got -6553\.5"),
    ("tum: zero depth scale in intrinsics.json", make_tum,
     lambda r: (r / "intrinsics.json").write_text(json.dumps({"fx": 20, "fy": 20, "cx": 16, "cy": 12, "width": 32,
                                                               "height": 24, "depth_scale": 0})), DataConfig(),
     r"intrinsics\.json: depth_scale: depth scale must be a finite number > 0"),
    ("replica: depth header of 20000 x 20000 px", make_replica,
     lambda r: _huge_png_header(r / "results" / "depth000000.png"), K,
     r"depth000000\.png: cannot read image header \(DecompressionBombError"),
]


@pytest.mark.parametrize("case", OPEN_CASES, ids=[c[0] for c in OPEN_CASES])
def test_bad_input_at_open(tmp_path, case):
    _, maker, mutate, cfg, pattern = case
    lay = maker(tmp_path)
    mutate(lay.root)
    with pytest.raises(DataError, match=pattern):
        open_folder(lay.root, cfg)


def test_truncated_depth_fails_when_read(tmp_path):
    lay = make_replica(tmp_path)
    p = lay.root / "results" / "depth000001.png"
    p.write_bytes(p.read_bytes()[:60])
    ds = open_folder(lay.root, K)  # structural checks pass
    ds[0]
    with pytest.raises(DataError, match=r"depth000001\.png: cannot read depth image"):
        ds[1]


def test_colour_depth_size_mismatch(tmp_path):
    lay = make_7scenes(tmp_path)
    write_rgb(lay.root / "seq-01" / "frame-000001.color.png", np.zeros((12, 16, 3)))
    ds = open_folder(lay.root)
    with pytest.raises(DataError, match=r"frame-000001\.color\.png: frame 1: colour is 16x12 but depth .* is 32x24"):
        ds[1]


def test_depth_size_differs_from_first_frame(tmp_path):
    lay = make_scannet(tmp_path)
    write_png16(lay.root / "depth" / "2.png", np.ones((12, 16)))
    ds = open_folder(lay.root)
    with pytest.raises(DataError, match=r"depth/2\.png: frame 2: depth is 16x12, expected 32x24"):
        ds[2]


def test_8bit_depth_named(tmp_path):
    lay = make_neuralrgbd(tmp_path)
    write_rgb(lay.root / "depth_filtered" / "depth2.png", np.zeros((24, 32, 3)))
    with pytest.raises(DataError, match=r"depth2\.png: expected a 16-bit single-channel depth PNG"):
        open_folder(lay.root, K)[2]


def test_non_finite_poses_are_not_errors(tmp_path):
    lay = make_7scenes(tmp_path)
    (lay.root / "seq-01" / "frame-000001.pose.txt").write_text("\n".join(["-inf -inf -inf -inf"] * 4) + "\n")
    ds = open_folder(lay.root)
    assert list(ds.pose_valid) == [True, False, True]
    assert np.all(np.isnan(ds[1].c2w))


def test_tum_quaternion_of_huge_components_is_a_rotation(tmp_path):
    lay = make_tum(tmp_path)
    lines = (lay.root / "groundtruth.txt").read_text().splitlines()
    ts, *xyz = lines[1].split()[:4]
    lines[1] = " ".join([ts, *xyz, "0", "0", "0", "1e300"])  # finite, but its norm overflows
    (lay.root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    ds = open_folder(lay.root, K)
    np.testing.assert_allclose(ds.poses[0][:3, :3], np.eye(3))
    lines[1] = " ".join([ts, *xyz, "0", "0", "0", "0"])
    (lay.root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"groundtruth\.txt:2: zero quaternion"):
        open_folder(lay.root, K)


def test_16bit_image_as_colour_named(tmp_path):
    lay = make_neuralrgbd(tmp_path)
    write_png16(lay.root / "images" / "img2.png", np.full((24, 32), 30000))
    with pytest.raises(DataError, match=r"img2\.png: colour image has I;16 pixels \(16/32-bit: a depth image\?\)"):
        open_folder(lay.root, K)[2]
