"""Shared test options: device parametrisation (CUDA cases skip without a GPU) and an isolated scene cache."""

from __future__ import annotations

import os
import tempfile

import pytest
import torch

# Built-in scenes are cached per test session in a private folder (never the user's ~/.cache).
os.environ.setdefault("INRSLAM_CACHE", tempfile.mkdtemp(prefix="inrslam-test-cache-"))

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"))]


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)
