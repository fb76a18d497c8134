"""Per-frame EHE mapping (docs/ehe.md §5): keyframe window by voxel coverage, optimisation with adaptive early
ending, and the overlap keyframe rule. Pure functions and small classes; the loop is `EheSystem`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch
from torch import Tensor

from inrslam.rendering.losses import psnr_from_mse
from inrslam.slam.ehe.config import EheConfig

# () -> world rays of one iteration: origins (R, 3), dirs (R, 3) (t = z-depth), rgb (R, 3), depth (R,) metres
RayBatch = Callable[[], tuple[Tensor, Tensor, Tensor, Tensor]]


class EarlyStop:
    """Adaptive early ending: stop when the loss exceeds the running mean of the losses before it twice in a row.

    >>> e = EarlyStop(); [e.update(x) for x in (4.0, 3.0, 3.9, 3.8)]
    [False, False, False, True]
    """

    def __init__(self) -> None:
        self.total, self.n, self.above = 0.0, 0, 0

    def update(self, loss: float) -> bool:
        """Feed one iteration's loss; True when mapping should end now."""
        if self.n:
            self.above = self.above + 1 if loss > self.total / self.n else 0
        self.total += loss
        self.n += 1
        return self.above >= 2


def voxel_overlap(current: Tensor, other: Tensor) -> float:
    """|current ∩ other| / |current| of two sets of voxel keys (1-D int64); 0 for an empty current set."""
    if current.numel() == 0:
        return 0.0
    return float(torch.isin(current, other).sum()) / current.numel()


def needs_keyframe(overlap: float, frames_since: int, cfg: EheConfig, n_observed: int = 1) -> bool:
    """New keyframe when the frame shares fewer than `kf_overlap` of its voxels with the last keyframe, or more
    than `kf_max_gap` frames passed since it; never for a frame that observes no voxel (`n_observed` 0: no valid
    depth), whose keyframe would hold no rays and make the next frame a keyframe too (overlap with nothing)."""
    return n_observed > 0 and (overlap < cfg.kf_overlap or frames_since > cfg.kf_max_gap)


def select_window(current: Tensor, kf_voxels: list[Tensor], window: int, random_fraction: float,
                  generator: torch.Generator) -> list[int]:
    """Keyframes (indices into `kf_voxels`) optimised with the current frame, at most `window`.

    Greedy maximum coverage first (at most window − round(window·random_fraction) picks): repeatedly the keyframe
    seeing most of the current frame's voxels not yet covered, while it adds any; then random keyframes among the
    rest up to `window`. All keyframes when there are no more than `window`.
    """
    n = len(kf_voxels)
    if n <= window:
        return list(range(n))
    n_cov = window - int(round(window * random_fraction))
    chosen: list[int] = []
    left = current
    for _ in range(n_cov):
        gains = [int(torch.isin(left, kf).sum()) if k not in chosen else -1 for k, kf in enumerate(kf_voxels)]
        best = max(range(n), key=lambda k: gains[k])
        if gains[best] <= 0:
            break
        chosen.append(best)
        left = left[~torch.isin(left, kf_voxels[best])]
    rest = [k for k in range(n) if k not in chosen]
    perm = torch.randperm(len(rest), generator=generator).tolist()
    return chosen + [rest[j] for j in perm[: window - len(chosen)]]


@dataclass
class MapResult:
    """One frame's mapping: losses (per iteration, total), iters run, psnr (dB) and depth_l1 (m) per iteration."""

    losses: list[float] = field(default_factory=list)
    psnr: list[float] = field(default_factory=list)
    depth_l1: list[float] = field(default_factory=list)
    skipped: int = 0

    @property
    def iters(self) -> int:
        return len(self.losses)


def optimise(model, optimizers: dict, batch: RayBatch, iters: int, early_stop: bool,
             generator: torch.Generator) -> MapResult:
    """Up to `iters` Adam steps of `model.loss` on fresh ray batches; non-finite losses take no step, and with
    `early_stop` the loss that ends mapping (`EarlyStop`) takes none either (its forward is the only one spent)."""
    res = MapResult()
    stop = EarlyStop()
    for _ in range(iters):
        o, d, rgb, depth = batch()
        losses = model.loss(o, d, rgb, depth, generator)
        total = losses["total"]
        for opt in optimizers.values():
            opt.zero_grad()
        value = float(total.detach())
        if not math.isfinite(value) or not total.requires_grad:
            res.skipped += 1
            continue
        if early_stop and stop.update(value):
            break  # as the original: the loss that ends mapping takes no step
        total.backward()
        for opt in optimizers.values():
            opt.step()
        res.losses.append(value)
        res.psnr.append(float(psnr_from_mse(float(losses["mse"]))) if float(losses["mse"]) > 0 else float("nan"))
        res.depth_l1.append(float(losses["depth_l1"]))
    return res
