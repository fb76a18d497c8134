"""Lost-tracking detection, recovery and stop (slam.lost) on a built-in room seen every 25th frame (16-29 cm steps)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from inrslam.config import load_config
from inrslam.datasets import open_dataset
from inrslam.errors import TrackingLost
from inrslam.slam.system import SlamSystem

BASE = ["data.max_frames=4", "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false",
        "slam.init_pixels=512"]


@functools.cache
def run(*overrides: str) -> SlamSystem:
    """A finished run with these overrides (shared by the tests, which only read it)."""
    cfg = load_config(preset="quick", overrides=BASE + list(overrides))
    return SlamSystem(cfg, open_dataset(cfg.data)).run()


def position_error(system: SlamSystem) -> np.ndarray:
    res = system.result()
    return np.linalg.norm(res.est[:, :3, 3] - res.gt[:, :3, 3], axis=1)


def test_normal_motion_is_never_flagged_lost():
    s = run()
    assert s.state.events == [] and s.state.lost_run == 0
    assert len(s.state.track_losses) == 4  # init's final loss + 3 tracked frames form the running level


def test_large_steps_are_detected_logged_and_counted():
    s = run("data.stride=25")
    lost = [e["frame"] for e in s.state.events if e["event"] == "tracking_lost"]
    assert lost == [1, 2, 3] and s.state.lost_run == 3
    assert s.result().metrics["fallbacks"] == 3 == s.result().metrics["lost_frames"]
    assert position_error(s)[1] > 0.1  # what went undetected before: the pose is far off


def test_recovery_retracks_from_wide_gicp_and_beats_no_recovery():
    lost, rec = run("data.stride=25"), run("data.stride=25", "slam.lost.recover=true")
    assert rec.state.events[0] == {"frame": 1, "event": "tracking_recovered"}
    assert position_error(rec)[1] < 0.02 < 0.1 < position_error(lost)[1]


def test_stop_after_consecutive_lost_frames_is_one_clear_error():
    with pytest.raises(TrackingLost, match=r"tracking lost for 2 consecutive frames up to frame 2 .*data.stride") as e:
        run("data.stride=25", "slam.lost.stop_after=2")
    assert "\n" not in str(e.value)


def test_detection_does_not_touch_a_run_it_does_not_fire_on():
    a, b = run(), run("slam.lost.factor=1000", "slam.lost.recover=true")
    assert np.array_equal(a.result().est, b.result().est)
