"""Options of the built-in scenes (`--data builtin:NAME`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional


@dataclass
class SceneConfig:
    """How a built-in scene is rendered. Every combination is deterministic from `seed` and cached."""

    frames: int = 0  # number of frames; 0 = the scene's own default length
    width: int = 0  # image width in pixels; 0 = scene default
    height: int = 0  # image height in pixels; 0 = scene default
    seed: int = 0  # seed of the layout, camera path and sensor noise
    depth_noise: Optional[float] = None  # std of Gaussian depth noise at 1 m, metres (scaled by depth^2, Kinect-like);
    # None = the scene's own default (0 for every scene but handheld)
    missing_depth: Optional[float] = None  # fraction of pixels with depth dropped to 0 (random holes); None = default
    motion_scale: float = 1.0  # multiplies the camera speed (larger = more motion between frames)


DEFAULT_SENSOR = {"handheld": (0.004, 0.05)}
"""(depth noise std at 1 m in metres, fraction of depth holes) of a scene when `SceneConfig` leaves them None."""
