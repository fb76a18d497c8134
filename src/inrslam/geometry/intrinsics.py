"""Pinhole camera intrinsics (pixels); pixel (u, v) = (column, row), integer coordinates at pixel centres."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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

    def cropped(self, edge: int) -> "Intrinsics":
        """Intrinsics after removing `edge` pixels on every side."""
        return Intrinsics(self.fx, self.fy, self.cx - edge, self.cy - edge, self.width - 2 * edge, self.height - 2 * edge)
