"""Materials of the built-in scenes: real photographs bundled with scikit-image, box-mapped in world metres.

A material turns a surface point p (metres) with face normal n into an albedo. The UV plane is chosen by the
dominant axis of n (box / tri-planar mapping without blending):

    |n_x| largest: (u, v) = ( y, -z)      |n_y| largest: (u, v) = (x, -z)      |n_z| largest: (u, v) = (x, y)
    u <- (u - offset_u) / tile_u,   v <- (v - offset_v) / tile_v,   texel = texture[v mod 1, u mod 1] (bilinear)

so one texture repeat covers `tile` metres and appearance is view-independent (Lambertian, no specularities).
Only images that ship inside the scikit-image wheel are used (no download).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

TEXTURE_SIZE = 128
"""Side of every texture in the atlas, texels (a 1 m tile gives ~8 mm texels: little aliasing at 320x240)."""

# name -> skimage.data function; all bundled with the wheel (checked offline with scikit-image 0.26)
_SOURCES = {
    "brick": "brick",
    "grass": "grass",
    "gravel": "gravel",
    "camera": "camera",
    "coins": "coins",
    "text": "text",
    "moon": "moon",
    "page": "page",
    "coffee": "coffee",
    "chelsea": "chelsea",
    "astronaut": "astronaut",
    "rocket": "rocket",
    "hubble": "hubble_deep_field",
    "ihc": "immunohistochemistry",
    "colorwheel": "colorwheel",
}


@dataclass(frozen=True)
class Material:
    """A box-mapped texture.

    Attributes:
        texture: key of `_SOURCES` (photograph) or "flat" (constant colour).
        tint: RGB multiplier in [0, 1]; grey images become `tint * (1 + contrast * (g - mean(g)))`.
        contrast: strength of the grey-image variation (0 = flat colour, ~1 = full photograph).
        tile: (tile_u, tile_v) metres covered by one repeat of the texture.
        offset: (3,) world point (metres) where the texture's top-left corner sits (for posters / pictures).
    """

    texture: str
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    contrast: float = 1.0
    tile: tuple[float, float] = (1.0, 1.0)
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@lru_cache(maxsize=None)
def _photo(name: str) -> np.ndarray:
    """(S, S, C) float32 in [0, 1] of a bundled skimage image resized to TEXTURE_SIZE (C = 1 or 3)."""
    import skimage.data
    from skimage.transform import resize

    img = getattr(skimage.data, _SOURCES[name])()
    img = np.asarray(img, dtype=np.float32) / 255.0
    if img.ndim == 2:
        img = img[..., None]
    img = img[..., :3]
    out = resize(img, (TEXTURE_SIZE, TEXTURE_SIZE, img.shape[2]), anti_aliasing=True, preserve_range=True)
    out = out.astype(np.float32)
    out.setflags(write=False)
    return out


def make_texture(mat: Material) -> np.ndarray:
    """Albedo texture of a material: (S, S, 3) float32 in [0, 1], S = TEXTURE_SIZE."""
    tint = np.asarray(mat.tint, dtype=np.float32)
    if mat.texture == "flat":
        return np.broadcast_to(tint, (TEXTURE_SIZE, TEXTURE_SIZE, 3)).astype(np.float32)
    if mat.texture not in _SOURCES:
        raise KeyError(f"unknown texture {mat.texture!r} (choices: flat, {', '.join(_SOURCES)})")
    img = _photo(mat.texture)
    if img.shape[2] == 1:
        g = img[..., 0]
        tex = tint * (1.0 + mat.contrast * (g - g.mean()))[..., None]
    else:
        mean = img.mean(axis=(0, 1), keepdims=True)
        tex = tint * (mean + mat.contrast * (img - mean))
    return np.clip(tex, 0.0, 1.0).astype(np.float32)


def texture_atlas(materials: list[Material]) -> np.ndarray:
    """(M, S, S, 3) float32 stack of `make_texture` for each material."""
    return np.stack([make_texture(m) for m in materials]).astype(np.float32)


def material_arrays(materials: list[Material]) -> tuple[np.ndarray, np.ndarray]:
    """Per-material mapping parameters: tiles (M, 2) metres and offsets (M, 3) metres (float64)."""
    tiles = np.array([m.tile for m in materials], dtype=np.float64).reshape(-1, 2)
    offsets = np.array([m.offset for m in materials], dtype=np.float64).reshape(-1, 3)
    return tiles, offsets


def box_uv(points: np.ndarray, normals: np.ndarray, tiles: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Box-mapped texture coordinates.

    Args:
        points: (N, 3) world points, metres.
        normals: (N, 3) face normals (any length).
        tiles: (N, 2) metres per texture repeat of each point's material.
        offsets: (N, 3) texture origin of each point's material, metres.
    Returns:
        (N, 2) (u, v) in texture repeats (not wrapped).
    """
    p = points - offsets
    axis = np.abs(normals).argmax(axis=1)
    u = np.where(axis == 0, p[:, 1], p[:, 0])
    v = np.where(axis == 2, p[:, 1], -p[:, 2])
    return np.stack([u / tiles[:, 0], v / tiles[:, 1]], axis=1)


def sample_atlas(atlas: np.ndarray, mat: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping texture lookup.

    Args:
        atlas: (M, S, S, 3) textures.
        mat: (N,) material index per point.
        uv: (N, 2) texture coordinates in repeats (u = column, v = row; 0..1 spans the texture once).
    Returns:
        (N, 3) float32 albedo.
    """
    S = atlas.shape[1]
    x = uv[:, 0] * S - 0.5
    y = uv[:, 1] * S - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0).astype(np.float32)[:, None]
    fy = (y - y0).astype(np.float32)[:, None]
    x0 = x0.astype(np.int64) % S
    y0 = y0.astype(np.int64) % S
    x1 = (x0 + 1) % S
    row0 = (mat.astype(np.int64) * S + y0) * S
    row1 = (mat.astype(np.int64) * S + (y0 + 1) % S) * S
    flat = atlas.reshape(-1, atlas.shape[-1])
    top = flat[row0 + x0] * (1 - fx) + flat[row0 + x1] * fx
    bot = flat[row1 + x0] * (1 - fx) + flat[row1 + x1] * fx
    return (top * (1 - fy) + bot * fy).astype(np.float32)
