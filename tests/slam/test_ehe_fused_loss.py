"""The fused EHE compositing + loss (`inrslam.slam.ehe.fused_loss`) against its reference, the torch path
(`render_samples` + `ehe_losses`): values and gradients on random inputs, float64 gradcheck, analytic cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.slam.ehe.config import EheConfig
from inrslam.slam.ehe.fused_loss import fused_losses, fused_weights
from inrslam.slam.ehe.model import EheModel
from inrslam.slam.ehe.rendering import packed_direct_weights

UNIT = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]])


def ray_starts(ray, n_rays: int):
    """(R + 1,) offsets of each ray's samples in a packed, ray-sorted (N,) `ray` index."""
    counts = torch.bincount(ray, minlength=n_rays)
    return torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)])


def random_packed(seed: int, R: int = 30, S: int = 10, dtype=torch.float64):
    """Packed samples of R rays (0..S each, sorted z, SDF crossing zero on many rays), colour logits for a random
    half of them, observed colour and depth (some rays without depth)."""
    g = torch.Generator().manual_seed(seed)
    count = torch.randint(0, S + 1, (R,), generator=g)
    ray = torch.repeat_interleave(torch.arange(R), count)
    N = ray.numel()
    z = 0.5 + torch.rand(R, 1, generator=g, dtype=dtype)[ray, 0] + torch.rand(N, generator=g, dtype=dtype) * 0.01
    z = z + torch.cat([torch.zeros(1, dtype=dtype), torch.cumsum(torch.full((N - 1,), 0.01, dtype=dtype), 0)])
    start = ray_starts(ray, R)
    z = z - z[start[:-1].clamp_max(N - 1)][ray] + 1.0 + 0.3 * torch.rand(R, generator=g, dtype=dtype)[ray]
    sdf = (torch.rand(R, generator=g, dtype=dtype)[ray] * 2 - 0.5) - 20.0 * (z - z[start[:-1].clamp_max(N - 1)][ray])
    sdf = sdf + 0.1 * torch.randn(N, generator=g, dtype=dtype)
    use = torch.nonzero(torch.rand(N, generator=g) < 0.6).reshape(-1)
    crow = torch.full((N,), -1, dtype=torch.int64)
    crow[use] = torch.arange(use.numel())
    logits = torch.randn(use.numel(), 3, generator=g, dtype=dtype)
    rgb = torch.rand(R, 3, generator=g, dtype=dtype)
    depth = 1.0 + 0.4 * torch.rand(R, generator=g, dtype=dtype)
    has_d = (count > 0) & (torch.rand(R, generator=g) < 0.8)
    return sdf, logits, z, ray, start, crow, use, rgb, depth, has_d


def reference_terms(sdf, logits, z, ray, use, rgb, depth, has_d, T):
    """The torch path on packed samples: `packed_direct_weights`, the composites and `ehe_losses`' four terms."""
    R = rgb.shape[0]
    w = packed_direct_weights(sdf, z, ray, R, T)
    col = torch.zeros(R, 3, dtype=sdf.dtype).index_add(0, ray[use], w[use, None] * torch.sigmoid(logits))
    dep = torch.zeros(R, dtype=sdf.dtype).index_add(0, ray, w * z)
    hit = torch.bincount(ray, minlength=R) > 0
    D = depth[ray]
    sup = has_d[ray]
    front, band = sup & (z < D - T), sup & ((z - D).abs() <= T)
    n_f, n_b, n = front.sum(), band.sum(), sup.sum()
    tot = (n_f + n_b).to(sdf.dtype)
    fs = (1 - n_f / tot) * torch.where(front, (sdf - 1) ** 2, 0.0).sum() / n
    sd = (1 - n_b / tot) * torch.where(band, (z + sdf * T - D) ** 2, 0.0).sum() / n
    return torch.stack([(col[hit] - rgb[hit]).abs().mean(), (dep[has_d] - depth[has_d]).abs().mean(), fs, sd])


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_fused_terms_and_gradients_match_the_reference_on_random_rays(seed):
    T = 0.05
    sdf, logits, z, ray, start, crow, use, rgb, depth, has_d = random_packed(seed)
    sdf.requires_grad_()
    logits.requires_grad_()
    terms, mse = fused_losses(sdf, torch.sigmoid(logits), z, start, crow, rgb, depth, has_d, T)
    ref = reference_terms(sdf, logits, z, ray, use, rgb, depth, has_d, T)
    assert torch.allclose(terms, ref, rtol=1e-10, atol=1e-12)
    coef = torch.tensor([5.0, 1.0, 10.0, 5e4], dtype=sdf.dtype)
    g_ref = torch.autograd.grad((coef * ref).sum(), (sdf, logits))
    g = torch.autograd.grad((coef * terms).sum(), (sdf, logits))
    for a, b in zip(g, g_ref):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12)
    assert mse.item() > 0 and not mse.requires_grad


