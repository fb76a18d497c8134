"""Losses (spec §6, supplementary Eqs. (1)-(6)) on tiny hand-computed inputs."""

from __future__ import annotations

import math

import pytest
import torch

from inrslam.rendering import LossConfig, LossReduction, RenderOutput, compute_losses, depth_l1, psnr_from_mse
from inrslam.rendering.losses import masked_sample_mean, sdf_masks

T = 0.1


def _batch():
    """3 rays x 5 samples. Ray 0: D = 1, ray 1: D = 2, ray 2: no depth.

    ray 0: z = .5 .8 (front) | .93 (tail) .98 (centre) 1.06 (tail); s = 1, .5 | .6 | .1 | -.5
           fs: (1-1)^2 = 0, (.5-1)^2 = .25; centre: (.98+.01-1)^2 = 1e-4;
           tail: (.93+.06-1)^2 = 1e-4, (1.06-.05-1)^2 = 1e-4
    ray 1: z = .5 1 1.5 (front) | 1.95 (tail) | 2.2 (behind, unsupervised); s = 1 .8 1 | .2 | -1
           fs: 0, .04, 0; tail: (1.95+.02-2)^2 = 9e-4
    """
    z = torch.tensor([[0.5, 0.8, 0.93, 0.98, 1.06], [0.5, 1.0, 1.5, 1.95, 2.2], [0.5, 1.0, 1.5, 2.0, 2.5]],
                     dtype=torch.float64)
    sdf = torch.tensor([[1.0, 0.5, 0.6, 0.1, -0.5], [1.0, 0.8, 1.0, 0.2, -1.0], [5.0, 5.0, 5.0, 5.0, 5.0]],
                       dtype=torch.float64, requires_grad=True)
    rgb = torch.zeros(3, 3, dtype=torch.float64, requires_grad=True)
    depth = torch.tensor([1.1, 1.8, 3.0], dtype=torch.float64, requires_grad=True)
    out = RenderOutput(rgb=rgb, depth=depth, opacity=torch.ones(3), depth_var=torch.zeros(3),
                       weights=torch.zeros(3, 5), sdf=sdf, z=z)
    target_rgb = torch.tensor([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0], [0.5, 0.5, 0.5]], dtype=torch.float64)
    target_depth = torch.tensor([1.0, 2.0, 0.0], dtype=torch.float64)
    return out, target_rgb, target_depth


def test_masks():
    out, _, D = _batch()
    front, center, tail = sdf_masks(out.z, D, T, 0.4)
    assert front.tolist() == [[True, True, False, False, False], [True, True, True, False, False], [False] * 5]
    assert center.tolist() == [[False, False, False, True, False], [False] * 5, [False] * 5]
    assert tail.tolist() == [[False, False, True, False, True], [False, False, False, True, False], [False] * 5]


def test_mask_boundaries():
    z = torch.tensor([[0.75, 0.875, 0.96875, 0.984375, 1.125]])  # exact binary fractions; T = 0.125
    front, center, tail = sdf_masks(z, torch.tensor([1.0]), 0.125, 0.25)
    # z = D - T is not front (strict) but tail (closed band); |z - D| = .25 T is not centre (strict); z = D + T tail
    assert front.tolist() == [[True, False, False, False, False]]
    assert center.tolist() == [[False, False, False, True, False]]
    assert tail.tolist() == [[False, True, True, False, True]]



def test_behind_band_ends_the_sdf_terms_behind_the_depth():
    # T = 0.125, D = 1: samples at D - T, D - T/8, D + T/8, D + T/4, D + T/2, D + T (exact binary fractions)
    z = torch.tensor([[0.875, 0.984375, 1.015625, 1.03125, 1.0625, 1.125]])
    D = torch.tensor([1.0])
    full = sdf_masks(z, D, 0.125, 0.25)
    assert all(torch.equal(a, b) for a, b in zip(full, sdf_masks(z, D, 0.125, 0.25, 1.0)))  # 1 = the paper's band
    front, center, tail = sdf_masks(z, D, 0.125, 0.25, 0.25)  # up to D + T/4 only
    assert center.tolist() == [[False, True, True, False, False, False]]
    assert tail.tolist() == [[True, False, False, True, False, False]]  # D + T/4 is kept (closed), beyond dropped
    assert torch.equal(front, full[0])  # free space in front is unchanged
    assert not sdf_masks(z, D, 0.125, 0.25, 0.0)[2][0, 3:].any()  # 0: nothing behind the surface
    # compute_losses honours LossConfig.behind: ray 0's sample 6 cm (0.6 T) behind its depth trains only with the band
    for behind, trained in ((1.0, True), (0.3, False)):
        out, rgb, D = _batch()
        compute_losses(out, rgb, D, LossConfig(behind=behind), T)["total"].backward()
        assert bool(out.sdf.grad[0, 4] != 0) is trained and bool(out.sdf.grad[0, 2] != 0)

