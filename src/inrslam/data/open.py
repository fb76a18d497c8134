"""`open_folder`: a dataset folder -> its reader (named or detected layout). Built-in scenes and the selection /
bounds steps are added above both data and scenes, by `inrslam.datasets.open_dataset`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from inrslam.data.config import DataConfig
from inrslam.data.detect import detect_layout
from inrslam.data.frame import RGBDDataset
from inrslam.data.registry import DATASETS
from inrslam.errors import ConfigError, DataError

BUILTIN_PREFIX = "builtin:"


def _config_bounds(b: Optional[list[list[float]]]) -> Optional[np.ndarray]:
    if b is None:
        return None
    try:
        arr = np.array(b, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"data.bounds: expected [[xmin, xmax], [ymin, ymax], [zmin, zmax]], got {b!r}") from None
    if arr.shape != (3, 2) or not np.all(np.isfinite(arr)) or np.any(arr[:, 0] >= arr[:, 1]):
        raise ConfigError(f"data.bounds: expected [[xmin, xmax], [ymin, ymax], [zmin, zmax]] with min < max, got {b!r}")
    return arr


def open_folder(root: str | Path, cfg: DataConfig | None = None) -> RGBDDataset:
    """The reader of folder `root`: `cfg.dataset` if set, else the detected layout (no selection / bounds)."""
    cfg = cfg if cfg is not None else DataConfig(path=str(root))
    root = Path(root).expanduser()
    if not root.is_dir():
        raise DataError(f"{root}: dataset folder not found (data.path)")
    kind = cfg.dataset
    if kind == "auto":
        kind = detect_layout(root)
    elif kind not in DATASETS:
        raise ConfigError(f"data.dataset: {DATASETS.unknown_message(kind)}, or 'auto'")
    return DATASETS.get(kind)(root, cfg)
