"""Frames from any dataset (custom ones through the API too) are held to the frame contract before the loop uses
them: NaN / inf depth is "no depth", wrong shapes and non-finite colour are one DataError naming the frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from inrslam.config import load_config
from inrslam.data.frame import checked_frame
from inrslam.datasets import open_dataset
from inrslam.errors import DataError
from inrslam.slam.system import SlamSystem

BASE = ["data.max_frames=3", "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false",
        "slam.init_pixels=512", "data.builtin.missing_depth=0.1"]


class Edited:
    """`inner` with every frame passed through `edit(frame)`: a user's own dataset."""

    def __init__(self, inner, edit):
        self.inner, self.edit = inner, edit
        self.name, self.root, self.intrinsics = inner.name, inner.root, inner.intrinsics
        self.bounds, self.gt_mesh = inner.bounds, inner.gt_mesh

    def __len__(self):
        return len(self.inner)

    def __getitem__(self, i):
        return self.edit(self.inner[i])

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def holes_as(value: float):
    return lambda f: dataclasses.replace(f, depth=np.where(f.depth > 0, f.depth, np.float32(value)))


def test_nan_and_inf_depth_are_holes_bit_for_bit():
    cfg = load_config(preset="quick", overrides=BASE)
    ds = open_dataset(cfg.data)
    assert (ds[0].depth == 0).mean() > 0.05  # the scene has holes to mark
    ref = SlamSystem(cfg, ds).run().result().est
    nan = SlamSystem(cfg, Edited(ds, holes_as(np.nan))).run().result().est
    assert np.isfinite(ref).all() and np.array_equal(ref, nan)
    frame = holes_as(np.inf)(ds[1])
    checked = checked_frame(frame, ds.intrinsics)
    assert np.array_equal(checked.depth, ds[1].depth) and checked.depth.dtype == np.float32
    assert np.isinf(frame.depth).any()  # the input is left alone
    good = ds[1]
    assert checked_frame(good, ds.intrinsics) is good  # a frame that keeps the contract is passed through


@pytest.mark.parametrize("edit,needle", [
    (lambda f: dataclasses.replace(f, depth=f.depth[:-1]), r"depth image of shape \(\d+, \d+\), expected"),
    (lambda f: dataclasses.replace(f, rgb=f.rgb[..., :1]), r"colour image of shape .*, 3\) as the intrinsics say"),
    (lambda f: dataclasses.replace(f, rgb=np.where(f.rgb > 0.5, np.nan, f.rgb)), "holds NaN or inf"),
])
def test_bad_frames_are_one_error_naming_the_frame(edit, needle):
    cfg = load_config(preset="quick", overrides=BASE)
    ds = open_dataset(cfg.data)
    frame = edit(ds[0])
    with pytest.raises(DataError, match=needle) as e:
        checked_frame(frame, ds.intrinsics)
    assert str(e.value).startswith(frame.source or "frame 0") and "\n" not in str(e.value)
    with pytest.raises(DataError, match=needle):
        SlamSystem(cfg, Edited(ds, edit)).process(0)


def test_a_first_frame_without_depth_is_one_error_before_anything_is_fitted():
    """A colour-only initialisation seeded the lost-tracking level with a loss without depth terms, so every later
    frame was flagged lost (and stop_after blamed data.stride); now the run stops at once, saying what to do."""
    cfg = load_config(preset="quick", overrides=BASE)
    ds = open_dataset(cfg.data)
    empty = Edited(ds, lambda f: dataclasses.replace(f, depth=np.zeros_like(f.depth)) if f.index == 0 else f)
    system = SlamSystem(cfg, empty)
    with pytest.raises(DataError, match=r"the first frame has no valid depth.*data\.start=K"):
        system.process(0)
    assert system.state.next_frame == 0 and system.state.init_ms == 0
