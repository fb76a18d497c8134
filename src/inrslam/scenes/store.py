"""Generating built-in scenes into the on-disk cache.

Cache folder: `$INRSLAM_CACHE/scenes` if the variable is set, else `~/.cache/inrslam/scenes`; one folder
`<name>-<hash>-v<GENERATOR_VERSION>` per rendered sequence, where the hash covers everything that changes the
rendered pixels (scene, frames, width, height, seed, motion_scale). Sensor effects (depth noise, holes) are applied
when frames are read (deterministic from the seed), so they share one cached render.

Folder layout (all written into a temporary folder, then moved into place with one `os.replace`)::

    rgb/000000.png       8-bit RGB
    depth/000000.png     uint16 z-depth, metres = value / DEPTH_SCALE (5000: 0.2 mm steps, up to 13.1 m); 0 = no hit
    poses.npy            (N, 4, 4) float64 camera-to-world, OpenCV axes, metres
    poses.txt            the same, one row-major 4x4 per line (16 values)
    intrinsics.json      fx, fy, cx, cy, width, height (pixels)
    bounds.json          {"bounds": [[xmin, xmax], [ymin, ymax], [zmin, zmax]]}: the room box + BOUNDS_MARGIN
    mesh.ply             ground-truth mesh with vertex colours (world metres)
    meta.json            scene, parameters, depth_scale, version; written last (its presence marks completion)
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import uuid
from pathlib import Path

import numpy as np
from PIL import Image

from inrslam.errors import ConfigError
from inrslam.geometry.intrinsics import Intrinsics
from inrslam.scenes.config import SceneConfig
from inrslam.scenes.layouts import DEFAULT_FRAMES, SCENES, SceneLayout
from inrslam.scenes.raycast import Renderer
from inrslam.scenes.trajectory import camera_poses

GENERATOR_VERSION = 1
"""Bump when the generator's output changes: old cache folders are then ignored."""

DEPTH_SCALE = 5000.0
"""Cached depth PNG units per metre."""

DEFAULT_WIDTH, DEFAULT_HEIGHT = 320, 240
FOCAL_PER_WIDTH = 0.8
"""fx = fy = 0.8 * width: a 64 degree horizontal field of view at any resolution (square pixels)."""

BOUNDS_MARGIN = 0.1
"""Metres added around the room box for `bounds.json`."""

STALE_TMP_SECONDS = 6 * 3600
"""Temporary generation folders older than this are leftovers of killed processes and are removed."""

CHUNK_FRAMES = 8
"""Frames per ray-casting call."""


def cache_root() -> Path:
    """`$INRSLAM_CACHE/scenes`, else `~/.cache/inrslam/scenes`."""
    env = os.environ.get("INRSLAM_CACHE")
    base = Path(env).expanduser() if env else Path.home() / ".cache" / "inrslam"
    return base / "scenes"


def scene_intrinsics(width: int, height: int) -> Intrinsics:
    """Pinhole intrinsics of the built-in camera at `width` x `height` (principal point at the image centre)."""
    f = FOCAL_PER_WIDTH * width
    return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


def render_params(name: str, cfg: SceneConfig) -> dict:
    """The resolved parameters that determine the rendered images (defaults filled in)."""
    SCENES.get(name)  # KeyError with a close match for unknown names
    for key in ("frames", "width", "height"):
        if getattr(cfg, key) < 0:
            raise ConfigError(f"data.builtin.{key}: expected >= 0 (0 = scene default), got {getattr(cfg, key)}")
    if cfg.seed < 0:
        raise ConfigError(f"data.builtin.seed: expected an integer >= 0, got {cfg.seed}")
    if cfg.motion_scale <= 0:
        raise ConfigError(f"data.builtin.motion_scale: expected > 0, got {cfg.motion_scale}")
    if cfg.missing_depth is not None and not 0.0 <= cfg.missing_depth < 1.0:
        raise ConfigError(f"data.builtin.missing_depth: expected a fraction in [0, 1), got {cfg.missing_depth}")
    if cfg.depth_noise is not None and cfg.depth_noise < 0:
        raise ConfigError(f"data.builtin.depth_noise: expected >= 0 metres, got {cfg.depth_noise}")
    frames = cfg.frames or DEFAULT_FRAMES[name]
    width = cfg.width or DEFAULT_WIDTH
    height = cfg.height or (DEFAULT_HEIGHT if not cfg.width else int(round(width * DEFAULT_HEIGHT / DEFAULT_WIDTH)))
    return {"scene": name, "frames": int(frames), "width": int(width), "height": int(height), "seed": int(cfg.seed),
            "motion_scale": float(cfg.motion_scale), "version": GENERATOR_VERSION}


