"""Image I/O: exact 16-bit depth, colour conversion, and DataError naming the file for unreadable input."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from inrslam.data.images import image_size, read_depth, read_depth_raw, read_rgb
from inrslam.errors import DataError


def test_depth_16bit_exact_above_32767(tmp_path):
    raw = np.array([[0, 1, 32767, 32768], [40000, 50000, 65534, 65535]], dtype=np.uint16)
    p = tmp_path / "d.png"
    Image.fromarray(raw).save(p)
    out = read_depth_raw(p)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, raw)
    m = read_depth(p, 1000.0, invalid=(65535,))
    assert m.dtype == np.float32
    assert m[1, 0] == pytest.approx(40.0) and m[1, 3] == 0.0 and m[0, 0] == 0.0


def test_depth_must_be_16bit(tmp_path):
    p = tmp_path / "d8.png"
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(p)
    with pytest.raises(DataError, match=r"d8\.png.*16-bit"):
        read_depth_raw(p)


def test_rgb_modes(tmp_path):
    rgba = np.zeros((3, 4, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 255, 7
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    out = read_rgb(tmp_path / "a.png")
    assert out.shape == (3, 4, 3) and out.dtype == np.float32
    np.testing.assert_array_equal(out[0, 0], [1.0, 0.0, 0.0])
    Image.fromarray(np.full((3, 4), 51, np.uint8)).save(tmp_path / "g.png")
    np.testing.assert_allclose(read_rgb(tmp_path / "g.png")[1, 1], [0.2, 0.2, 0.2], atol=1e-6)
    assert read_rgb(tmp_path / "a.png", size=(8, 6)).shape == (6, 8, 3)
    assert image_size(tmp_path / "a.png") == (4, 3)


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_truncated_image(tmp_path, suffix):
    p = tmp_path / f"img{suffix}"
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(p)
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    with pytest.raises(DataError, match=f"img\\{suffix}"):
        read_rgb(p)


def test_not_an_image_and_missing(tmp_path):
    p = tmp_path / "depth000001.png"
    p.write_text("not a png")
    with pytest.raises(DataError, match="depth000001.png"):
        read_depth_raw(p)
    with pytest.raises(DataError, match="nothere.jpg.*not found"):
        read_rgb(tmp_path / "nothere.jpg")
