"""Typed configuration of the Explicit Hybrid Encoding mapper (`ehe:` section, used when `mapper` is ehe;
docs/ehe.md). Defaults are the original's ScanNet settings; value ranges are checked at
load time (`inrslam.config.ranges`)."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from inrslam.fields.config import TouchedRows


class MeshVoxels(str, enum.Enum):
    """Voxels marching cubes runs over: every allocated one, or only those whose 8 priors were initialised."""

    ALLOCATED = "allocated"
    INITIALISED = "initialised"


@dataclass
class EheConfig:
    """Explicit Hybrid Encoding: sparse 10 cm voxels with SDF priors + one 2 cm dense feature level (docs/ehe.md)."""

    voxel_size: float = 0.1  # edge of the sparse voxels, metres
    min_points: int = 10  # a voxel is allocated where more than this many depth points of one frame fall
    margin: float = 0.1  # fraction of a voxel edge: points' mean this close to a face also allocates that neighbour
    max_vertices: int = 200000  # cap on voxel vertices in use; a frame that would exceed it allocates nothing
    point_stride: int = 1  # back-project every n-th pixel row and column for allocation and prior init
    fine_cell: float = 0.02  # cell size of the single dense feature level, metres
    feature_dim: int = 2  # features per vertex of the dense level
    hidden_dim: int = 32  # hidden width of the two bias-free decoders (SDF residual, colour)
    grid_init: float = 1e-4  # dense-level features init U(-grid_init, grid_init)
    touched_rows: TouchedRows = TouchedRows.GRADIENT  # dense-level rows one Adam step updates: gradient = rows with a
    # non-zero gradient (samples no loss term reaches are skipped in the backward) | read = every row read (docs/ehe.md)
    truncation: float = 0.05  # SDF truncation T, metres (SDF values are in units of T)
    step: float = 0.1  # sample spacing inside hit voxels, as a fraction of voxel_size (0.1 -> 1 cm)
    max_hits: int = 10  # voxels a ray may pass through (nearest first)
    max_depth: float = 10.0  # rays are marched at most this far (metres of z-depth)
    depth_min: float = 0.01  # rays with measured depth in (depth_min, depth_max) m get the depth / SDF losses
    depth_max: float = 10.0  # see depth_min; also the far limit of allocation points
    rays: int = 2048  # rays per mapping iteration (spread evenly over the window's frames)
    iters: int = 10  # mapping iterations per frame
    first_iters: int = 100  # mapping iterations on the first frame
    early_stop: bool = True  # end a frame's mapping (not the first's) when its loss twice in a row exceeds their mean
    window: int = 10  # keyframes optimised with the current frame
    random_fraction: float = 0.5  # share of the window drawn at random (the rest: greedy voxel coverage)
    kf_overlap: float = 0.55  # new keyframe when the frame shares fewer than this fraction of voxels with the last
    kf_max_gap: int = 100  # ... or when this many frames passed since the last keyframe
    kf_ray_fraction: float = 0.25  # fraction of a keyframe's pixels kept for mapping (random, fixed per keyframe)
    lr: float = 0.01  # Adam learning rate of priors, dense level and decoders
    color_weight: float = 5.0  # weight of the L1 colour loss
    depth_weight: float = 1.0  # weight of the L1 depth loss
    free_space_weight: float = 10.0  # weight of the free-space loss (s - 1)^2 in front of z < D - T
    sdf_weight: float = 50000.0  # weight of the SDF loss (z + s T - D)^2 inside |z - D| <= T
    mesh_samples: int = 8  # SDF samples per voxel edge for the mesh (marching cubes)
    mesh_voxels: MeshVoxels = MeshVoxels.ALLOCATED  # mesh over allocated voxels | initialised (all 8 priors)

