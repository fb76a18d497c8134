"""Layout detection: which registered reader understands a folder."""

from __future__ import annotations

import os
from pathlib import Path

from inrslam.data import neuralrgbd, replica, scannet, sevenscenes, tum  # noqa: F401  (registers the readers)
from inrslam.data.registry import DATASETS
from inrslam.errors import DataError


def detect_layout(root: str | os.PathLike) -> str:
    """Name of the first registered reader whose `detect(root)` is true.

    Raises DataError listing every layout looked for when none matches.
    """
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: dataset folder not found")
    for entry in DATASETS.entries():
        if entry.obj.detect(root):
            return entry.name
    expected = "; ".join(f"{e.name}: {e.obj.layout}" for e in DATASETS.entries())
    raise DataError(
        f"{root}: unrecognised dataset layout. Looked for — {expected}. Set data.dataset to force a reader."
    )
