"""Held-out image metrics: full frames rendered *without* the measured depth, compared with the observations."""

from __future__ import annotations

from typing import Callable

import numpy as np

from inrslam.eval.image import depth_l1, psnr, ssim
from inrslam.status import logger, progress

log = logger(__name__)

DEPTH_ERROR_MAX = 0.10  # metres: the top of the error colour scale of the panels


def heldout_panel(gt_rgb: np.ndarray, rgb: np.ndarray, depth: np.ndarray, gt_depth: np.ndarray) -> np.ndarray:
    """One held-out frame as a picture: observed colour | rendered colour | rendered depth | |depth error|.

    Args: gt_rgb, rgb: (H, W, 3) in [0, 1]; depth, gt_depth: (H, W) metres (gt 0 = no measurement).
    Returns: (H, 4W, 3) uint8. Depth shares one scale, 0 .. the largest observed depth ('turbo'); the error runs
    0 .. DEPTH_ERROR_MAX ('magma'); pixels without a measurement are black in the error panel.
    """
    from matplotlib import colormaps

    valid = gt_depth > 0
    top = float(gt_depth[valid].max()) if valid.any() else max(float(np.nanmax(depth)), 1e-6)
    depth_rgb = colormaps["turbo"](np.clip(np.nan_to_num(depth) / top, 0.0, 1.0))[..., :3]
    err = np.where(valid, np.abs(np.nan_to_num(depth) - gt_depth), 0.0)
    err_rgb = colormaps["magma"](np.clip(err / DEPTH_ERROR_MAX, 0.0, 1.0))[..., :3] * valid[..., None]
    panel = np.concatenate([np.clip(gt_rgb, 0, 1), np.clip(rgb, 0, 1), depth_rgb, err_rgb], axis=1)
    return (panel * 255.0 + 0.5).astype(np.uint8)


def heldout_frames(n: int, every: int, max_frames: int, offset: int = 0) -> list[int]:
    """Frame indices of the held-out renders of an n-frame sequence: offset, offset + every, ... (offset clipped to
    the last frame); when there are more than `max_frames`, `max_frames` of them evenly spread from the first to
    the last, so that the whole sequence is judged, not its beginning. Example: n=320, every=10, max 20, offset 2:
    2, 12, ..., 312 are 32 candidates; picked: 2, 22, 32, 52, ..., 292, 312 (the first, the last and 18 evenly
    between)."""
    cand = list(range(min(offset, n - 1), n, every)) if n > 0 and every > 0 else []
    if max_frames <= 0:
        return []
    if len(cand) <= max_frames:
        return cand
    if max_frames == 1:
        return cand[:1]
    return [cand[round(k * (len(cand) - 1) / (max_frames - 1))] for k in range(max_frames)]


def heldout_metrics(render: Callable, dataset, poses, every: int, max_frames: int, offset: int = 0,
                    sink: Callable[[int, np.ndarray], None] | None = None) -> dict:
    """PSNR / SSIM / depth L1 of the frames `heldout_frames` picks (offset, offset + every, ..., at most
    `max_frames` of them spread over the sequence); an offset between keyframes keeps them out of the keyframe ray
    store.

    Args:
        render: (c2w (4,4) tensor, intrinsics) -> (rgb (H,W,3) in [0,1], depth (H,W) metres), tensors or arrays.
        dataset: the run's dataset (frames give the observed rgb / depth).
        poses: (N, 4, 4) estimated c2w used for rendering (the estimate, not the ground truth).
        sink: called with (frame index, `heldout_panel` picture) for every rendered frame (to save it).
    Returns:
        dict(psnr_db, ssim, depth_l1_m, heldout_frames), and depth_l1_true_m (against the noise-free depth,
        `true_depth_of`) when the dataset knows it (the built-in scenes).
    """
    idx = heldout_frames(len(dataset), every, max_frames, offset)
    ps, ss, dl, dt = [], [], [], []
    for k, i in enumerate(idx):
        frame = dataset[i]
        rgb, depth = render(poses[i], frame.intrinsics)
        rgb, depth = np.clip(_np(rgb), 0.0, 1.0), _np(depth)
        ps.append(float(psnr(rgb, frame.rgb)))
        ss.append(float(ssim(rgb, frame.rgb)))
        if (frame.depth > 0).any():
            dl.append(float(depth_l1(depth, frame.depth)))
        true = true_depth_of(dataset, i)
        if true is not None and (true > 0).any():
            dt.append(float(depth_l1(depth, true)))
        if sink is not None:
            sink(i, heldout_panel(frame.rgb, rgb, depth, frame.depth))
        progress(log, "renders", k + 1, len(idx))
    out = {"psnr_db": float(np.mean(ps)) if ps else None, "ssim": float(np.mean(ss)) if ss else None,
           "depth_l1_m": float(np.mean(dl)) if dl else None, "heldout_frames": idx}
    if dt and len(dt) == len(idx):
        out["depth_l1_true_m"] = float(np.mean(dt))
    return out


def true_depth_of(dataset, i: int) -> np.ndarray | None:
    """(H, W) noise-free depth of frame i in metres (0 = none) when the dataset knows it (`true_depth(i)`: the
    built-in scenes, before their sensor noise and holes), else None."""
    fn = getattr(dataset, "true_depth", None)
    return None if fn is None else fn(i)


def _np(x):
    return x.detach().float().cpu().numpy() if hasattr(x, "detach") else np.asarray(x, dtype=np.float32)
