"""Options of the dataset readers (`data:` section of a run config)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional


@dataclass
class SceneConfig:
    """How a built-in scene is rendered. Every combination is deterministic from `seed` and cached."""

    frames: int = 0  # number of frames; 0 = the scene's own default length
    width: int = 0  # image width in pixels; 0 = scene default
    height: int = 0  # image height in pixels; 0 = scene default
    seed: int = 0  # seed of the layout, camera path and sensor noise
    depth_noise: Optional[float] = None  # std of depth noise at 1 m, metres (x depth^2, Kinect-like), None = scene's
    # own default (0.004 for handheld, loop and symmetric, else 0)
    missing_depth: Optional[float] = None  # fraction of pixels with depth dropped to 0 (random holes); None = default
    motion_scale: float = 1.0  # multiplies the camera speed (larger = more motion between frames)


@dataclass
class TumConfig:
    """TUM RGB-D timestamp association (`data.tum.*`, used when the reader is tum)."""

    max_dt_depth: float = 0.02  # max |t_rgb - t_depth| in seconds for a colour/depth pair
    max_dt_pose: float = 0.02  # max |t_rgb - t_gt| s for the nearest GT pose; farther = invalid


@dataclass
class NeuralRgbdConfig:
    """NeuralRGBD reader options (`data.neuralrgbd.*`, used when the reader is neuralrgbd)."""

    depth_dir: str = "depth_filtered"  # depth folder (depth_filtered as the paper, or depth)


@dataclass
class SevenScenesConfig:
    """7-Scenes reader options (`data.sevenscenes.*`, used when the reader is 7scenes)."""

    sequence: str = ""  # frame sub-folder when there are several (e.g. seq-02); "" = the only one


@dataclass
class DataConfig:
    """Which RGB-D sequence to read and how. Overrides apply to folder datasets (and bounds/cropping to all); each
    sub-section only to the reader (or, `builtin`, the built-in scenes) it is named after."""

    path: str = "builtin:room"  # dataset folder, or builtin:NAME for a built-in procedural scene
    dataset: str = "auto"  # reader name (replica, neuralrgbd, scannet, tum, 7scenes) or auto = detect the layout
    max_frames: int = 0  # keep at most this many frames after start/stride; 0 = all
    stride: int = 1  # keep every stride-th frame
    start: int = 0  # index of the first frame kept
    depth_scale: Optional[float] = None  # raw units per metre; None = per reader (replica 6553.5, tum 5000, else 1000)
    intrinsics: Optional[list[float]] = None  # [fx, fy, cx, cy] px of the files on disk; None = reader's
    color_intrinsics: Optional[list[float]] = None  # [fx, fy, cx, cy] px of the colour files when the colour camera
    # differs from the depth camera (7-Scenes: Kinect colour ~525 px, depth 585): colour is resampled into the depth
    # camera (baseline neglected); None = colour shares the depth intrinsics
    bounds: Optional[list[list[float]]] = None  # [[xmin, xmax], [ymin, ymax], [zmin, zmax]] m; None = table/estimate
    bounds_frames: int = 20  # frames (evenly spread over the sequence) back-projected when estimating bounds
    bounds_margin: float = 0.2  # metres added on every side of estimated bounds
    crop_edge: int = 0  # pixels removed on every image side (cx, cy shifted accordingly)
    depth_max: float = 0.0  # metres; depth beyond it is set to 0 (invalid); 0 = no clamp
    faithful_intrinsics: bool = False  # floor default intrinsics like the original (replica cx/cy 599/339, nrgbd f 554)
    builtin: SceneConfig = field(default_factory=SceneConfig)  # options of builtin:NAME scenes
    tum: TumConfig = field(default_factory=TumConfig)  # options of the tum reader
    neuralrgbd: NeuralRgbdConfig = field(default_factory=NeuralRgbdConfig)  # options of the neuralrgbd reader
    sevenscenes: SevenScenesConfig = field(default_factory=SevenScenesConfig)  # options of the 7scenes reader
