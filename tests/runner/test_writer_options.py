"""Run-writer options: a TensorBoard that was asked for but is missing is a warning, not silence."""

from __future__ import annotations

import subprocess
import sys

import pytest

from inrslam.config import load_config
from inrslam.errors import InrslamWarning
from inrslam.runner import run_slam

TINY = ["data.max_frames=3", "slam.poses=gt", "mesh.enabled=false", "eval.enabled=false"]


def test_missing_tensorboard_warns_once_and_the_run_goes_on(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # import fails as if not installed
    with pytest.warns(InrslamWarning, match="tensorboard is not installed") as rec:
        run_slam(load_config(preset="quick", overrides=TINY + ["output.tensorboard=true"]), tmp_path / "r")
    assert len([w for w in rec if issubclass(w.category, InrslamWarning)]) == 1
    assert (tmp_path / "r" / "trajectory.txt").is_file() and not (tmp_path / "r" / "tensorboard").exists()


def test_the_cli_prints_it_as_one_line(tmp_path):
    code = ("import sys; sys.modules['torch.utils.tensorboard'] = None\n"
            "from inrslam.cli import main\nsys.exit(main(sys.argv[1:]))")
    res = subprocess.run([sys.executable, "-c", code, "run", "--preset", "quick", "--out", str(tmp_path / "r"),
                          "--quiet", *TINY, "output.tensorboard=true"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    assert [line for line in res.stderr.splitlines() if "tensorboard" in line] == [
        "inrslam: warning: output.tensorboard=true but tensorboard is not installed (pip install tensorboard); "
        "this run writes no TensorBoard scalars (set output.tensorboard=false to silence this)"]
