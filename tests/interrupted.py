"""Interrupting a SLAM run mid-way, for the resume tests: a Ctrl-C raised from the run's progress callback."""

from __future__ import annotations

import pytest

from inrslam.api import run_slam


def run_interrupted(cfg, out, frame: int) -> None:
    """`run_slam(cfg, out)` stopped by a KeyboardInterrupt when the progress callback reports frame `frame` (the
    frame in progress is saved, as after a real Ctrl-C); fails the test if the run ends without being interrupted."""

    def stop(i, n, info):
        if i == frame:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_slam(cfg, out, progress=stop)
