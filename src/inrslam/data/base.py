"""Shared machinery of the folder readers: file pairing, intrinsics resolution, lazy frame reading."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import ClassVar, Iterator, Mapping, Optional, Sequence

import numpy as np

from inrslam.data.config import DataConfig
from inrslam.data.frame import Frame, Intrinsics
from inrslam.data.images import image_size, read_depth, read_rgb
from inrslam.errors import ConfigError, DataError
from inrslam.geometry.intrinsics import reproject_image


def numbered_files(folder: Path, pattern: str) -> dict[int, Path]:
    """Files in `folder` whose name fully matches regex `pattern` (one group = the frame number) -> {number: path}."""
    rx = re.compile(pattern)
    out: dict[int, Path] = {}
    if not folder.is_dir():
        return out
    for p in folder.iterdir():
        m = rx.fullmatch(p.name)
        if m:
            n = int(m.group(1))
            if n in out:
                raise DataError(f"{folder}: two files for frame {n}: {out[n].name} and {p.name}")
            out[n] = p
    return out


def pair_numbered(colour: dict[int, Path], depth: dict[int, Path], colour_glob: str, depth_glob: str) -> list[int]:
    """Sorted frame numbers present in both maps; raise DataError naming a file without its counterpart."""
    if not colour:
        raise DataError(f"no colour images found (expected {colour_glob})")
    if not depth:
        raise DataError(f"no depth images found (expected {depth_glob})")
    only_c = sorted(set(colour) - set(depth))
    only_d = sorted(set(depth) - set(colour))
    if only_c or only_d:
        example = colour[only_c[0]] if only_c else depth[only_d[0]]
        kind = "depth" if only_c else "colour"
        raise DataError(
            f"count mismatch: {len(colour)} colour images ({colour_glob}) vs {len(depth)} depth images "
            f"({depth_glob}); {example} has no matching {kind} image"
        )
    return sorted(colour)


def check_count(n_frames: int, n_poses: int, pose_file: Path | str) -> None:
    """Raise DataError unless there is exactly one pose per frame."""
    if n_frames != n_poses:
        raise DataError(
            f"{pose_file}: count mismatch: {n_poses} poses for {n_frames} colour/depth frames (expected one per frame)"
        )


class FolderDataset:
    """Base of the folder readers (an `RGBDDataset`). Subclasses implement `detect` and `_scan`.

    `_scan` fills: `_rgb`, `_depth` (lists of paths), `_c2w` (N, 4, 4) OpenCV camera-to-world (NaN if invalid),
    `_valid` (N,) bool, `_timestamps` (N,) seconds, `_ids` (N,) frame numbers in the files, and returns the default
    intrinsics (or None when the size comes from the images).
    """

    name: ClassVar[str] = "folder"
    layout: ClassVar[str] = ""  # human-readable list of the files the reader expects (for error messages)
    fps: ClassVar[float] = 30.0
    default_depth_scale: ClassVar[float] = 1000.0
    invalid_depth: ClassVar[tuple[int, ...]] = ()  # raw depth values meaning "no measurement" besides 0
    resize_colour: ClassVar[bool] = False  # True: colour is resized to the depth size (ScanNet)
    floors_intrinsics: ClassVar[bool] = True  # the original code floor-divided this layout's intrinsics (faithful mode)

    root: Path
    intrinsics: Intrinsics
    bounds: Optional[np.ndarray]
    gt_mesh: Optional[Path]

    def __init__(self, root: str | os.PathLike, cfg: DataConfig | None = None):
        self.root = Path(root)
        self.cfg = cfg if cfg is not None else DataConfig(path=str(root))
        if not self.root.is_dir():
            raise DataError(f"{self.root}: dataset folder not found (expected {self.layout})")
        self.depth_scale = float(self.cfg.depth_scale) if self.cfg.depth_scale is not None else self.default_depth_scale
        if not self.depth_scale > 0:
            raise ConfigError(f"data.depth_scale: must be > 0, got {self.cfg.depth_scale}")
        self.bounds = None
        self.gt_mesh = None
        self._rgb: list[Path] = []
        self._depth: list[Path] = []
        self._ids = np.zeros(0, dtype=np.int64)
        default = self._scan()
        if not self._rgb:
            raise DataError(f"{self.root}: no frames found (expected {self.layout})")
        if not (len(self._rgb) == len(self._depth) == len(self._c2w) == len(self._valid) == len(self._timestamps)):
            raise AssertionError("reader produced inconsistent per-frame lists")  # programming error, not user input
        self.intrinsics = self._resolve_intrinsics(default)
        self.colour_intrinsics = self._resolve_colour_intrinsics()

    # --- to implement -------------------------------------------------------------------------------------------
    @classmethod
    def detect(cls, root: Path) -> bool:
        """True if `root` looks like this layout (cheap: names only, no file reading)."""
        raise NotImplementedError

    def _scan(self) -> Optional[Intrinsics]:
        raise NotImplementedError

    # --- shared -------------------------------------------------------------------------------------------------
    def _set_numbered_frames(
        self,
        colour: dict[int, Path],
        depth: dict[int, Path],
        ids: Sequence[int],
        poses: Sequence[tuple[np.ndarray, bool]],
        time_from_number: bool,
    ) -> None:
        """Fill the per-frame lists of a layout whose files carry frame numbers (see `pair_numbered`).

        Args:
            colour, depth: {frame number: path}, as from `numbered_files`.
            ids: the paired frame numbers, sorted.
            poses: one (c2w (4, 4), valid) per frame of `ids`, as from `check_pose`.
            time_from_number: True: timestamp = frame number / fps (the numbers are frame indices of the
                capture, gaps included); False: timestamp = position in the sequence / fps.
        """
        self._rgb = [colour[n] for n in ids]
        self._depth = [depth[n] for n in ids]
        self._ids = np.array(ids, dtype=np.int64)
        self._c2w = np.stack([T for T, _ in poses])
        self._valid = np.array([ok for _, ok in poses])
        if time_from_number:
            self._timestamps = np.asarray(ids, dtype=np.float64) / self.fps
        else:
            self._timestamps = np.arange(len(ids), dtype=np.float64) / self.fps

    def _resolve_intrinsics(self, default: Optional[Intrinsics]) -> Intrinsics:
        """Override [fx, fy, cx, cy] or the layout default; image size from the first depth image header."""
        width, height = image_size(self._depth[0])
        if self.cfg.intrinsics is not None:
            vals = list(self.cfg.intrinsics)
            if len(vals) != 4:
                raise ConfigError(f"data.intrinsics: expected [fx, fy, cx, cy], got {vals}")
            fx, fy, cx, cy = (float(v) for v in vals)
            return Intrinsics(fx, fy, cx, cy, width, height).checked("data.intrinsics")
        if default is None:
            raise DataError(f"{self.root}: no intrinsics found and data.intrinsics not set")
        default.checked(f"{self.root}: the {self.name} camera parameters")
        if self.cfg.faithful_intrinsics and self.floors_intrinsics:
            fl = math.floor
            d = default
            default = Intrinsics(fl(d.fx), fl(d.fy), fl(d.cx), fl(d.cy), d.width, d.height)
        if (default.width, default.height) != (width, height):
            raise DataError(
                f"{self._depth[0]}: image is {width}x{height} but the {self.name} intrinsics are for "
                f"{default.width}x{default.height}; set data.intrinsics = [fx, fy, cx, cy] for this size"
            )
        return default

    def _resolve_colour_intrinsics(self) -> Optional[Intrinsics]:
        """`data.color_intrinsics` for the colour files' size, or None (colour shares the depth intrinsics)."""
        vals = self.cfg.color_intrinsics
        if vals is None:
            return None
        if len(vals) != 4:
            raise ConfigError(f"data.color_intrinsics: expected [fx, fy, cx, cy], got {list(vals)}")
        width, height = image_size(self._rgb[0])
        fx, fy, cx, cy = (float(v) for v in vals)
        return Intrinsics(fx, fy, cx, cy, width, height).checked("data.color_intrinsics")

    def __len__(self) -> int:
        return len(self._rgb)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) float64 ground-truth camera-to-world (OpenCV axes), all-NaN where invalid (no image reads)."""
        return self._c2w.copy()

    @property
    def pose_valid(self) -> np.ndarray:
        """(N,) bool: ground-truth pose known."""
        return self._valid.copy()

    @property
    def timestamps(self) -> np.ndarray:
        """(N,) float64 seconds."""
        return self._timestamps.copy()

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames")
        rgb_path, depth_path = self._rgb[i], self._depth[i]
        depth = read_depth(depth_path, self.depth_scale, self.invalid_depth)
        H, W = depth.shape
        intr = self.intrinsics
        if (W, H) != (intr.width, intr.height):
            raise DataError(
                f"{depth_path}: frame {i}: depth is {W}x{H}, expected {intr.width}x{intr.height} like the first frame"
            )
        ci = self.colour_intrinsics
        rgb = read_rgb(rgb_path, size=(W, H) if self.resize_colour and ci is None else None)
        if ci is not None:  # colour resampled into the depth camera
            if rgb.shape[:2] != (ci.height, ci.width):
                raise DataError(f"{rgb_path}: frame {i}: colour is {rgb.shape[1]}x{rgb.shape[0]}, expected "
                                f"{ci.width}x{ci.height} like the first frame (data.color_intrinsics)")
            rgb = reproject_image(rgb, ci, intr)
        if rgb.shape[:2] != (H, W):
            raise DataError(
                f"{rgb_path}: frame {i}: colour is {rgb.shape[1]}x{rgb.shape[0]} but depth {depth_path.name} "
                f"is {W}x{H} (expected the same size)"
            )
        return Frame(
            index=i,
            timestamp=float(self._timestamps[i]),
            rgb=rgb,
            depth=depth,
            intrinsics=intr,
            c2w=self._c2w[i].copy(),
            pose_valid=bool(self._valid[i]),
            source=str(rgb_path),
            meta={"depth_file": str(depth_path), "frame_id": int(self._ids[i])},
        )

    def __repr__(self) -> str:
        return f"{type(self).__name__}(root={str(self.root)!r}, frames={len(self)}, intrinsics={self.intrinsics})"


def checked_depth_scale(value: float, source: str) -> float:
    """A depth scale (stored units per metre) read from a dataset's own file, or a `DataError` naming `source` unless
    it is finite and > 0. Example: Replica's cam_params.json scale 6553.5 -> 6553.5."""
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise DataError(f"{source}: depth scale must be a finite number > 0 (units per metre), got {value}")
    return v


