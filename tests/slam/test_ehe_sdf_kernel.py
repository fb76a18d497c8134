"""The fused EHE SDF (`inrslam.slam.ehe.sdf_kernel`) against its reference, the prior lookup + decoder composition
(values and every gradient on fresh random inputs, float64 gradcheck), an analytic linear prior, NaN samples,
thread-count independence and the dispatch in `EheField.sdf_from`."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.fields.kernels.threads import thread_scope
from inrslam.slam.ehe.config import EheConfig
from inrslam.slam.ehe.field import EheField
from inrslam.slam.ehe.sdf_kernel import EheSdfFn, ehe_sdf

BOX = np.array([[-1.0, 2.0], [-0.5, 1.5], [0.0, 2.2]])


def random_field(seed: int, kernel: str = "auto", decoder: str = "auto", dtype=torch.float32) -> EheField:
    """An EHE field with random priors, dense level and decoders (same values for the same seed)."""
    torch.manual_seed(seed)
    field = EheField(EheConfig(), BOX, kernel=kernel, decoder_kernel=decoder)
    with torch.no_grad():
        field.voxels.priors.table.normal_()
        field.grid.table.normal_(0.0, 0.1)
    return field.to(dtype)


def random_points(n: int, seed: int, dtype=torch.float32) -> torch.Tensor:
    """Points over the box and 20 cm beyond it on every side (outside points use the nearest cell)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(BOX[:, 0]) - 0.2, torch.tensor(BOX[:, 1]) + 0.2
    return (lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)).to(dtype)


def sdf_and_grads(field: EheField, x: torch.Tensor, g: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """s and the gradients of Σ g·s (+ a colour term, so that the dense level gets both decoders' gradients)."""
    p, f = field.encode(x)
    s = field.sdf_from(x, p, f)
    ((s * g).sum() + field.rgb_from(p, f).square().sum()).backward()
    grads = {n: (q.grad.to_dense() if q.grad.is_sparse else q.grad).clone() for n, q in field.named_parameters()}
    return s.detach(), grads


@pytest.mark.parametrize("seed", [0, 1])
def test_fused_sdf_and_gradients_equal_the_reference(seed):
    x = random_points(4000, seed)
    g = torch.randn(x.shape[0], generator=torch.Generator().manual_seed(seed + 10))
    fused = random_field(seed)
    s_f, g_f = sdf_and_grads(fused, x, g)
    s_r, g_r = sdf_and_grads(random_field(seed, kernel="torch", decoder="torch"), x, g)
    torch.testing.assert_close(s_f, s_r, rtol=1e-5, atol=2e-5)
    for name in g_r:
        scale = float(g_r[name].abs().max())
        torch.testing.assert_close(g_f[name], g_r[name], rtol=1e-4, atol=1e-5 * max(scale, 1.0), msg=name)
    assert float(g_r["voxels.priors.table"].abs().sum()) > 0 and float(g_r["sdf_net.0.weight"].abs().sum()) > 0


def test_gradcheck_float64():
    field = random_field(3, dtype=torch.float64)
    x = random_points(40, 3, torch.float64)
    p, f = field.encode(x)
    f = f.detach().requires_grad_(True)
    prior = field.voxels.priors.table.detach().clone().requires_grad_(True)
    w1 = field.sdf_net[0].weight.detach().clone().requires_grad_(True)
    w2 = field.sdf_net[2].weight.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f_, t_, a_, b_: EheSdfFn.apply(x, f_, p.detach(), t_, a_, b_, field.voxels),
                                    (f, prior, w1, w2), eps=1e-6, atol=1e-6)


def test_a_linear_prior_is_interpolated_exactly_and_its_gradient_is_the_corner_weights():
    """Decoders zero: s is the trilinear prior, exact for prior(v) = a·v + b; ∂s/∂prior are the 8 corner weights,
    which sum to 1 and reproduce the point as their weighted mean of corners."""
    field = random_field(4)
    vg = field.voxels
    with torch.no_grad():
        for q in (field.sdf_net[0].weight, field.sdf_net[2].weight):
            q.zero_()
        vx, vy, vz = vg.vdims
        k, j, i = torch.meshgrid(torch.arange(vz), torch.arange(vy), torch.arange(vx), indexing="ij")
        v = torch.stack([i, j, k], -1).reshape(-1, 3).float() * vg.voxel_size + vg.origin  # vertex id order
        a = torch.tensor([0.7, -1.3, 2.1])
        vg.priors.table[:, 0] = v @ a + 0.25
    x = random_points(200, 4)
    inside = ((x >= vg.origin) & (x <= vg.origin + torch.tensor(vg.dims) * vg.voxel_size)).all(1)
    x = x[inside]
    s = ehe_sdf(x, torch.zeros(len(x), 2), field.normalise(x), vg, field.sdf_net[0].weight, field.sdf_net[2].weight)
    torch.testing.assert_close(s, x @ a + 0.25, rtol=0, atol=2e-5)
    xs = x[:1]
    prior = vg.priors.table.detach().clone().requires_grad_(True)
    EheSdfFn.apply(xs, torch.zeros(1, 2), field.normalise(xs), prior, field.sdf_net[0].weight,
                   field.sdf_net[2].weight, vg).sum().backward()
    w = prior.grad[:, 0]
    rows = torch.nonzero(w).reshape(-1)
    assert len(rows) == 8 and float(w.sum()) == pytest.approx(1.0, abs=1e-6)
    torch.testing.assert_close((w[rows, None] * v[rows]).sum(0), xs[0], rtol=0, atol=1e-5)


