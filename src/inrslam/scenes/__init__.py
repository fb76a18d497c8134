"""Built-in procedural indoor scenes rendered into RGB-D sequences with ground truth (no download).

    >>> from inrslam.scenes import list_scenes, load_scene
    >>> ds = load_scene("room")          # generated on first use (~10 s), then read from the cache
    >>> frame = ds[0]                    # Frame: rgb (240, 320, 3), depth (240, 320) metres, c2w (OpenCV axes)

Scenes are textured with photographs bundled in scikit-image and ray-cast with trimesh (embree when available).
Geometry, camera path and sensor noise are deterministic from `SceneConfig.seed`. See `store.py` for the cache.
"""

from __future__ import annotations

from typing import NamedTuple

from inrslam.scenes.config import SceneConfig
from inrslam.scenes.dataset import BuiltinDataset
from inrslam.scenes.export import export_replica, export_tum
from inrslam.scenes.layouts import SCENES, SceneLayout
from inrslam.scenes.store import cache_root, ensure_scene

DEFAULT_SCENE = "room"


class SceneInfo(NamedTuple):
    """Name and one-line description of a built-in scene (unpacks as a (name, description) pair)."""

    name: str
    description: str


def list_scenes() -> list[SceneInfo]:
    """All registered scenes as (name, description), default first."""
    return [SceneInfo(e.name, e.help) for e in SCENES.entries()]


def load_scene(name: str = DEFAULT_SCENE, cfg: SceneConfig | None = None) -> BuiltinDataset:
    """Dataset of a built-in scene, rendering it into the cache on first use.

    Args:
        name: registered scene name (`list_scenes()`); unknown names raise KeyError naming the closest one.
        cfg: rendering options (frames, resolution, seed, sensor effects); None = defaults.
    """
    cfg = cfg or SceneConfig()
    return BuiltinDataset(ensure_scene(name, cfg), cfg)


__all__ = [
    "DEFAULT_SCENE",
    "SCENES",
    "BuiltinDataset",
    "SceneConfig",
    "SceneInfo",
    "SceneLayout",
    "cache_root",
    "export_replica",
    "export_tum",
    "list_scenes",
    "load_scene",
]