def test_fused_losses_gradcheck():
    sdf, logits, z, ray, start, crow, use, rgb, depth, has_d = random_packed(7, R=6, S=6)
    sdf.requires_grad_()
    logits.requires_grad_()

    def f(s, lg):
        return fused_losses(s, torch.sigmoid(lg), z, start, crow, rgb, depth, has_d, 0.05)[0]

    assert torch.autograd.gradcheck(f, (sdf, logits))


def test_fused_weights_match_the_reference_and_sum_to_one_per_ray():
    sdf, _, z, ray, start, *_ = random_packed(4)
    w = fused_weights(sdf, z, start, 0.05)
    assert torch.allclose(w, packed_direct_weights(sdf, z, ray, start.numel() - 1, 0.05), atol=1e-12)
    per_ray = torch.zeros(start.numel() - 1, dtype=w.dtype).index_add(0, ray, w)
    near = torch.zeros_like(per_ray).index_add(0, ray, (sdf.abs() < 0.1).to(w.dtype)) > 0  # bell >= 0.1
    assert torch.allclose(per_ray[near], torch.ones_like(per_ray[near]), atol=1e-6)
    assert (per_ray <= 1 + 1e-9).all() and (per_ray[start[1:] == start[:-1]] == 0).all()


def test_two_samples_around_the_surface_render_its_depth_and_colour():
    # s = +-0.2 T at z = 1.00 / 1.01: equal weights 1/2, D̂ = 1.005; colour logits 0 -> 0.5; observed depth 1.005
    sdf = torch.tensor([0.2, -0.2], dtype=torch.float64)
    z = torch.tensor([1.0, 1.01], dtype=torch.float64)
    start = torch.tensor([0, 2])
    crow = torch.tensor([0, 1])
    logits = torch.zeros(2, 3, dtype=torch.float64)
    rgb = torch.tensor([[0.6, 0.5, 0.3]], dtype=torch.float64)
    terms, mse = fused_losses(sdf, torch.sigmoid(logits), z, start, crow, rgb,
                              torch.tensor([1.005], dtype=torch.float64), torch.tensor([True]), 0.05)
    # both samples in the band |z - D| <= T: L_fs = 0 (balance 1 - 0/2 = 1), L_sdf = 0 * ... (balance 1 - 2/2 = 0)
    # (weights b / (2b + 1e-8) with b = σ(4)σ(−4) = 0.0177: 0.5 up to 3e-7)
    assert terms[0].item() == pytest.approx((0.1 + 0.0 + 0.2) / 3, rel=1e-6)
    assert terms[1].item() == pytest.approx(0.0, abs=1e-6)
    assert terms[2].item() == 0.0 and terms[3].item() == 0.0
    assert mse.item() == pytest.approx((0.01 + 0.0 + 0.04) / 3)


