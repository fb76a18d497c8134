"""Fixtures for the reader tests (the layout builders live in data_layouts.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from data_layouts import MAKERS, SHARED, Layout


@pytest.fixture(params=sorted(MAKERS))
def layout(request, tmp_path) -> tuple[str, Layout]:
    """(reader name, fixture) for every layout."""
    return request.param, MAKERS[request.param](tmp_path)


@pytest.fixture
def shared_data() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"{SHARED} not found (real 7-Scenes / SUN3D frames; set INRSLAM_SHARED_DATA)")
    return SHARED
