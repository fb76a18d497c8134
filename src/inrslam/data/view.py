"""A lazy view of a dataset: frame selection (start / stride / max_frames), cropping, depth clamping, bounds."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any, Iterator, Optional

import numpy as np

from inrslam.data.frame import Frame, Intrinsics, RGBDDataset
from inrslam.errors import ConfigError


class DatasetView:
    """Frames `start, start + stride, ...` (at most `max_frames`) of `base`, post-processed on read.

    Frame `index` is the position in the view; the base index is kept in `frame.meta["base_index"]`.

    Args:
        base: any RGBDDataset.
        start, stride, max_frames: selection (max_frames 0 = all).
        crop_edge: pixels removed on every side (intrinsics shifted).
        depth_max: metres; larger depths set to 0; 0 = no clamp.
        bounds: (3, 2) metres, overriding `base.bounds` (None = keep the base's).
    """

    def __init__(
        self,
        base: RGBDDataset,
        start: int = 0,
        stride: int = 1,
        max_frames: int = 0,
        crop_edge: int = 0,
        depth_max: float = 0.0,
        bounds: Optional[np.ndarray] = None,
    ):
        if start < 0 or stride < 1 or max_frames < 0 or crop_edge < 0 or depth_max < 0:
            raise ConfigError(
                "data: need start >= 0, stride >= 1, max_frames >= 0, crop_edge >= 0, depth_max >= 0; got "
                f"start={start}, stride={stride}, max_frames={max_frames}, crop_edge={crop_edge}, depth_max={depth_max}"
            )
        self.base = base
        idx = list(range(start, len(base), stride))
        if max_frames:
            idx = idx[:max_frames]
        self.indices = idx
        self.crop_edge = int(crop_edge)
        self.depth_max = float(depth_max)
        intr: Intrinsics = base.intrinsics
        if 2 * crop_edge >= min(intr.width, intr.height):
            raise ConfigError(f"data.crop_edge={crop_edge} removes the whole {intr.width}x{intr.height} image")
        self.intrinsics = intr.cropped(crop_edge) if crop_edge else intr
        self.name: str = base.name
        self.root: Path = base.root
        self.gt_mesh: Optional[Path] = base.gt_mesh
        self.bounds: Optional[np.ndarray] = (
            np.asarray(bounds, dtype=np.float64) if bounds is not None else base.bounds
        )

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> Frame:
        n = len(self.indices)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames")
        f = self.base[self.indices[i]]
        rgb, depth = f.rgb, f.depth
        if self.crop_edge:
            e = self.crop_edge
            rgb, depth = rgb[e:-e, e:-e], depth[e:-e, e:-e]
        if self.depth_max > 0:
            depth = np.where(depth > self.depth_max, np.float32(0), depth).astype(np.float32)
        meta = dict(f.meta, base_index=f.index)
        return replace(f, index=i, rgb=np.ascontiguousarray(rgb), depth=np.ascontiguousarray(depth),
                       intrinsics=self.intrinsics, meta=meta)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def true_depth(self, i: int) -> Optional[np.ndarray]:
        """(H, W) noise-free depth of selected frame i, metres (cropped and clamped like the frame's), when the
        base dataset has it (`true_depth`: the built-in scenes, before their sensor effects), else None."""
        fn = getattr(self.base, "true_depth", None)
        if fn is None:
            return None
        n = len(self.indices)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames")
        depth = fn(self.indices[i])
        if self.crop_edge:
            e = self.crop_edge
            depth = depth[e:-e, e:-e]
        if self.depth_max > 0:
            depth = np.where(depth > self.depth_max, np.float32(0), depth)
        return np.ascontiguousarray(depth, dtype=np.float32)

    def _per_frame(self, attr: str) -> Any:
        values = getattr(self.base, attr, None)
        if callable(values):
            values = values()
        return None if values is None else np.asarray(values)[self.indices]

    @property
    def poses(self) -> Optional[np.ndarray]:
        """(N, 4, 4) ground-truth c2w of the selected frames without reading images (None if the base cannot)."""
        return self._per_frame("poses")

    @property
    def pose_valid(self) -> Optional[np.ndarray]:
        """(N,) bool, or None if the base cannot tell without reading images."""
        return self._per_frame("pose_valid")

    @property
    def timestamps(self) -> Optional[np.ndarray]:
        """(N,) seconds, or None if the base cannot tell without reading images."""
        return self._per_frame("timestamps")

    def __repr__(self) -> str:
        return f"DatasetView({self.base!r}, frames={len(self)})"
