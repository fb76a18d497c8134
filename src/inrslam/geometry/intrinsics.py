"""Pinhole camera intrinsics (pixels); pixel (u, v) = (column, row), integer coordinates at pixel centres."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from inrslam.errors import DataError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels for an image of `width` x `height`."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def checked(self, source: str) -> "Intrinsics":
        """Self when fx, fy > 0, cx, cy finite and the image at least 1 px; else DataError naming `source`."""
        f = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(v) for v in f) or self.fx <= 0 or self.fy <= 0:
            raise DataError(f"{source}: invalid camera intrinsics fx={self.fx}, fy={self.fy}, cx={self.cx}, "
                            f"cy={self.cy} (expected finite values with fx, fy > 0 pixels)")
        if self.width < 1 or self.height < 1:
            raise DataError(f"{source}: invalid image size {self.width}x{self.height}")
        return self

    def cropped(self, edge: int) -> "Intrinsics":
        """Intrinsics after removing `edge` pixels on every side."""
        return Intrinsics(self.fx, self.fy, self.cx - edge, self.cy - edge, self.width - 2 * edge, self.height - 2 * edge)
