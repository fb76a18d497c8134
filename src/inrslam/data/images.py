"""Image files: 8-bit colour and 16-bit depth PNG, read exactly; every failure is a `DataError` naming the file."""

from __future__ import annotations

import os
from pathlib import Path
from typing import cast

import numpy as np
from PIL import Image, UnidentifiedImageError

from inrslam.errors import DataError

_DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I")


def _open(path: Path, what: str) -> Image.Image:
    if not path.is_file():
        raise DataError(f"{path}: {what} not found")
    try:
        img = Image.open(path)
        img.load()  # decode now so truncated / corrupt files fail here
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError, ValueError, SyntaxError) as e:
        raise DataError(f"{path}: cannot read {what} ({type(e).__name__}: {e})") from None
    return img


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image from its header only (no decoding)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: image not found")
    try:
        with Image.open(path) as img:
            return img.size
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError, ValueError, SyntaxError) as e:
        raise DataError(f"{path}: cannot read image header ({type(e).__name__}: {e})") from None


def read_rgb(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a colour image as (H, W, 3) float32 in [0, 1] (grey is replicated, alpha dropped).

    Args:
        path: JPEG / PNG file (8-bit per channel).
        size: optional (width, height) to resize to (bilinear, antialiased when shrinking).
    """
    path = Path(path)
    img = _open(path, "colour image")
    if img.mode in _DEPTH_MODES or img.mode == "F":
        raise DataError(f"{path}: colour image has {img.mode} pixels (16/32-bit: a depth image?); expected 8-bit "
                        "colour or grey")
    if img.mode != "RGB":
        try:
            img = img.convert("RGB")
        except (ValueError, OSError) as e:
            raise DataError(f"{path}: cannot convert mode {img.mode} to RGB ({e})") from None
    if size is not None and img.size != tuple(size):
        # Pillow sets its module-level filter names (BILINEAR, ...) at import, so its annotations lack them
        img = img.resize(cast("tuple[int, int]", tuple(size)), Image.BILINEAR)  # type: ignore[attr-defined]
    return np.asarray(img, dtype=np.float32) / 255.0


def read_depth_raw(path: str | os.PathLike) -> np.ndarray:
    """Read a 16-bit single-channel depth PNG exactly: (H, W) uint16 raw sensor units (values > 32767 kept)."""
    path = Path(path)
    img = _open(path, "depth image")
    if img.mode not in _DEPTH_MODES:
        raise DataError(f"{path}: expected a 16-bit single-channel depth PNG, got image mode {img.mode!r}")
    arr = np.asarray(img)
    if arr.ndim != 2:
        raise DataError(f"{path}: expected a single-channel depth image, got shape {arr.shape}")
    if arr.dtype != np.uint16:
        if arr.min(initial=0) < 0 or arr.max(initial=0) > 65535:
            raise DataError(f"{path}: depth values outside the 16-bit range")
        arr = arr.astype(np.uint16)
    return arr


def read_depth(path: str | os.PathLike, scale: float, invalid: tuple[int, ...] = ()) -> np.ndarray:
    """Read a 16-bit depth PNG as (H, W) float32 metres = raw / `scale`; raw 0 and values in `invalid` become 0."""
    raw = read_depth_raw(path)
    depth = raw.astype(np.float32) / np.float32(scale)
    for bad in invalid:
        depth[raw == bad] = 0.0
    return depth
