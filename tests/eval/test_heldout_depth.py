"""Held-out depth against the noise-free depth of the built-in scenes (`depth_l1_true_m`), and the choice of the
rendered depth (`eval.heldout_depth`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from inrslam.config import load_config
from inrslam.data.view import DatasetView
from inrslam.datasets import open_dataset
from inrslam.eval.config import EvalConfig, HeldoutDepth
from inrslam.eval.heldout import heldout_metrics
from inrslam.geometry.intrinsics import Intrinsics

H, W = 12, 16
INTR = Intrinsics(fx=10.0, fy=10.0, cx=8.0, cy=6.0, width=W, height=H)


@dataclass
class _Frame:
    rgb: np.ndarray
    depth: np.ndarray
    intrinsics: Intrinsics = INTR


class _Noisy:
    """Frames whose observed depth is 2 m + 3 cm of 'noise' (holes in the first row); the truth is 2 m."""

    def __len__(self):
        return 4

    def __getitem__(self, i):
        d = np.full((H, W), 2.03, np.float32)
        d[0] = 0.0
        return _Frame(np.full((H, W, 3), 0.5, np.float32), d)


class _NoisyWithTruth(_Noisy):
    def true_depth(self, i):
        return np.full((H, W), 2.0, np.float32)


def _render(c2w, intr):  # a perfect map: the true surface at 2 m, the right colour
    return np.full((H, W, 3), 0.5, np.float32), np.full((H, W), 2.0, np.float32)


def test_true_depth_l1_is_reported_only_where_the_dataset_knows_the_truth():
    poses = [np.eye(4)] * 4
    with_truth = heldout_metrics(_render, _NoisyWithTruth(), poses, every=1, max_frames=4)
    assert with_truth["depth_l1_m"] == pytest.approx(0.03, abs=1e-6)  # the observation's noise, holes ignored
    assert with_truth["depth_l1_true_m"] == pytest.approx(0.0, abs=1e-7)  # the map is exact
    assert "depth_l1_true_m" not in heldout_metrics(_render, _Noisy(), poses, every=1, max_frames=4)


def test_builtin_true_depth_is_the_depth_before_the_sensor_model_through_the_view():
    cfg = load_config(preset="paper", overrides=["data.path=builtin:handheld", "data.max_frames=3",
                                                 "data.start=1", "data.builtin.width=96", "data.builtin.height=72"])
    ds = open_dataset(cfg.data)
    assert isinstance(ds, DatasetView)
    true, observed = ds.true_depth(0), ds[0].depth
    assert np.array_equal(true, ds.base.depth(1, clean=True))  # view index 0 = scene frame 1
    assert (true > 0).all() and (observed == 0).any()  # holes are a sensor effect
    both = (observed > 0)
    rel = (observed[both] - true[both]) / true[both] ** 2  # noise s z^2 with s = 4 mm at 1 m
    assert 0.002 < float(np.std(rel)) < 0.006
    with pytest.raises(IndexError):
        ds.true_depth(3)


def test_heldout_depth_setting_is_validated():
    assert EvalConfig().heldout_depth is HeldoutDepth.EXPECTED  # the benchmark's weighted mean by default
    cfg = load_config(preset="accurate")
    assert HeldoutDepth(cfg.eval.heldout_depth) is HeldoutDepth.SURFACE
    with pytest.raises(Exception, match="heldout_depth"):
        load_config(preset="paper", overrides=["eval.heldout_depth=median"])


def test_heldout_frames_spread_over_the_whole_sequence():
    from inrslam.eval.heldout import heldout_frames

    short = heldout_frames(200, 10, 20, offset=2)
    assert short == list(range(2, 200, 10))  # 20 candidates: all of them
    picked = heldout_frames(320, 10, 20, offset=2)
    assert len(picked) == 20 and picked[0] == 2 and picked[-1] == 312  # the first and the last candidate ...
    assert all(f % 10 == 2 for f in picked) and picked == sorted(set(picked))  # ... and only candidates
    gaps = np.diff(picked)
    assert gaps.min() >= 10 and gaps.max() <= 20  # evenly between: 31 steps of 10 over 19 gaps
    assert heldout_frames(400, 10, 5, offset=2) == [2, 102, 202, 292, 392]
    assert heldout_frames(320, 10, 1, offset=2) == [2]
    assert heldout_frames(320, 10, 0) == [] and heldout_frames(0, 10, 20) == [] and heldout_frames(5, 0, 20) == []
    assert heldout_frames(5, 10, 20, offset=8) == [4]  # the offset clipped to the last frame