def scene_dir(params: dict) -> Path:
    """Cache folder of a parameter set."""
    digest = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:12]
    return cache_root() / f"{params['scene']}-{digest}-v{GENERATOR_VERSION}"


def is_complete(folder: Path) -> bool:
    return (folder / "meta.json").is_file()


def ensure_scene(name: str, cfg: SceneConfig) -> Path:
    """Folder holding the rendered sequence, generating it first if it is not cached.

    Safe under concurrency: each process renders into its own temporary folder and moves it into place with
    one `os.replace`; a process that loses the race discards its copy and uses the winner's.
    """
    params = render_params(name, cfg)
    final = scene_dir(params)
    if is_complete(final):
        return final
    root = final.parent
    root.mkdir(parents=True, exist_ok=True)
    _remove_stale_tmp(root)
    tmp = root / f".tmp-{final.name}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        generate(SCENES.get(name)(params["seed"]), params, tmp)
        if final.exists() and not is_complete(final):  # a broken folder (e.g. files deleted by hand)
            trash = root / f".tmp-broken-{final.name}-{uuid.uuid4().hex[:8]}"
            try:
                os.replace(final, trash)
                shutil.rmtree(trash, ignore_errors=True)
            except OSError:
                pass
        try:
            os.replace(tmp, final)
        except OSError:
            if not is_complete(final):
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final


def _remove_stale_tmp(root: Path) -> None:
    now = time.time()
    for p in root.glob(".tmp-*"):
        try:
            if now - p.stat().st_mtime > STALE_TMP_SECONDS:
                shutil.rmtree(p, ignore_errors=True)
        except OSError:
            pass


def generate(layout: SceneLayout, params: dict, out: Path) -> None:
    """Render `layout` with `params` (see `render_params`) into the folder `out` (created)."""
    out = Path(out)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    intr = scene_intrinsics(params["width"], params["height"])
    poses = camera_poses(layout.path, params["frames"], params["motion_scale"])
    renderer = Renderer(layout.geometry)
    for s in range(0, len(poses), CHUNK_FRAMES):
        rgb, depth = renderer.render_many(poses[s:s + CHUNK_FRAMES], intr)
        for k in range(len(rgb)):
            write_rgb(out / "rgb" / f"{s + k:06d}.png", rgb[k])
            write_depth(out / "depth" / f"{s + k:06d}.png", depth[k], DEPTH_SCALE)

    np.save(out / "poses.npy", poses)
    np.savetxt(out / "poses.txt", poses.reshape(len(poses), 16), fmt="%.12f")
    room = layout.geometry.room
    bounds = np.stack([room[:, 0] - BOUNDS_MARGIN, room[:, 1] + BOUNDS_MARGIN], axis=1)
    _write_json(out / "intrinsics.json", {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
                                           "width": intr.width, "height": intr.height})
    _write_json(out / "bounds.json", {"bounds": bounds.tolist(), "room": room.tolist(), "margin": BOUNDS_MARGIN})
    mesh = layout.geometry.mesh.copy()
    mesh.visual.vertex_colors = layout.geometry.vertex_colors()
    mesh.export(out / "mesh.ply")
    _write_json(out / "meta.json", {**params, "depth_scale": DEPTH_SCALE, "fps": 30.0, "axes": "opencv c2w",
                                     "frames_written": len(poses)})


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    """(H, W, 3) float in [0, 1] -> 8-bit PNG."""
    Image.fromarray(np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)).save(path, compress_level=1)


def write_depth(path: Path, depth: np.ndarray, scale: float) -> None:
    """(H, W) metres -> uint16 PNG with value = round(depth * scale), clipped to 65535."""
    Image.fromarray(encode_depth(depth, scale)).save(path, compress_level=1)


def encode_depth(depth: np.ndarray, scale: float) -> np.ndarray:
    """(H, W) metres -> (H, W) uint16 round(depth * scale), clipped to [0, 65535]."""
    return np.clip(np.round(np.asarray(depth, dtype=np.float64) * scale), 0, 65535).astype(np.uint16)


def _write_json(path: Path, obj: dict) -> None:
    path.write_text(json.dumps(obj, indent=2) + "\n", encoding="utf-8")
