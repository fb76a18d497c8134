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
        return Intrinsics(self.fx, self.fy, self.cx - edge, self.cy - edge, self.width - 2 * edge,
                          self.height - 2 * edge)


def reproject_image(image: np.ndarray, src: Intrinsics, dst: Intrinsics) -> np.ndarray:
    """`image` (H, W, ...) taken with intrinsics `src`, as a camera at the same centre and orientation with `dst`
    would see it: (dst.height, dst.width, ...), bilinear, coordinates outside `image` clamped to its edge. Pixel (u, v)
    of the result samples `image` at (src.cx + (u - dst.cx) src.fx / dst.fx, same in v). Registers colour to depth
    when the two cameras differ in intrinsics only (their baseline neglected). Integer images are rounded to the
    nearest level."""
    img = np.asarray(image)
    wdtype = img.dtype if img.dtype.kind == "f" else np.float32  # weights in the image's precision
    if img.shape[:2] != (src.height, src.width):
        raise DataError(f"image is {img.shape[1]}x{img.shape[0]}, its intrinsics are for {src.width}x{src.height}")
    u = src.cx + (np.arange(dst.width) - dst.cx) * (src.fx / dst.fx)
    v = src.cy + (np.arange(dst.height) - dst.cy) * (src.fy / dst.fy)

    def weights(x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = np.clip(x, 0.0, n - 1.0)
        i0 = np.minimum(np.floor(x).astype(np.int64), max(n - 2, 0))
        return i0, np.minimum(i0 + 1, n - 1), (x - i0).astype(wdtype)

    u0, u1, wu = weights(u, src.width)
    v0, v1, wv = weights(v, src.height)
    shape = (-1,) + (1,) * (img.ndim - 1)
    rows = img[v0] * (1 - wv.reshape(shape)) + img[v1] * wv.reshape(shape)  # (H', W, ...)
    shape = (1, -1) + (1,) * (img.ndim - 2)
    out = rows[:, u0] * (1 - wu.reshape(shape)) + rows[:, u1] * wu.reshape(shape)
    if img.dtype.kind in "iu":  # integer images round to the nearest level (a cast would truncate: -0.5 on average)
        info = np.iinfo(img.dtype)
        out = np.clip(np.rint(out), info.min, info.max)
    return out.astype(img.dtype, copy=False)
