"""`BuiltinDataset`: streams a cached built-in scene as `Frame`s (the `RGBDDataset` protocol)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterator

import numpy as np
from PIL import Image

from inrslam.data.frame import Frame, Intrinsics
from inrslam.errors import DataError
from inrslam.scenes.config import DEFAULT_SENSOR, SceneConfig
from inrslam.scenes.sensor import apply_sensor

FPS = 30.0
"""Frame rate of the built-in sequences: timestamp = index / FPS seconds."""


class BuiltinDataset:
    """A rendered built-in scene read lazily from its cache folder (see `inrslam.scenes.store`).

    Attributes:
        name: "builtin" (the dataset kind); `scene` holds the scene name ("room", ...).
        root: cache folder.
        intrinsics: pinhole intrinsics of every frame.
        bounds: (3, 2) float64 room box plus a 0.1 m margin, metres.
        gt_mesh: path of the ground-truth mesh (PLY with vertex colours).
        poses: (N, 4, 4) float64 camera-to-world, OpenCV axes.
        timestamps: (N,) seconds, index / 30.
        depth_noise, missing_depth: sensor effects applied on read (see `SceneConfig`), seeded by `seed`.
    """

    name = "builtin"

    def __init__(self, root: str | Path, cfg: SceneConfig | None = None):
        cfg = cfg or SceneConfig()
        self.root = Path(root)
        meta = _read_json(self.root / "meta.json")
        intr = _read_json(self.root / "intrinsics.json")
        self.scene: str = meta["scene"]
        self.depth_scale = float(meta["depth_scale"])
        self.seed = int(cfg.seed)
        noise, holes = DEFAULT_SENSOR.get(self.scene, (0.0, 0.0))
        self.depth_noise = float(noise if cfg.depth_noise is None else cfg.depth_noise)
        self.missing_depth = float(holes if cfg.missing_depth is None else cfg.missing_depth)
        self.intrinsics = Intrinsics(float(intr["fx"]), float(intr["fy"]), float(intr["cx"]), float(intr["cy"]),
                                     int(intr["width"]), int(intr["height"]))
        self.bounds = np.asarray(_read_json(self.root / "bounds.json")["bounds"], dtype=np.float64)
        self.gt_mesh = self.root / "mesh.ply"
        try:
            self.poses = np.load(self.root / "poses.npy")
        except (OSError, ValueError) as e:
            raise DataError(f"{self.root / 'poses.npy'}: unreadable ({e})") from None
        self.timestamps = np.arange(len(self.poses), dtype=np.float64) / FPS

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def pose_valid(self) -> np.ndarray:
        """(N,) bool: every generated pose is a pose (what each frame's `pose_valid` says), without reading images."""
        return np.ones(len(self.poses), dtype=bool)

    def _index(self, i: int) -> int:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames of builtin:{self.scene}")
        return i % n

    def rgb(self, i: int) -> np.ndarray:
        """(H, W, 3) float32 colour of frame i in [0, 1]."""
        return _read_png(self.root / "rgb" / f"{self._index(i):06d}.png").astype(np.float32) / 255.0

    def depth(self, i: int, clean: bool = False) -> np.ndarray:
        """(H, W) float32 z-depth of frame i, metres (0 = invalid); `clean` skips the sensor effects."""
        i = self._index(i)
        d = _read_png(self.root / "depth" / f"{i:06d}.png").astype(np.float32) / np.float32(self.depth_scale)
        if clean:
            return d
        return apply_sensor(d, self.seed, i, self.depth_noise, self.missing_depth)

    def true_depth(self, i: int) -> np.ndarray:
        """(H, W) float32 noise-free z-depth of frame i, metres: the rendered depth before sensor noise and holes."""
        return self.depth(i, clean=True)

    def __getitem__(self, i: int) -> Frame:
        i = self._index(int(i))
        return Frame(
            index=i,
            timestamp=float(self.timestamps[i]),
            rgb=self.rgb(i),
            depth=self.depth(i),
            intrinsics=self.intrinsics,
            c2w=self.poses[i].copy(),
            pose_valid=True,
            source=str(self.root / "rgb" / f"{i:06d}.png"),
            meta={"scene": self.scene},
        )

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return f"BuiltinDataset(scene={self.scene!r}, frames={len(self)}, root={str(self.root)!r})"


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise DataError(f"{path}: missing or invalid built-in scene file ({e}); delete the folder to regenerate") from None


def _read_png(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as im:
            return np.asarray(im)
    except OSError as e:
        raise DataError(f"{path}: unreadable frame ({e}); delete {path.parent.parent} to regenerate") from None
