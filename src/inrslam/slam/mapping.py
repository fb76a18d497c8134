"""Mapping with global bundle adjustment over the keyframe ray store (docs/spec.md §7.5)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping

import torch
from torch import Tensor

from inrslam.rendering.losses import depth_l1, psnr_from_mse
from inrslam.slam.config import SlamConfig
from inrslam.slam.keyframes import KeyframeStore
from inrslam.slam.model import SceneModel
from inrslam.slam.poses import PoseSet, ray_poses

Optimizers = Mapping[str, torch.optim.Optimizer]  # the scene optimisers of `SceneModel.make_optimizers`
# n -> dirs_cam (n,3), rgb (n,3), depth (n,) metres[, behind (n,) units of T or None]
CurrentRays = Callable[[int], tuple[Tensor, ...]]
FrameRays = Callable[[int], tuple[Tensor, ...]]  # n -> c2w (4,4), dirs_cam, rgb, depth[, behind or None]


@dataclass
class MapResult:
    kf_c2w: Tensor  # (K, 4, 4) refined keyframe poses
    cur_c2w: Tensor  # (4, 4) refined current pose
    skipped: int = 0  # iterations whose loss was not finite (no step taken)
    psnr: list[float] = field(default_factory=list)  # per-iteration batch PSNR (dB)
    depth_l1: list[float] = field(default_factory=list)  # per-iteration batch depth L1 (m), iterations with depth
    losses: list[float] = field(default_factory=list)  # per-iteration total loss


def map_frame(model: SceneModel, optimizers: Optimizers, store: KeyframeStore, kf_c2w: Tensor, cur_c2w: Tensor,
              cur_rays: CurrentRays, cfg: SlamConfig, generator: torch.Generator) -> MapResult:
    """Jointly optimise the scene (every iteration) and keyframe + current poses (every `ba_pose_every`).

    Args:
        model: the scene; optimizers: its scene optimisers (from `make_optimizers`), stepped every iteration.
        store: the keyframe ray store with K >= 1 keyframes; kf_c2w: (K, 4, 4) their current poses (metres).
        cur_c2w: (4, 4) current frame pose; cur_rays: n -> (dirs_cam (n,3), rgb (n,3), depth (n,)[, behind (n,)])
            uniform over the current frame (behind: per-ray SDF band ends, when the store holds them too).
        cfg: mapping settings (`map_iters`, `map_pixels`, `map_current_min`, `bundle_adjust`, `ba_lr`,
            `ba_pose_every`, `pose_param`).
        generator: ray-sampling and jitter generator.
    Returns: the refined poses (keyframe 0 fixed) and per-iteration PSNR / depth L1 / loss.
    """
    K = len(store)
    do_ba = cfg.bundle_adjust and K >= 2
    all_c2w = torch.cat([kf_c2w, cur_c2w[None]])  # slot K = current frame
    poses = PoseSet(all_c2w[1:], cfg.pose_param) if do_ba else None  # keyframe 0 fixed
    pose_opt = torch.optim.Adam(poses.parameters(), lr=cfg.ba_lr) if poses is not None else None
    n_cur = max(cfg.map_pixels // K, cfg.map_current_min)
    res = MapResult(kf_c2w.clone(), cur_c2w.clone())
    for it in range(1, cfg.map_iters + 1):
        idx = store.sample_index(cfg.map_pixels, generator)
        slot, dirs_kf, rgb_kf, depth_kf = store.take(idx)
        dirs_c, rgb_c, depth_c, *behind_c = cur_rays(n_cur)
        slots = torch.cat([slot, torch.full((dirs_c.shape[0],), K, dtype=torch.long, device=slot.device)])
        mats = torch.cat([all_c2w[:1], poses.matrices()]) if poses is not None else all_c2w
        c2w = ray_poses(mats, slots)
        losses, out = model.loss(c2w, torch.cat([dirs_kf, dirs_c]), torch.cat([rgb_kf, rgb_c]),
                                 torch.cat([depth_kf, depth_c]), generator,
                                 behind=_join_behind(store.behind_of(idx), behind_c, depth_kf, depth_c))
        if not optimisation_step(losses["total"], optimizers):
            res.skipped += 1
            continue
        if pose_opt is not None and it % cfg.ba_pose_every == 0:
            pose_opt.step()
            pose_opt.zero_grad(set_to_none=True)
        with torch.no_grad():
            d = torch.cat([depth_kf, depth_c])
            res.psnr.append(float(psnr_from_mse(losses["color"])))
            if bool((d > 0).any()):
                res.depth_l1.append(float(depth_l1(out.depth, d)))
            res.losses.append(float(losses["total"].detach()))
    if poses is not None:
        with torch.no_grad():
            mats = torch.cat([all_c2w[:1], poses.matrices()])
        res.kf_c2w, res.cur_c2w = mats[:K].detach().clone(), mats[K].detach().clone()
    return res


def refit(model: SceneModel, optimizers: Optimizers, store: KeyframeStore, kf_c2w: Tensor, iters: int,
          n_pixels: int, generator: torch.Generator) -> list[float]:
    """Re-fit the scene to every keyframe's stored rays at (K, 4, 4) poses `kf_c2w` (after a loop closure moved
    them): `iters` iterations of `n_pixels` rays drawn over the whole store, poses fixed. Returns the losses."""
    hist: list[float] = []
    for _ in range(iters):
        idx = store.sample_index(n_pixels, generator)
        slot, dirs, rgb, depth = store.take(idx)
        losses, _ = model.loss(ray_poses(kf_c2w, slot), dirs, rgb, depth, generator, behind=store.behind_of(idx))
        if optimisation_step(losses["total"], optimizers):
            hist.append(float(losses["total"].detach()))
    return hist


def initialise(model: SceneModel, optimizers: Optimizers, frame_rays: FrameRays, iters: int, n_pixels: int,
               generator: torch.Generator | None, stop_window: int = 0, stop_tol: float = 0.0) -> list[float]:
    """Fit the scene to the first frame (pose fixed) for `iters` iterations of `n_pixels` fresh random rays, or
    fewer: with `stop_window` > 0, until `loss_plateaued(hist, stop_window, stop_tol)`.

    Args:
        model, optimizers: as `map_frame`.
        frame_rays: n -> (c2w (4,4), dirs_cam (n,3), rgb (n,3), depth (n,) metres[, behind (n,) or None]).
        generator: sample-jitter generator (None: the global one).
    Returns: the loss of every iteration run.
    """
    hist: list[float] = []
    for _ in range(iters):
        c2w, dirs, rgb, depth, *rest = frame_rays(n_pixels)
        losses, _ = model.loss(c2w, dirs, rgb, depth, generator, behind=rest[0] if rest else None)
        optimisation_step(losses["total"], optimizers)
        hist.append(float(losses["total"].detach()))
        if stop_window > 0 and loss_plateaued(hist, stop_window, stop_tol):
            break
    return hist


def loss_plateaued(hist: list[float], window: int, tol: float) -> bool:
    """Whether a noisy loss history has stopped falling: checked every `window` iterations, once there are two full
    windows, true when the mean of the last `window` losses is less than `tol` (relative) below the mean of the
    `window` before (non-finite losses are left out; a window without a finite one is not a plateau). Example:
    loss 0.9^k, window 10: the ratio of two consecutive window means is 0.9^10 = 0.35, never a plateau at tol 0.01."""
    n = len(hist)
    if window < 1 or n < 2 * window or n % window:
        return False
    last = [x for x in hist[n - window:] if math.isfinite(x)]
    before = [x for x in hist[n - 2 * window:n - window] if math.isfinite(x)]
    if not last or not before:
        return False
    m_last, m_before = sum(last) / len(last), sum(before) / len(before)
    return m_last > (1.0 - tol) * m_before


def _join_behind(kf: Tensor | None, cur: list[Tensor], depth_kf: Tensor, depth_c: Tensor) -> Tensor | None:
    """Per-ray band ends of a keyframe + current batch (`cur`: [] or [(n,)]): None if neither part has them, else 1
    where one part is missing."""
    if kf is None and not cur:
        return None
    return torch.cat([torch.ones_like(depth_kf) if kf is None else kf, cur[0] if cur else torch.ones_like(depth_c)])


def optimisation_step(loss: Tensor, optimizers: Optimizers) -> bool:
    """Backward and step every optimiser, unless the loss is not finite (then nothing changes: a NaN never
    reaches the map). Returns whether a step was taken."""
    for opt in optimizers.values():
        opt.zero_grad()
    if not bool(torch.isfinite(loss.detach())):
        return False
    loss.backward()
    for opt in optimizers.values():
        opt.step()
    return True
