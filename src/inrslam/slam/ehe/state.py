"""`EheState`: the SLAM loop's state plus what the EHE mapper carries between frames (saved with checkpoints)."""

from __future__ import annotations

from dataclasses import dataclass, field

from torch import Tensor

from inrslam.slam.state import SlamState


@dataclass(eq=False)
class EheState(SlamState):
    """`SlamState` plus kf_voxels: per keyframe slot, the (K,) int64 keys of the voxels its depth allocated
    (keyframe window coverage and overlap rule). The voxel structure itself is part of the model's state."""

    kf_voxels: list[Tensor] = field(default_factory=list)
