"""Tracking: optimise one camera pose against the frozen map (spec §7.4, with bug §13.9 fixed)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from inrslam.slam.poses import PoseSet


@dataclass
class TrackResult:
    c2w: Tensor  # (4, 4) chosen pose
    best_loss: float  # loss of the chosen pose (nan if none finite)
    iters: int  # iterations run
    fallback: str | None  # why the prediction was kept ("nan_loss", "pose_jump", "no_valid_pixels") or None


def track_frame(model, c2w_pred: Tensor, dirs_cam: Tensor, rgb: Tensor, depth: Tensor, cfg, generator,
                max_jump: float) -> TrackResult:
    """Adam on the pose only; returns the lowest-loss pose among all evaluated poses, *including* the pose after
    the final update (evaluated with one extra forward pass).

    Args:
        model: `SceneModel` (its parameters are not stepped here).
        c2w_pred: (4, 4) predicted pose.
        dirs_cam, rgb, depth: the frame's sampled rays (drawn once, reused every iteration).
        cfg: `SlamConfig`. generator: sample-jitter generator.
        max_jump: metres; a best pose farther than this from the prediction is rejected.
    """
    pose = PoseSet(c2w_pred[None], cfg.pose_param)
    opt = torch.optim.Adam(pose.parameters(), lr=cfg.track_lr)
    best_loss, best = math.inf, c2w_pred.detach().clone()
    n_iters = cfg.track_iters
    for it in range(n_iters + 1):
        c2w = pose.matrices()[0]
        final_eval = it == n_iters
        with torch.set_grad_enabled(not final_eval):
            losses, _ = model.loss(c2w, dirs_cam, rgb, depth, generator)
            loss = losses["total"]
        val = float(loss.detach())
        if not math.isfinite(val):
            break
        if val < best_loss or not cfg.keep_best_pose:
            best_loss, best = val, c2w.detach().clone()
        if final_eval:
            break
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    model.zero_grad(set_to_none=True)
    if not math.isfinite(best_loss):
        return TrackResult(c2w_pred.detach().clone(), float("nan"), it, "nan_loss")
    if float(torch.linalg.norm(best[:3, 3] - c2w_pred[:3, 3])) > max_jump:
        return TrackResult(c2w_pred.detach().clone(), best_loss, it, "pose_jump")
    return TrackResult(best, best_loss, it, None)
