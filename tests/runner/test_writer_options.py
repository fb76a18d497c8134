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


def test_held_out_pictures_go_to_tensorboard_too(tmp_path):
    pytest.importorskip("tensorboard", reason="tensorboard not installed (the [tensorboard] extra)")
    from tensorboard.backend.event_processing.event_accumulator import IMAGES, EventAccumulator

    cfg = load_config(preset="quick", overrides=["data.max_frames=3", "slam.poses=gt", "slam.init_iters=10",
                                                 "mesh.enabled=false", "eval.heldout_every=2",
                                                 "data.builtin.width=64", "data.builtin.height=48",
                                                 "output.tensorboard=true"])
    run_slam(cfg, tmp_path / "r")
    renders = sorted(p.stem for p in (tmp_path / "r" / "renders").glob("*.png"))
    acc = EventAccumulator(str(tmp_path / "r" / "tensorboard"), size_guidance={IMAGES: 0}).Reload()
    tags = sorted(acc.Tags()[IMAGES])
    assert tags and tags == [f"heldout/{name}" for name in renders]  # one picture per held-out frame
    img = acc.Images(tags[0])[0]
    assert img.step == 2 and (img.width, img.height) == (4 * 64, 48)  # observed | render | depth | error
