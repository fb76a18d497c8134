"""Options of the built-in scenes (`--data builtin:NAME`): `SceneConfig` lives with the data config (the `data.builtin`
section); the per-scene sensor defaults live here."""

from __future__ import annotations

from inrslam.data.config import SceneConfig

__all__ = ["DEFAULT_SENSOR", "SceneConfig"]

DEFAULT_SENSOR = {"handheld": (0.004, 0.05), "loop": (0.004, 0.05), "symmetric": (0.004, 0.05)}
"""(depth noise std at 1 m in metres, fraction of depth holes) of a scene when `SceneConfig` leaves them None."""
