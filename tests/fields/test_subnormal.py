"""Subnormal gradients in the fused backward kernels (`fields.kernels.subnormal`): the grid decoder, the plane decoder
and the compositing + losses kernel count a subnormal output gradient as zero and never hand one on, and otherwise
agree with their references."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.fields.kernels.mlp import BLOCK, mlp2, mlp2_torch
from inrslam.fields.kernels.mlp3 import mlp3, mlp3_torch
from inrslam.fields.kernels.subnormal import tiny_of
from inrslam.rendering import RenderOutput, composite, compute_losses
from inrslam.rendering.config import LossConfig
from inrslam.rendering.fused_losses import TERMS, composite_losses

DTYPES = [torch.float32, torch.float64]


def _tiny(dtype: torch.dtype) -> float:
    return torch.finfo(dtype).tiny


def subnormal(t: torch.Tensor) -> torch.Tensor:
    """Where t is subnormal (0 < |t| < the smallest normal number of its dtype)."""
    return (t != 0) & (t.abs() < _tiny(t.dtype))


def _with_subnormals(cot: torch.Tensor, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """cot with about a third of its entries replaced by subnormals of either sign, and those entries' mask."""
    mask = torch.rand(cot.shape, generator=g) < 0.3
    tiny = _tiny(cot.dtype)
    sub = torch.sign(cot) * tiny * torch.rand(cot.shape, generator=g, dtype=cot.dtype).clamp(1e-3, 0.99)
    out = torch.where(mask, sub, cot)
    assert bool(subnormal(out[mask]).all()) and int(mask.sum()) > 0
    return out, mask


def test_tiny_of_is_the_smallest_normal_number():
    assert tiny_of(np.float32) == 2.0 ** -126 and tiny_of(np.dtype("float64")) == 2.0 ** -1022


def _grads(fn, leaves_in, cot, need):
    leaves = [t.clone().requires_grad_(r) for t, r in zip(leaves_in, need)]
    fn(*leaves).backward(cot)
    return [t.grad for t in leaves]


DECODERS = {
    "grid": (lambda n, dtype, g: [torch.randn(n, 7, dtype=dtype, generator=g),
                                  torch.randn(32, 7, dtype=dtype, generator=g) / 7 ** 0.5,
                                  torch.randn(3, 32, dtype=dtype, generator=g) / 32 ** 0.5],
             lambda *a: mlp2(*a, backend="numba"), lambda *a: mlp2_torch(*a)),
    "plane": (lambda n, dtype, g: [torch.randn(n, 7, dtype=dtype, generator=g)]
              + [p for i, o in ((7, 32), (32, 32), (32, 3)) for p in (torch.randn(o, i, dtype=dtype, generator=g)
                                                                       / i ** 0.5, 0.3 * torch.randn(o, dtype=dtype,
                                                                                                     generator=g))],
              lambda *a: mlp3(*a, backend="numba"), lambda *a: mlp3_torch(*a)),
}


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("decoder", sorted(DECODERS))
def test_decoder_counts_subnormal_output_gradients_as_zero(decoder, dtype):
    make, fused, ref = DECODERS[decoder]
    g = torch.Generator().manual_seed(int(np.random.SeedSequence().generate_state(1)[0]))  # fresh inputs every run
    inputs = make(2 * BLOCK + 37, dtype, g)
    cot = torch.randn(inputs[0].shape[0], 3, dtype=dtype, generator=g)
    cot_sub, mask = _with_subnormals(cot, g)
    need = [True] * len(inputs)
    got = _grads(fused, inputs, cot_sub, need)
    zeroed = _grads(fused, inputs, torch.where(mask, torch.zeros((), dtype=dtype), cot_sub), need)
    for a, b in zip(got, zeroed):  # exactly as if those entries were 0
        assert torch.equal(a, b)
    for a, b in zip(got, _grads(ref, inputs, cot_sub, need)):  # and the reference's up to rounding
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * max(1.0, float(b.abs().max())))


@pytest.mark.parametrize("decoder", sorted(DECODERS))
def test_decoder_input_gradient_has_no_subnormals(decoder):
    """Output gradients a few times the smallest normal number give input gradients around it: the reference's has
    subnormal entries, the kernel's the same values with those set to zero."""
    make, fused, ref = DECODERS[decoder]
    g = torch.Generator().manual_seed(int(np.random.SeedSequence().generate_state(1)[0]))
    inputs = make(BLOCK + 5, torch.float32, g)
    cot = 3 * _tiny(torch.float32) * torch.randn(inputs[0].shape[0], 3, generator=g)
    cot = torch.where(subnormal(cot), torch.zeros(()), cot)  # normal numbers only
    need = [True] + [False] * (len(inputs) - 1)
    gx_ref = _grads(ref, inputs, cot, need)[0]
    gx = _grads(fused, inputs, cot, need)[0]
    assert int(subnormal(gx_ref).sum()) > 0  # the case is not vacuous
    assert not bool(subnormal(gx).any())
    normal = ~subnormal(gx_ref)
    torch.testing.assert_close(gx[normal], gx_ref[normal], rtol=1e-3, atol=1e-3 * float(gx_ref.abs().max()))
    assert bool((gx[~normal].abs() <= 1e-3 * float(gx_ref.abs().max())).all())


@pytest.mark.parametrize("dtype", DTYPES)
def test_loss_kernel_writes_subnormal_gradients_as_zero(dtype):
    """Samples far behind the surface (weights ~1e-40 in float32, ~1e-310 in float64) get colour gradients of
    about that size: the kernel writes 0 there and the reference's values elsewhere."""
    g = torch.Generator().manual_seed(int(np.random.SeedSequence().generate_state(1)[0]))
    R, S, T = 96, 24, 0.1
    D = 0.5 + 2.5 * torch.rand(R, generator=g, dtype=dtype)
    z = torch.sort(D[:, None] + 0.4 * torch.randn(R, S, generator=g, dtype=dtype), dim=1).values
    sdf = (D[:, None] - z) / T
    w = torch.rand(R, S, generator=g, dtype=dtype) / S
    far = z > D[:, None] + 0.3
    w = torch.where(far, _tiny(dtype) * 0.01 * torch.rand(R, S, generator=g, dtype=dtype), w)
    c = torch.rand(R, S, 3, generator=g, dtype=dtype)
    C = torch.rand(R, 3, generator=g, dtype=dtype)
    cfg = LossConfig()
    leaves_ref = [t.clone().requires_grad_() for t in (w, c, sdf)]
    out = RenderOutput(*composite(leaves_ref[0], leaves_ref[1], z), leaves_ref[0], leaves_ref[2], z)
    ref = compute_losses(out, C, D, cfg, T, True, None)
    leaves = [t.clone().requires_grad_() for t in (w, c, sdf)]
    got, _ = composite_losses(*leaves[:2], z, leaves[2], C, D, T, cfg.center_band, cfg.free_space_target,
                              cfg.reduction == "per_ray", True, cfg.behind)
    g_ref = torch.autograd.grad(sum(ref[k] for k in TERMS), leaves_ref)
    g_got = torch.autograd.grad(sum(got[k] for k in TERMS), leaves)
    assert int(subnormal(g_ref[1]).sum()) > 0  # the reference hands subnormal colour gradients on
    for a, b in zip(g_got, g_ref):
        assert not bool(subnormal(a).any())
        keep = ~subnormal(b)
        torch.testing.assert_close(a[keep], b[keep], rtol=1e-4, atol=1e-6)
        assert bool((a[~keep] == 0).all())
