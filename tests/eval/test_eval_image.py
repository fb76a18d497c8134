"""PSNR / SSIM / depth L1 against hand computations and scikit-image."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage import data as skdata
from skimage.metrics import structural_similarity
from skimage.transform import resize

from inrslam.eval.image import depth_l1, lpips_available, psnr, ssim


def sk_ssim(a, b):
    kw = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0)
    if a.ndim == 3:
        kw["channel_axis"] = -1
    return structural_similarity(np.asarray(a, np.float64), np.asarray(b, np.float64), **kw)


def test_psnr_hand_computed():
    target = np.full((8, 10, 3), 0.6)
    pred = np.full((8, 10, 3), 0.5)  # MSE = 0.01 -> 20 dB
    assert psnr(pred, target) == pytest.approx(20.0, abs=1e-10)
    pred[..., 0] = 0.6  # errors 0, 0.1, 0.1 -> MSE = 0.02/3
    assert psnr(pred, target) == pytest.approx(-10 * np.log10(0.02 / 3), abs=1e-10)
    assert psnr(target, target) == float("inf")


def test_psnr_mask_selects_pixels_and_accepts_torch(device):
    target = torch.zeros(6, 6, 3, device=device)
    pred = torch.full((6, 6, 3), 0.01, device=device)  # MSE 1e-4 -> 40 dB
    pred[:, :3] = 1.0  # terrible left half, masked out
    mask = torch.zeros(6, 6, dtype=torch.bool, device=device)
    mask[:, 3:] = True
    assert psnr(pred, target, mask) == pytest.approx(40.0, abs=1e-6)
    assert psnr(pred, target) < 5.0


@pytest.mark.parametrize("seed", [0, 1])
def test_ssim_matches_skimage_random(seed):
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 1, (37, 53, 3))
    b = np.clip(a + rng.normal(0, 0.15, a.shape), 0, 1)
    assert ssim(a, b) == pytest.approx(sk_ssim(a, b), abs=1e-6)
    c = rng.uniform(0, 1, (37, 53, 3))  # unrelated image: SSIM near 0
    assert ssim(a, c) == pytest.approx(sk_ssim(a, c), abs=1e-6)


def test_ssim_matches_skimage_structured():
    img = resize(skdata.astronaut(), (96, 128), anti_aliasing=True)  # float64 in [0, 1]
    rng = np.random.default_rng(3)
    blurred = resize(resize(img, (48, 64), anti_aliasing=True), (96, 128))  # loses detail
    noisy = np.clip(img + rng.normal(0, 0.05, img.shape), 0, 1)
    shifted = np.roll(img, 2, axis=1)
    for other in (blurred, noisy, shifted):
        assert ssim(img, other) == pytest.approx(sk_ssim(img, other), abs=1e-6)
    grey = resize(skdata.camera() / 255.0, (80, 80), anti_aliasing=True)
    grey2 = np.clip(grey * 0.8 + 0.1, 0, 1)  # contrast + brightness change
    assert ssim(grey, grey2) == pytest.approx(sk_ssim(grey, grey2), abs=1e-6)
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    # float32 torch input gives the float64 answer
    t = torch.from_numpy(img.astype(np.float32))
    assert ssim(t, torch.from_numpy(noisy.astype(np.float32))) == pytest.approx(
        sk_ssim(img.astype(np.float32), noisy.astype(np.float32)), abs=1e-6)


def test_ssim_rejects_tiny_images():
    with pytest.raises(ValueError, match="11x11"):
        ssim(np.zeros((10, 20, 3)), np.zeros((10, 20, 3)))


def test_depth_l1_ignores_invalid_target():
    target = np.array([[1.0, 2.0, 0.0], [np.nan, 3.0, 0.0]])
    pred = np.array([[1.5, 2.0, 99.0], [99.0, 2.0, 99.0]])  # errors on valid pixels: 0.5, 0, 1
    assert depth_l1(pred, target) == pytest.approx(0.5)
    assert depth_l1(pred, target, mask=np.array([[True, False, True], [True, True, True]])) == pytest.approx(0.75)
    assert np.isnan(depth_l1(pred, np.zeros_like(target)))


def test_lpips_reports_unavailable_with_reason():
    ok, reason = lpips_available()
    assert isinstance(ok, bool) and isinstance(reason, str) and reason
    try:
        import lpips  # noqa: F401
    except ImportError:
        assert ok is False and "lpips" in reason.lower()
