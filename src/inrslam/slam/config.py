"""Options of the SLAM loop (defaults = the paper's settings, supplementary §1 / spec §7)."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class PoseParam(str, enum.Enum):
    """How a pose is optimised."""

    QUAT = "quat"  # unnormalised quaternion + translation (the paper)
    SE3 = "se3"  # left-multiplied se(3) twist around the initial pose (smooth at zero)


@dataclass
class SlamConfig:
    """Tracking, mapping and keyframe settings."""

    init_iters: int = 500  # optimisation iterations on the first frame
    init_pixels: int = 2048  # rays per initialisation iteration
    track_iters: int = 20  # pose iterations per frame
    track_pixels: int = 1024  # rays per tracking iteration (drawn once per frame)
    track_lr: float = 1e-3  # Adam learning rate of the pose
    track_edge: int = 20  # pixels ignored at the image border during tracking
    keep_best_pose: bool = True  # keep the lowest-loss evaluated pose (False: the last evaluated pose)
    eval_final_pose: bool = True  # also evaluate the pose after the final update (the original never did)
    pose_param: PoseParam = PoseParam.QUAT  # pose parameterisation for tracking and BA
    const_velocity: bool = True  # constant-velocity motion prediction
    map_every: int = 5  # mapping + keyframe every N frames
    map_iters: int = 20  # mapping iterations per call
    map_pixels: int = 2048  # rays per mapping iteration drawn from the keyframe store
    map_current_min: int = 100  # min current-frame rays per mapping iteration (max(map_pixels/#KF, this))
    map_lr: float = 0.01  # Adam learning rate of the scene parameters
    bundle_adjust: bool = True  # optimise keyframe poses (first keyframe fixed) during mapping
    ba_lr: float = 1e-3  # Adam learning rate of keyframe poses
    ba_pose_every: int = 5  # pose step every N mapping iterations (gradients accumulate in between)
    keyframe_fraction: float = 0.05  # fraction of each keyframe's pixels stored for global sampling
    keyframe_variant: bool = False  # Table-3 keyframe variant: store 0.5 % instead of keyframe_fraction
    max_pose_jump: float = 0.5  # metres; a tracked pose moving more than this from the prediction is rejected
    checkpoint_every: int = 50  # frames between checkpoints (0 = only at the end)
    mesh_every: int = 0  # extract an intermediate mesh every N frames (0 = only at the end)


@dataclass
class MeshConfig:
    """Marching cubes on the SDF inside the scene bounds."""

    enabled: bool = True  # extract mesh.ply at the end
    resolution: float = 0.02  # grid spacing in metres
    chunk: int = 65536  # points per field query
    color: bool = True  # query vertex colours from the colour decoder


@dataclass
class OutputConfig:
    """What a run writes besides the mandatory outputs."""

    tensorboard: bool = True  # TensorBoard scalars when tensorboard is installed
