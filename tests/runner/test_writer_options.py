"""Run-writer options: a TensorBoard that was asked for but is missing is a warning, not silence."""

from __future__ import annotations

import sys

import pytest

from inrslam.config import load_config
from inrslam.errors import InrslamWarning
from inrslam.runner import run_slam

TINY = ["data.max_frames=3", "slam.poses=gt", "slam.init_iters=10", "mesh.enabled=false", "eval.enabled=false"]


def test_missing_tensorboard_warns_once_and_the_run_goes_on(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # import fails as if not installed
    with pytest.warns(InrslamWarning, match="tensorboard is not installed") as rec:
        run_slam(load_config(preset="quick", overrides=TINY + ["output.tensorboard=true"]), tmp_path / "r")
    assert len([w for w in rec if issubclass(w.category, InrslamWarning)]) == 1
    assert (tmp_path / "r" / "trajectory.txt").is_file() and not (tmp_path / "r" / "tensorboard").exists()


def test_the_cli_prints_it_as_one_line():
    import warnings

    from inrslam.cli import _one_line_warnings

    before = warnings.formatwarning
    try:
        _one_line_warnings()
        assert warnings.formatwarning("asked for X", InrslamWarning, "w.py", 3) == "inrslam: warning: asked for X\n"
        assert "w.py:3" in warnings.formatwarning("other", UserWarning, "w.py", 3)  # others keep their form
    finally:
        warnings.formatwarning = before
