"""The frame and dataset protocol every reader implements.

Conventions (written once, converted at the reader boundary):
- poses are camera-to-world 4x4 (float64) in **OpenCV camera axes** (x right, y down, z forward), metres;
- RGB is float32 in [0, 1], shape (H, W, 3);
- depth is float32 metres, shape (H, W), 0 = invalid (`checked_frame` reads NaN / inf as 0);
- pixel (u, v) = (column, row) with integer coordinates at pixel centres (the usual K convention).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator, Optional, Protocol, runtime_checkable

import numpy as np

from inrslam.errors import DataError
from inrslam.geometry.intrinsics import Intrinsics  # re-exported: readers build frames with it


@dataclass
class Frame:
    """One RGB-D frame.

    Attributes:
        index: position in the (possibly subsampled) sequence, 0-based.
        timestamp: seconds (index / fps when the dataset has none).
        rgb: (H, W, 3) float32 in [0, 1].
        depth: (H, W) float32 metres, 0 = invalid.
        intrinsics: camera intrinsics of `rgb`/`depth` (same size).
        c2w: (4, 4) float64 ground-truth camera-to-world, OpenCV axes; all-NaN when unknown.
        pose_valid: False when the ground-truth pose is missing or non-finite.
        source: file the frame came from (for error messages), if any.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    intrinsics: Intrinsics
    c2w: np.ndarray
    pose_valid: bool = True
    source: Optional[str] = None
    meta: dict = field(default_factory=dict)


@runtime_checkable
class RGBDDataset(Protocol):
    """What every reader provides. Frames are read lazily (streamed), never all at once.

    Attributes:
        name: dataset kind ("replica", "tum", ...).
        root: folder it reads from.
        intrinsics: intrinsics of the frames it yields.
        bounds: (3, 2) float64 scene box [[xmin, xmax], [ymin, ymax], [zmin, zmax]] in metres, or None if unknown
            (then estimated with `inrslam.data.bounds.estimate_bounds`).
        gt_mesh: path to a ground-truth mesh, or None.
    """

    name: str
    root: Path
    intrinsics: Intrinsics
    bounds: Optional[np.ndarray]
    gt_mesh: Optional[Path]

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Frame: ...

    def __iter__(self) -> Iterator[Frame]: ...


NAN_POSE = np.full((4, 4), np.nan)


def checked_frame(frame: Frame, intrinsics: Intrinsics) -> Frame:
    """`frame` held to the frame contract for a dataset of `intrinsics`: rgb (H, W, 3) and finite, depth (H, W);
    NaN / inf depth (the "no depth" of float-depth formats) becomes 0. `frame` itself when nothing needs changing.

    Raises:
        DataError naming the frame's source (or index) and what was expected.
    """
    H, W = intrinsics.height, intrinsics.width
    where = frame.source or f"frame {frame.index}"
    rgb, depth = np.asarray(frame.rgb), np.asarray(frame.depth)
    if rgb.shape != (H, W, 3):
        raise DataError(f"{where}: colour image of shape {rgb.shape}, expected ({H}, {W}, 3) as the intrinsics say")
    if depth.shape != (H, W):
        raise DataError(f"{where}: depth image of shape {depth.shape}, expected ({H}, {W}) as the intrinsics say")
    if not np.isfinite(rgb).all():
        raise DataError(f"{where}: colour image holds NaN or inf values; expected colours in [0, 1]")
    finite = np.isfinite(depth)
    if finite.all():
        return frame
    return replace(frame, depth=np.where(finite, depth, 0).astype(np.float32))


def repeated_streams(prev: Frame, cur: Frame) -> str | None:
    """"colour", "depth" or "both" when `cur`'s colour / depth is bit-identical to `prev`'s: a dropped sensor frame
    that the recorder repeated (7-Scenes has them every few frames in places), so that `cur`'s colour and depth were
    taken at different times; None when both are new."""
    same = [name for name, a, b in (("colour", prev.rgb, cur.rgb), ("depth", prev.depth, cur.depth))
            if np.array_equal(a, b)]
    return None if not same else same[0] if len(same) == 1 else "both"