def test_the_models_fused_loss_equals_its_torch_path():
    class Cfg:
        ehe = EheConfig()
        field = type("F", (), {"kernel": "auto", "decoder_kernel": "torch"})

    torch.manual_seed(0)
    model = EheModel(Cfg, UNIT)
    vg, T = model.field.voxels, Cfg.ehe.truncation
    with torch.no_grad():  # a wall at x = 0.537 in the priors, random features and decoders
        vx, vy, vz = vg.vdims
        i = torch.arange(vx * vy * vz) % vx
        vg.priors.table[:, 0] = (0.537 - 0.1 * i.float()) / T
        for prm in model.field.grid.parameters():
            prm.uniform_(-0.1, 0.1)
    vg.allocated[:] = True
    g = torch.Generator().manual_seed(1)
    o = torch.rand(64, 3, generator=g) * torch.tensor([0.2, 0.6, 0.6]) + torch.tensor([0.0, 0.2, 0.2])
    d = torch.cat([torch.ones(64, 1), 0.3 * (torch.rand(64, 2, generator=g) - 0.5)], 1)
    rgb, depth = torch.rand(64, 3, generator=g), (0.537 - o[:, 0]) + 0.01 * torch.randn(64, generator=g)
    depth[::7] = 0.0  # some rays without depth
    grads = []
    for kernel in ("numba", "torch"):
        model.kernel = kernel
        model.zero_grad()
        losses = model.loss(o, d, rgb, depth, torch.Generator().manual_seed(5))
        losses["total"].backward()
        grads.append(({k: v.detach().clone() for k, v in losses.items()},
                      [p.grad.to_dense() for p in model.parameters() if p.grad is not None]))
    (fused, g_fused), (ref, g_ref) = grads
    for k in ("total", "rgb", "depth", "free_space", "sdf", "mse"):
        assert torch.allclose(fused[k], ref[k], rtol=1e-4, atol=1e-7), k
    assert len(g_fused) == len(g_ref) == 6 and all(b.abs().max() > 0 for b in g_ref)  # priors, level, decoders
    for a, b in zip(g_fused, g_ref):
        assert torch.allclose(a, b, rtol=1e-3, atol=1e-6 * b.abs().max().item() + 1e-9)


def test_reference_and_kernel_agree_on_samples_exactly_at_the_thresholds():
    # float32 samples at z = D - T (front, not band) and at z = z_k + T (cut): the reference compares as the kernel
    # does (thresholds in float64); in float32 alone z = D - T fell in neither set and the cut sample was dropped
    from inrslam.slam.ehe.losses import ehe_losses
    from inrslam.slam.ehe.rendering import EheRender

    T = EheConfig().truncation
    z = torch.tensor([1.0 - T, 0.99, 1.0, 1.01], dtype=torch.float32)
    sdf = torch.tensor([3.0, 0.2, 0.0, -0.2], dtype=torch.float32)
    depth, rgb = torch.tensor([1.0]), torch.zeros(1, 3)
    ray, start = torch.zeros(4, dtype=torch.long), torch.tensor([0, 4])
    w = packed_direct_weights(sdf, z, ray, 1, T)
    out = EheRender(torch.zeros(1, 3), (w * z).sum()[None], torch.tensor([True]), sdf, z, ray, w, start)
    ref = ehe_losses(out, rgb, depth, EheConfig())
    terms, _ = fused_losses(sdf, torch.zeros(0, 3), z, start, torch.full((4,), -1), rgb, depth, torch.tensor([True]), T)
    assert ref["free_space"].item() == pytest.approx(terms[2].item(), rel=1e-6) and terms[2].item() > 0
    z2 = torch.tensor([0.99, 1.0, 1.0 + T, 1.05], dtype=torch.float32)  # z_k = 1.0: the third sample at z_k + T
    s2 = torch.tensor([0.5, 0.01, -0.01, -0.012], dtype=torch.float32)
    torch.testing.assert_close(packed_direct_weights(s2, z2, torch.zeros(4, dtype=torch.long), 1, T),
                               fused_weights(s2, z2, torch.tensor([0, 4]), T))
