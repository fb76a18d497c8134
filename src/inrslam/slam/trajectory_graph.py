"""A pose graph of a whole trajectory (slam.refine): photometric links between frames a few apart, and the tracked
relative poses of consecutive frames, optimised together once the last frame is tracked.

A link (i, j, T_ij) is frame j aligned onto frame i (`photometric.align_photometric`) from their tracked relative
pose: T_ij = T_i^-1 T_j, camera j in camera i. Numpy poses in, numpy poses out.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from inrslam.data.frame import Frame
from inrslam.slam.config import RefineConfig, SlamConfig
from inrslam.slam.photometric import PhotoLevel, align_photometric, build_pyramid
from inrslam.slam.pose_graph import Edge, odometry_edges, optimise, relative
from inrslam.slam.registration import filtered_depth


def frame_pyramid(frame: Frame, cfg: SlamConfig, smooth: np.ndarray | None = None) -> list[PhotoLevel]:
    """Photometric pyramid of a frame: its colour and its depth after the GICP stage's filter (`cfg.gicp`; noisy
    depth only), given as `smooth` when already computed; `cfg.photo.levels` levels."""
    intr = frame.intrinsics
    depth = filtered_depth(frame.depth, cfg.gicp) if smooth is None else smooth
    return build_pyramid(frame.rgb, depth, (intr.fx, intr.fy, intr.cx, intr.cy), cfg.photo.levels)


def photometric_links(pyramid: Callable[[int], list[PhotoLevel]], poses: np.ndarray, gaps: list[int], photo_cfg,
                      max_shift: float, seed: int = 0) -> tuple[list[tuple[int, int, np.ndarray]], int]:
    """Align every frame j onto frames j - g (g in `gaps`) from their relative pose in `poses`.

    Args:
        pyramid: frame index -> its photometric pyramid (`photometric.build_pyramid`); called once per frame, in order.
        poses: (N, 4, 4) float64 c2w, metres.
        gaps: frame offsets (>= 1).
        photo_cfg: `PhotoConfig` (the alignment's settings).
        max_shift: metres; an alignment that moved camera j's position relative to camera i further is left out.
        seed: seeds the reference-pixel subsets (link (i, j) draws with seed + 1009 j + i).
    Returns:
        the links (i, j, T_ij (4, 4) float64) and how many alignments were left out (failed or moved too far).
    """
    poses = np.asarray(poses, dtype=np.float64)
    keep = max(gaps, default=0)
    pyrs: dict[int, list[PhotoLevel]] = {}
    links, dropped = [], 0
    for j in range(len(poses)):
        pyrs[j] = pyramid(j)
        for k in [k for k in pyrs if k < j - keep]:
            del pyrs[k]
        for g in gaps:
            i = j - g
            if i < 0:
                continue
            T_ji = np.linalg.solve(poses[j], poses[i])  # camera i -> camera j, as tracked
            res = align_photometric(pyrs[i], pyrs[j], torch.as_tensor(T_ji), photo_cfg,
                                    torch.Generator().manual_seed(seed + 1009 * j + i))
            T_ij = np.linalg.inv(res.T_ik.numpy())
            shift = float(np.linalg.norm(T_ij[:3, 3] - relative(poses[i], poses[j])[:3, 3]))
            if res.fallback is not None or not shift <= max_shift:
                dropped += 1
                continue
            links.append((i, j, T_ij))
    return links, dropped


def refine_trajectory(poses: np.ndarray, links: list[tuple[int, int, np.ndarray]], cfg: RefineConfig) -> np.ndarray:
    """(N, 4, 4) c2w -> the optimum of the links (`cfg.sigma_t` / `sigma_r`, Huber `cfg.huber`) and the poses' own
    consecutive relative poses (`cfg.odom_sigma_t` / `odom_sigma_r`), frame 0 fixed. Without links: unchanged."""
    poses = np.asarray(poses, dtype=np.float64)
    if not links:
        return poses.copy()
    edges = odometry_edges(poses, cfg.odom_sigma_t, cfg.odom_sigma_r)
    edges += [Edge(i, j, T, cfg.sigma_t, cfg.sigma_r, cfg.huber) for i, j, T in links]
    return optimise(poses, edges)
