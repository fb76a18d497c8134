"""Image metrics: PSNR, SSIM, depth L1 (torch, device-agnostic; numpy arrays accepted), LPIPS availability.

Images are RGB in [0, 1], shape (H, W, 3) (or (H, W) grey); depth maps are metres, (H, W), 0 = invalid.
Every function returns a Python float. Maths runs in float64 on the input's device.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

ArrayLike = Union[np.ndarray, Tensor]


def _t(x: ArrayLike, device: Optional[torch.device] = None) -> Tensor:
    if isinstance(x, Tensor):
        t = x.detach()
        return t.to(device=device if device is not None else t.device, dtype=torch.float64)
    return torch.as_tensor(np.asarray(x), dtype=torch.float64, device=device)


def psnr(pred: ArrayLike, target: ArrayLike, mask: Optional[ArrayLike] = None) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (data range 1).

        MSE = mean over selected pixels and channels of (pred − target)²,   PSNR = −10 log10(MSE)

    Args:
        pred, target: (H, W, C) or (H, W) images in [0, 1] (numpy or torch), same shape.
        mask: optional (H, W) bool; only these pixels count.
    Returns:
        PSNR in dB (inf for identical images, NaN when the mask selects nothing).
    """
    p = _t(pred)
    t = _t(target, p.device)
    if p.shape != t.shape:
        raise ValueError(f"psnr: shapes differ, pred {tuple(p.shape)} vs target {tuple(t.shape)}")
    d2 = (p - t) ** 2
    if mask is not None:
        m = _t(mask, p.device).bool()
        if tuple(m.shape) != tuple(p.shape[:2]):
            raise ValueError(f"psnr: mask shape {tuple(m.shape)} does not match image {tuple(p.shape[:2])}")
        d2 = d2[m]
    if d2.numel() == 0:
        return float("nan")
    mse = float(d2.mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def gaussian_window_1d(sigma: float = 1.5, radius: int = 5, device=None) -> Tensor:
    """(2r+1,) normalised Gaussian taps w_k ∝ exp(−k² / 2σ²), k = −r..r (float64); r = 5, σ = 1.5 -> 11 taps."""
    k = torch.arange(-radius, radius + 1, dtype=torch.float64, device=device)
    w = torch.exp(-0.5 * (k / sigma) ** 2)
    return w / w.sum()


def ssim(pred: ArrayLike, target: ArrayLike, data_range: float = 1.0) -> float:
    """Structural similarity (Wang, Bovik, Sheikh, Simoncelli, TIP 2004), mean over the image, channels averaged.

    Local statistics with an 11-tap Gaussian window (σ = 1.5), population (co)variances:
        SSIM(x, y) = (2 μx μy + C1)(2 σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2)),
        C1 = (0.01 L)², C2 = (0.03 L)², L = data_range.
    The mean is taken over pixels at least 5 px (the window radius) from the border, exactly as
    `skimage.metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    data_range=1, channel_axis=-1)`; there, the border strip is cropped after filtering, so computing only the
    "valid" positions (no padding) gives identical numbers.

    Args:
        pred, target: (H, W, C) or (H, W), same shape, H, W >= 11.
        data_range: L, 1 for images in [0, 1].
    Returns:
        SSIM in [−1, 1] (1 for identical images).
    """
    p = _t(pred)
    t = _t(target, p.device)
    if p.shape != t.shape:
        raise ValueError(f"ssim: shapes differ, pred {tuple(p.shape)} vs target {tuple(t.shape)}")
    if p.dim() == 2:
        p, t = p[..., None], t[..., None]
    if p.dim() != 3:
        raise ValueError(f"ssim: expected (H, W) or (H, W, C) images, got {tuple(p.shape)}")
    H, W, C = p.shape
    radius = 5
    if H < 2 * radius + 1 or W < 2 * radius + 1:
        raise ValueError(f"ssim: image {H}x{W} is smaller than the 11x11 window")
    w = gaussian_window_1d(1.5, radius, p.device)
    wy = w.view(1, 1, -1, 1)
    wx = w.view(1, 1, 1, -1)

    def filt(x: Tensor) -> Tensor:  # (C, 1, H, W) -> (C, 1, H-10, W-10), separable valid convolution
        return F.conv2d(F.conv2d(x, wy), wx)

    x = p.permute(2, 0, 1)[:, None]
    y = t.permute(2, 0, 1)[:, None]
    mx, my = filt(x), filt(y)
    vx = filt(x * x) - mx * mx
    vy = filt(y * y) - my * my
    vxy = filt(x * y) - mx * my
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return float(s.mean(dim=(1, 2, 3)).mean())


def depth_l1(pred: ArrayLike, target: ArrayLike, mask: Optional[ArrayLike] = None) -> float:
    """Mean absolute depth error in metres over pixels with valid target depth.

        L1 = (1/|V|) Σ_{p ∈ V} |D̂(p) − D(p)|,   V = {p : D(p) > 0 and finite} (∩ mask)

    Args:
        pred: (H, W) rendered / predicted depth, metres.
        target: (H, W) measured depth, metres, 0 (or non-finite) = invalid.
        mask: optional (H, W) bool restricting V further.
    Returns:
        metres (NaN when no pixel is valid).
    """
    p = _t(pred)
    t = _t(target, p.device)
    if p.shape != t.shape:
        raise ValueError(f"depth_l1: shapes differ, pred {tuple(p.shape)} vs target {tuple(t.shape)}")
    valid = torch.isfinite(t) & (t > 0)
    if mask is not None:
        valid &= _t(mask, p.device).bool()
    if not bool(valid.any()):
        return float("nan")
    return float((p[valid] - t[valid]).abs().mean())


def lpips_available() -> tuple[bool, str]:
    """Whether LPIPS (Zhang et al., CVPR 2018) can be computed offline here. Returns (available, reason).

    LPIPS needs the `lpips` package, its linear-layer weights (shipped inside the package) and the ImageNet
    backbone weights (torchvision AlexNet) already in the torch hub cache. inrslam never downloads weights, so
    without all three LPIPS is reported as unavailable (and metrics leave it out) with the reason.
    """
    spec = importlib.util.find_spec("lpips")
    if spec is None or spec.origin is None:
        return False, ("LPIPS unavailable: the 'lpips' package is not installed (inrslam does not download it or its "
                       "weights)")
    lin = Path(spec.origin).parent / "weights" / "v0.1" / "alex.pth"
    if not lin.is_file():
        return False, f"LPIPS unavailable: linear-layer weights not found at {lin}"
    hub = Path(torch.hub.get_dir()) / "checkpoints"
    if not any(hub.glob("alexnet-*.pth")):
        return False, f"LPIPS unavailable: AlexNet backbone weights not in the torch hub cache {hub} (not downloaded)"
    return True, "LPIPS available (lpips package with local AlexNet weights)"
