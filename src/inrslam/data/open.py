"""`open_dataset`: a `DataConfig` -> a ready `RGBDDataset` (built-in scene or folder, selection, overrides, bounds)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from inrslam.data.bounds import estimate_bounds
from inrslam.data.config import DataConfig
from inrslam.data.detect import detect_layout
from inrslam.data.frame import RGBDDataset
from inrslam.data.registry import DATASETS
from inrslam.data.view import DatasetView
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


def open_dataset(cfg: DataConfig) -> RGBDDataset:
    """Open the sequence described by `cfg`.

    `builtin:NAME` loads a procedural scene (`inrslam.scenes.load_scene`); any other path is a folder read by the
    reader named in `cfg.dataset` or the detected one. Then start / stride / max_frames, crop_edge and depth_max are
    applied lazily, and bounds come from `cfg.bounds`, else the dataset (known scene tables), else
    `estimate_bounds` over `cfg.bounds_frames` frames spread over the sequence (attribute `bounds_estimated` tells which).
    """
    bounds = _config_bounds(cfg.bounds)
    if cfg.path.startswith(BUILTIN_PREFIX):
        name = cfg.path[len(BUILTIN_PREFIX) :]
        if cfg.dataset not in ("auto", "builtin"):
            raise ConfigError(f"data.dataset={cfg.dataset!r} does not apply to data.path={cfg.path!r} (use 'auto')")
        if cfg.depth_scale is not None or cfg.intrinsics is not None:
            raise ConfigError("data.depth_scale / data.intrinsics apply to folder datasets only, not builtin scenes")
        from inrslam.scenes import load_scene

        base = load_scene(name, cfg.builtin)
    else:
        base = open_folder(cfg.path, cfg)
    view = DatasetView(base, cfg.start, cfg.stride, cfg.max_frames, cfg.crop_edge, cfg.depth_max, bounds)
    if len(view) == 0:
        raise DataError(
            f"{base.root}: no frames selected ({len(base)} frames, data.start={cfg.start}, data.stride={cfg.stride})"
        )
    view.bounds_estimated = view.bounds is None
    if view.bounds is None:
        view.bounds = estimate_bounds(view, cfg.bounds_frames, cfg.bounds_margin)
    return view