def test_per_ray_reduction_hand_computed():
    out, rgb, D = _batch()
    L = compute_losses(out, rgb, D, LossConfig(), T)
    color = (0.01 + 0.04 + 0.09 + 3 * 0.25) / 9
    depth = (0.1**2 + 0.2**2) / 2
    fs = (0.25 / 2 + 0.04 / 3) / 2
    center = 1e-4
    tail = ((1e-4 + 1e-4) / 2 + 9e-4) / 2
    expected = dict(color=color, depth=depth, free_space=fs, center=center, tail=tail,
                    total=5 * color + depth + 10 * fs + 50 * center + 200 * tail)
    for k, v in expected.items():
        assert L[k].item() == pytest.approx(v, rel=1e-9, abs=1e-15), k


def test_global_reduction_hand_computed():
    out, rgb, D = _batch()
    L = compute_losses(out, rgb, D, LossConfig(reduction=LossReduction.GLOBAL), T)
    assert L["free_space"].item() == pytest.approx((0.25 + 0.04) / 5)
    assert L["center"].item() == pytest.approx(1e-4)
    assert L["tail"].item() == pytest.approx((1e-4 + 1e-4 + 9e-4) / 3)
    assert L["depth"].item() == pytest.approx(0.025)


def test_loss_variant_free_space_target_and_weights():
    out, rgb, D = _batch()
    cfg = LossConfig(free_space_target=0.1, color=0.0, depth=0.0, free_space=2.0, center=0.0, tail=0.0)
    L = compute_losses(out, rgb, D, cfg, T)
    fs = ((0.81 + 0.16) / 2 + (0.81 + 0.49 + 0.81) / 3) / 2
    assert L["free_space"].item() == pytest.approx(fs)
    assert L["total"].item() == pytest.approx(2 * fs)


def test_center_band_option():
    out, rgb, D = _batch()
    L = compute_losses(out, rgb, D, LossConfig(center_band=1.0), T)  # every band sample is 'centre'
    assert L["tail"].item() == 0.0
    assert L["center"].item() == pytest.approx(((1e-4 * 3) / 3 + 9e-4) / 2)


def test_gradients_only_from_masked_samples():
    out, rgb, D = _batch()
    compute_losses(out, rgb, D, LossConfig(), T)["total"].backward()
    g = out.sdf.grad
    assert torch.isfinite(g).all()
    assert (g[2] == 0).all()  # ray without depth: no SDF supervision
    assert g[1, 4] == 0  # behind the band: unsupervised
    assert g[0, 0] == 0  # front sample already at the target
    assert (g[0, 1:4] != 0).all()
    assert out.depth.grad[2] == 0 and out.depth.grad[0] != 0


def test_empty_masks_give_zero_not_nan():
    out, rgb, _ = _batch()
    for red in LossReduction:
        L = compute_losses(out, rgb, torch.zeros(3, dtype=torch.float64), LossConfig(reduction=red), T)
        for k in ("depth", "free_space", "center", "tail"):
            assert L[k].item() == 0.0
        assert L["total"].item() == pytest.approx(5 * L["color"].item())
        L["total"].backward()
        assert torch.isfinite(out.sdf.grad).all() and torch.isfinite(out.rgb.grad).all()
        out.sdf.grad = None
        out.rgb.grad = None
    empty = torch.zeros(0, 4)
    assert masked_sample_mean(empty, empty > 0, LossReduction.PER_RAY).item() == 0.0


def test_masked_sample_mean_docstring_example():
    v = torch.tensor([[1.0, 3.0, 8.0], [5.0, 5.0, 5.0]])
    m = torch.tensor([[True, True, False], [True, False, False]])
    assert masked_sample_mean(v, m, LossReduction.PER_RAY).item() == pytest.approx(3.5)
    assert masked_sample_mean(v, m, LossReduction.GLOBAL).item() == pytest.approx(3.0)


def test_psnr_and_depth_l1():
    assert psnr_from_mse(0.01) == pytest.approx(20.0)
    assert psnr_from_mse(torch.tensor(1e-3)).item() == pytest.approx(30.0)
    assert math.isfinite(psnr_from_mse(0.0))
    assert depth_l1(torch.tensor([1.1, 1.8, 3.0]), torch.tensor([1.0, 2.0, 0.0])).item() == pytest.approx(0.15)
    assert depth_l1(torch.tensor([1.0]), torch.tensor([0.0])).item() == 0.0


def test_sdf_terms_off_for_non_sdf_renderers():
    out, rgb, D = _batch()
    on = compute_losses(out, rgb, D, LossConfig(), T)
    off = compute_losses(out, rgb, D, LossConfig(), T, sdf_terms=False)
    assert set(off) == set(on)
    for k in ("free_space", "center", "tail"):
        assert on[k].item() > 0
        assert torch.is_tensor(off[k]) and off[k].item() == 0.0 and off[k].dtype == out.sdf.dtype
    assert off["color"].item() == on["color"].item() and off["depth"].item() == on["depth"].item()
    cfg = LossConfig()
    assert off["total"].item() == pytest.approx(cfg.color * on["color"].item() + cfg.depth * on["depth"].item())
    assert off["total"].item() < on["total"].item()
    off["total"].backward()
    assert out.sdf.grad is None  # the scalar is only supervised through the rendered colour / depth
    assert out.rgb.grad is not None and out.depth.grad is not None
