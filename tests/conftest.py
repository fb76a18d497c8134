"""Shared test options: device parametrisation (CUDA cases skip without a GPU) and an isolated scene cache."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile

import pytest
import torch

# Built-in scenes are cached per test session in a private folder (never the user's ~/.cache), removed at exit.
if "INRSLAM_CACHE" not in os.environ:
    _CACHE = tempfile.mkdtemp(prefix="inrslam-test-cache-")
    os.environ["INRSLAM_CACHE"] = _CACHE
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"))]


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)
