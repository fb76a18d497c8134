"""Optimisable camera poses for tracking and bundle adjustment.

Two parameterisations (`PoseParam`):
- QUAT (the paper): an unnormalised quaternion (w, x, y, z) and a translation per pose; c2w = [R(q) | t].
- SE3: a twist xi per pose applied on the left of the initial pose, c2w = exp(xi) @ c2w_0 (smooth at xi = 0).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from inrslam.geometry.se3 import compose_qt, matrix_to_quat, se3_exp
from inrslam.slam.config import PoseParam


class PoseSet(nn.Module):
    """K camera-to-world poses as optimisable parameters.

    Args:
        c2w: (K, 4, 4) initial poses.
        param: parameterisation.
    """

    base: Tensor  # (K, 4, 4) initial poses of the SE3 parameterisation (a buffer)

    def __init__(self, c2w: Tensor, param: PoseParam = PoseParam.QUAT):
        super().__init__()
        self.param = PoseParam(param)
        c2w = c2w.detach()
        if self.param is PoseParam.QUAT:
            self.q = nn.Parameter(matrix_to_quat(c2w[:, :3, :3]).clone())
            self.t = nn.Parameter(c2w[:, :3, 3].clone())
        else:
            self.register_buffer("base", c2w.clone())
            self.xi = nn.Parameter(torch.zeros(c2w.shape[0], 6, dtype=c2w.dtype, device=c2w.device))

    def matrices(self) -> Tensor:
        """(K, 4, 4) current camera-to-world matrices (differentiable)."""
        if self.param is PoseParam.QUAT:
            return compose_qt(self.q, self.t)
        return se3_exp(self.xi) @ self.base


def ray_poses(mats: Tensor, slots: Tensor) -> Tensor:
    """(N,4,4) pose of every ray from (K,4,4) poses and (N,) int64 slots, with a deterministic backward:
    ``index_select`` sums each pose's gradient in a fixed order, while ``mats[slots]`` adds them atomically from
    several threads on a CPU (a different rounding on every run)."""
    return mats.index_select(0, slots)


def constant_velocity(prev: Tensor, prev2: Tensor | None) -> Tensor:
    """Predict the next c2w: (prev @ prev2^-1) @ prev (world-frame delta on the left); prev when prev2 is None."""
    if prev2 is None:
        return prev.clone()
    return prev @ torch.linalg.inv(prev2) @ prev


def relative_pose(c2w_kf: torch.Tensor, c2w: torch.Tensor, faithful: bool = False) -> torch.Tensor:
    """A frame's pose `c2w` (4, 4) relative to its keyframe's `c2w_kf` (4, 4), as `relative_trajectory` composes it:
    c2w_kf^-1 c2w (in the keyframe's camera), or with `faithful` the original's c2w c2w_kf^-1 (in the world)."""
    return c2w @ torch.linalg.inv(c2w_kf) if faithful else torch.linalg.inv(c2w_kf) @ c2w


def relative_trajectory(est: np.ndarray, rel: np.ndarray, rel_kf: np.ndarray, keyframes,
                        faithful: bool = False) -> np.ndarray:
    """The "relative" trajectory of docs/spec.md §7.6: keyframes keep their (bundle-adjusted) pose; every other frame
    i with a reference rel_kf[i] >= 0 is carried along by that keyframe's refinement: est[k] @ rel[i], its pose held
    rigid to the keyframe (rel = `relative_pose`), or with `faithful` the original's (Co-SLAM's) rel[i] @ est[k]
    (rel = c2w_i c2w_k^-1: the keyframe's correction applied in frame i's own camera, so a rotation turns the frame
    about itself instead of about the keyframe). est, rel (N,4,4) c2w; rel_kf (N,) int; returns (N,4,4)."""
    out = est.copy()
    kfs = set(int(k) for k in keyframes)
    for i in range(est.shape[0]):
        k = int(rel_kf[i])
        if i not in kfs and k >= 0 and np.isfinite(rel[i]).all():
            out[i] = rel[i] @ est[k] if faithful else est[k] @ rel[i]
    return out
