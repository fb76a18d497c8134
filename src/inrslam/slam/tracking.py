"""Tracking: optimise one camera pose against the frozen map (docs/spec.md §7.4, with bug §13.9 fixed)."""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import torch
from torch import Tensor

from inrslam.slam.config import SlamConfig
from inrslam.slam.model import SceneModel
from inrslam.slam.poses import PoseSet


@dataclass
class TrackResult:
    c2w: Tensor  # (4, 4) chosen pose
    best_loss: float  # loss of the chosen pose (nan if none finite)
    iters: int  # pose updates made (track_iters when the loop ran to the end, with or without the final evaluation)
    fallback: str | None  # "nan_loss" / "pose_jump" (prediction or best finite pose kept), or None


@contextmanager
def frozen(module: torch.nn.Module) -> Iterator[torch.nn.Module]:
    """Temporarily stop gradients into `module`'s parameters (tracking only needs gradients to the points)."""
    flags = [(p, p.requires_grad) for p in module.parameters()]
    for p, _ in flags:
        p.requires_grad_(False)
    try:
        yield module
    finally:
        for p, flag in flags:
            p.requires_grad_(flag)


def track_frame(model: SceneModel, c2w_pred: Tensor, dirs_cam: Tensor, rgb: Tensor, depth: Tensor, cfg: SlamConfig,
                generator: torch.Generator | None, max_jump: float) -> TrackResult:
    """Adam on the pose only (map frozen); returns the lowest-loss pose among all evaluated poses, *including* the
    pose after the final update (one extra forward pass) unless `cfg.eval_final_pose` is off (the original code).

    Args:
        model: the scene (its parameters are not stepped here; gradients flow only to the pose).
        c2w_pred: (4, 4) predicted camera-to-world, metres.
        dirs_cam: (R, 3) camera-frame directions (z = 1), rgb: (R, 3) in [0, 1], depth: (R,) metres (0 = none): the
            frame's sampled rays (drawn once, reused every iteration).
        cfg: tracking settings (`track_iters`, `track_lr`, `pose_param`, `keep_best_pose`, `eval_final_pose`).
        generator: sample-jitter generator (None: the global one).
        max_jump: metres; a best pose farther than this from the prediction is rejected (0: never, the original).
    Returns: the chosen (4, 4) pose, its loss, the iterations run and the fallback taken, if any.
    """
    with frozen(model):
        return _track(model, c2w_pred, dirs_cam, rgb, depth, cfg, generator, max_jump)


def _track(model: SceneModel, c2w_pred: Tensor, dirs_cam: Tensor, rgb: Tensor, depth: Tensor, cfg: SlamConfig,
           generator: torch.Generator | None, max_jump: float) -> TrackResult:
    pose = PoseSet(c2w_pred[None], cfg.pose_param)
    opt = torch.optim.Adam(pose.parameters(), lr=cfg.track_lr)
    best_loss, best = math.inf, c2w_pred.detach().clone()
    n_evals = cfg.track_iters + (1 if cfg.eval_final_pose else 0)
    fallback = None
    it = 0  # pose updates made (the TrackResult's `iters`)
    for k in range(n_evals):
        c2w = pose.matrices()[0]
        final_eval = k == cfg.track_iters  # only reached with eval_final_pose: forward pass, no update
        with torch.set_grad_enabled(not final_eval):
            losses, _ = model.loss(c2w, dirs_cam, rgb, depth, generator)
            loss = losses["total"]
        val = float(loss.detach())
        if not math.isfinite(val):
            fallback = "nan_loss"
            break
        if val < best_loss or not cfg.keep_best_pose:
            best_loss, best = val, c2w.detach().clone()
        if final_eval:
            break
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        it = k + 1
    if not math.isfinite(best_loss):
        return TrackResult(c2w_pred.detach().clone(), float("nan"), it, "nan_loss")
    if max_jump > 0 and float(torch.linalg.norm(best[:3, 3] - c2w_pred[:3, 3])) > max_jump:
        return TrackResult(c2w_pred.detach().clone(), best_loss, it, "pose_jump")
    # a NaN after some finite iterations keeps the best finite pose; the event is still reported
    return TrackResult(best, best_loss, it, fallback)
