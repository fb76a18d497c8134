"""The frame and dataset protocol every reader implements.

Conventions (written once, converted at the reader boundary):
- poses are camera-to-world 4x4 (float64) in **OpenCV camera axes** (x right, y down, z forward), metres;
- RGB is float32 in [0, 1], shape (H, W, 3);
- depth is float32 metres, shape (H, W), 0 = invalid;
- pixel (u, v) = (column, row) with integer coordinates at pixel centres (the usual K convention).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional, Protocol, runtime_checkable

import numpy as np

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


def repeated_streams(prev: Frame, cur: Frame) -> str | None:
    """"colour", "depth" or "both" when `cur`'s colour / depth is bit-identical to `prev`'s: a dropped sensor frame
    that the recorder repeated (7-Scenes has them every few frames in places), so that `cur`'s colour and depth were
    taken at different times; None when both are new."""
    same = [name for name, a, b in (("colour", prev.rgb, cur.rgb), ("depth", prev.depth, cur.depth))
            if np.array_equal(a, b)]
    return None if not same else same[0] if len(same) == 1 else "both"