def known_bounds(table: Mapping[str, Sequence[Sequence[float]]], name: str) -> Optional[np.ndarray]:
    """(3, 2) bounds from `table` when the folder `name` is a key, else None."""
    b = table.get(name)
    return None if b is None else np.array(b, dtype=np.float64)


def read_camera_json(path: Path, section: Optional[str] = None) -> dict[str, float]:
    """Camera parameters from a JSON file (`cam_params.json` of Replica, `intrinsics.json` of our TUM exports).

    Returns the numeric entries of the top level (or of `section`), e.g. fx, fy, cx, cy, w/width, h/height, scale.
    """
    try:
        data = json.loads(path.read_text())
        if section is not None:
            data = data[section]
        out = {k: float(v) for k, v in data.items() if isinstance(v, (int, float))}
        bad = [k for k, v in out.items() if not math.isfinite(v)]
        if bad:
            raise ValueError(f"{', '.join(bad)} not a finite number")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise DataError(f"{path}: cannot read camera parameters ({type(e).__name__}: {e})") from None
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in out]
    if missing:
        raise DataError(f"{path}: missing camera parameters {missing} (expected fx, fy, cx, cy)")
    return out


def require_dir(path: Path, layout: str) -> None:
    """Raise DataError naming `path` unless it is a folder."""
    if not path.is_dir():
        raise DataError(f"{path}: folder not found (expected {layout})")


def first_existing(paths: Sequence[Path]) -> Optional[Path]:
    """The first path that is a file, or None."""
    for p in paths:
        if p.is_file():
            return p
    return None
