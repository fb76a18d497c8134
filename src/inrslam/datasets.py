"""`open_dataset`: a `DataConfig` -> a ready `RGBDDataset` (built-in scene or folder, selection, overrides, bounds).

It sits above both `inrslam.data` (readers) and `inrslam.scenes` (procedural scenes, which build on data), so that
imports only go down.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from inrslam.data.bounds import estimate_bounds
from inrslam.data.config import DataConfig
from inrslam.data.frame import RGBDDataset
from inrslam.data.open import BUILTIN_PREFIX, _config_bounds, open_folder
from inrslam.data.view import DatasetView
from inrslam.errors import ConfigError, DataError
from inrslam.scenes import load_scene

__all__ = ["BUILTIN_PREFIX", "absolute_data_config", "absolute_path", "open_dataset", "open_folder"]


def absolute_path(path: str | os.PathLike) -> Path:
    """`path` with `~` expanded, made absolute against the current directory and normalised (symlinks kept)."""
    return Path(os.path.abspath(Path(path).expanduser()))


def absolute_data_config(cfg: DataConfig) -> DataConfig:
    """A copy of `cfg` whose folder path (`data.path`, its only path key) is absolute; `builtin:NAME` unchanged.

    A run records its config, so a relative path would later be read against whatever directory `--resume` or
    `eval` is started from.
    """
    if cfg.path.startswith(BUILTIN_PREFIX):
        return cfg
    return dataclasses.replace(cfg, path=str(absolute_path(cfg.path)))


def open_dataset(cfg: DataConfig) -> RGBDDataset:
    """Open the sequence described by `cfg`.

    `builtin:NAME` loads a procedural scene (`inrslam.scenes.load_scene`); any other path is a folder read by the
    reader named in `cfg.dataset` or the detected one. Then start / stride / max_frames, crop_edge and depth_max are
    applied lazily, and bounds come from `cfg.bounds`, else the dataset (known scene tables), else
    `estimate_bounds` over `cfg.bounds_frames` frames spread over the sequence (attribute `bounds_estimated` tells which).
    A folder is opened by its absolute path (relative to the current directory), so `root` and `gt_mesh` are absolute.
    """
    bounds = _config_bounds(cfg.bounds)
    if cfg.path.startswith(BUILTIN_PREFIX):
        name = cfg.path[len(BUILTIN_PREFIX) :]
        if cfg.dataset not in ("auto", "builtin"):
            raise ConfigError(f"data.dataset={cfg.dataset!r} does not apply to data.path={cfg.path!r} (use 'auto')")
        if cfg.depth_scale is not None or cfg.intrinsics is not None or cfg.color_intrinsics is not None:
            raise ConfigError("data.depth_scale / data.intrinsics / data.color_intrinsics apply to folder datasets "
                              "only, not builtin scenes")
        base = load_scene(name, cfg.builtin)
    else:
        base = open_folder(absolute_path(cfg.path), cfg)  # absolute root and GT mesh in run_info.json
    view = DatasetView(base, cfg.start, cfg.stride, cfg.max_frames, cfg.crop_edge, cfg.depth_max, bounds)
    if len(view) == 0:
        raise DataError(
            f"{base.root}: no frames selected ({len(base)} frames, data.start={cfg.start}, data.stride={cfg.stride})"
        )
    view.bounds_estimated = view.bounds is None
    if view.bounds is None:
        view.bounds = estimate_bounds(view, cfg.bounds_frames, cfg.bounds_margin)
    return view
