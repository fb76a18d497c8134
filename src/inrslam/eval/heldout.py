"""Held-out image metrics: full frames rendered *without* the measured depth, compared with the observations."""

from __future__ import annotations

from typing import Callable

import numpy as np

from inrslam.eval.image import depth_l1, psnr, ssim


def heldout_metrics(render: Callable, dataset, poses, every: int, max_frames: int, offset: int = 0) -> dict:
    """PSNR / SSIM / depth L1 of frames offset, offset + every, ... (at most `max_frames`); an offset between
    keyframes keeps the evaluated frames out of the keyframe ray store.

    Args:
        render: (c2w (4,4) tensor, intrinsics) -> (rgb (H,W,3) in [0,1], depth (H,W) metres), tensors or arrays.
        dataset: the run's dataset (frames give the observed rgb / depth).
        poses: (N, 4, 4) estimated c2w used for rendering (the estimate, not the ground truth).
    Returns:
        dict(psnr_db, ssim, depth_l1_m, heldout_frames).
    """
    idx = list(range(min(offset, len(dataset) - 1), len(dataset), every))[:max_frames]
    ps, ss, dl = [], [], []
    for i in idx:
        frame = dataset[i]
        rgb, depth = render(poses[i], frame.intrinsics)
        rgb = np.clip(_np(rgb), 0.0, 1.0)
        ps.append(float(psnr(rgb, frame.rgb)))
        ss.append(float(ssim(rgb, frame.rgb)))
        if (frame.depth > 0).any():
            dl.append(float(depth_l1(_np(depth), frame.depth)))
    return {"psnr_db": float(np.mean(ps)) if ps else None, "ssim": float(np.mean(ss)) if ss else None,
            "depth_l1_m": float(np.mean(dl)) if dl else None, "heldout_frames": idx}


def _np(x):
    return x.detach().float().cpu().numpy() if hasattr(x, "detach") else np.asarray(x, dtype=np.float32)