def sdf_grads(field: EheField, x: torch.Tensor, g: torch.Tensor, keep: slice) -> dict[str, torch.Tensor]:
    """Gradients of Σ g·s[keep] (the SDF alone)."""
    p, f = field.encode(x)
    (field.sdf_from(x, p, f)[keep] * g).sum().backward()
    return {n: (q.grad.to_dense() if q.grad.is_sparse else q.grad) for n, q in field.named_parameters()
            if q.grad is not None}


def test_a_nan_sample_gives_nan_and_leaves_the_other_gradients_as_they_were():
    x = random_points(300, 5)
    g = torch.randn(300, generator=torch.Generator().manual_seed(5))
    xn = torch.cat([x, torch.tensor([[float("nan"), 0.5, 0.5]])])
    field = random_field(5)
    p, f = field.encode(xn)
    s = field.sdf_from(xn, p, f)
    assert torch.isnan(s[-1]) and torch.isfinite(s[:-1]).all()
    with_nan = sdf_grads(random_field(5), xn, g, slice(0, -1))  # the NaN sample's output gradient is 0
    clean = sdf_grads(random_field(5), x, g, slice(None))
    assert set(with_nan) == set(clean) == {"voxels.priors.table", "grid.table", "sdf_net.0.weight", "sdf_net.2.weight"}
    for name in clean:
        torch.testing.assert_close(with_nan[name], clean[name], msg=name)


def test_results_do_not_depend_on_the_thread_count():
    x = random_points(5000, 6)
    g = torch.randn(5000, generator=torch.Generator().manual_seed(6))
    out = []
    for threads in (1, 2):
        with thread_scope(threads):
            out.append(sdf_and_grads(random_field(6), x, g))
    assert torch.equal(out[0][0], out[1][0])
    for name in out[0][1]:
        assert torch.equal(out[0][1][name], out[1][1][name]), name


@pytest.mark.parametrize("kernel, decoder, fused", [("auto", "auto", True), ("numba", "numba", True),
                                                    ("torch", "auto", False), ("auto", "torch", False)])
def test_sdf_from_runs_the_fused_kernel_only_with_both_kernels_on(kernel, decoder, fused):
    field = random_field(7, kernel=kernel, decoder=decoder)
    x = random_points(10, 7)
    p, f = field.encode(x)
    s = field.sdf_from(x, p, f)
    assert (type(s.grad_fn).__name__ == "EheSdfFnBackward") == fused


def test_zero_gradient_samples_are_left_out_with_the_same_gradients():
    """Samples whose output gradient is zero (about a third on EHE's rays) are dropped from the backward's block
    products; every gradient still equals the reference, with whole blocks of zeros and zero runs between."""
    x = random_points(5000, 7)
    gen = torch.Generator().manual_seed(8)
    g = torch.randn(x.shape[0], generator=gen)
    g[:2100] = 0.0  # the first blocks carry no gradient at all
    g[torch.randint(0, 2, (5000 // 10,), generator=gen).repeat_interleave(10).bool()] = 0.0
    assert 0.3 < float((g == 0).float().mean()) < 0.9
    s_f, g_f = sdf_and_grads(random_field(7), x, g)
    s_r, g_r = sdf_and_grads(random_field(7, kernel="torch", decoder="torch"), x, g)
    torch.testing.assert_close(s_f, s_r, rtol=1e-5, atol=2e-5)
    for name in g_r:
        scale = float(g_r[name].abs().max())
        torch.testing.assert_close(g_f[name], g_r[name], rtol=1e-4, atol=1e-5 * max(scale, 1.0), msg=name)
    assert float(g_r["voxels.priors.table"].abs().sum()) > 0 and float(g_r["sdf_net.0.weight"].abs().sum()) > 0
    # and without any gradient nothing reaches the priors or the decoder
    all_zero = torch.zeros(x.shape[0])
    _, g0 = sdf_and_grads(random_field(7), x, all_zero)
    assert float(g0["voxels.priors.table"].abs().sum()) == 0 and float(g0["sdf_net.0.weight"].abs().sum()) == 0
