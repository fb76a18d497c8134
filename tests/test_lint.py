"""ruff and mypy (settings in pyproject.toml) over the packages held to them; part of the test suite so CI runs
them."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import inrslam

LINTED = ["slam", "rendering", "config", "io", "viewer", "fields", "geometry", "eval", "data"]


def test_ruff_is_clean_on_the_linted_packages():
    ruff = shutil.which("ruff") or shutil.which("ruff", path=str(Path(sys.executable).parent))
    if ruff is None:
        pytest.skip("ruff is not installed (pip install -e '.[test]')")
    src = Path(inrslam.__file__).parent
    root = src.parent.parent  # the checkout, where pyproject.toml holds the rules
    if not (root / "pyproject.toml").is_file():
        pytest.skip("not a source checkout (no pyproject.toml beside src/)")
    res = subprocess.run([ruff, "check", "--output-format", "concise", *[str(src / p) for p in LINTED]],
                         cwd=root, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_mypy_is_clean_on_the_linted_packages():
    pytest.importorskip("mypy", reason="mypy is not installed (pip install -e '.[test]')")
    src = Path(inrslam.__file__).parent
    root = src.parent.parent
    if not (root / "pyproject.toml").is_file():
        pytest.skip("not a source checkout (no pyproject.toml beside src/)")
    res = subprocess.run([sys.executable, "-m", "mypy", "--no-error-summary", *[str(src / p) for p in LINTED]],
                         cwd=root, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
