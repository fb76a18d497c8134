"""Fused per-level combinations of plane / line features (numba: tri-plane sums, TensoRF vector-matrix products) vs
the PyTorch references: bit-identical outputs and gradients on fresh random inputs, gradcheck, analytic cases,
thread independence, dispatch, and the encoders using them."""

import numpy as np
import pytest
import torch

from inrslam.fields import kernels
from inrslam.fields.config import KernelChoice
from inrslam.fields.encoders import TensoRFEncoder, TriPlaneEncoder
from inrslam.fields.kernels.combine import (
    PlaneSumFn,
    VmProductFn,
    plane_sum,
    plane_sum_torch,
    vm_product,
    vm_product_torch,
)
from inrslam.fields.kernels.threads import thread_scope

SIZES = [[6, 5, 4], [11, 9, 7]]  # vertices per axis of two levels' planes and lines


def _inputs(n, levels, feat, dtype=torch.float32, per_level=6):
    g = torch.Generator().manual_seed(int(np.random.SeedSequence().generate_state(1)[0]))  # fresh every run
    f = torch.randn(n, per_level * levels, feat, dtype=dtype, generator=g)
    cot = torch.randn(n, levels * feat, dtype=dtype, generator=g)
    f[::7, 0] = 0.0  # exact zeros and negative-zero cotangents: the signs of zero products must match too
    cot[::5] = -0.0
    return f, cot


def _run(backend, f, cot, levels, faithful):
    leaf = f.clone().requires_grad_()
    out = vm_product(leaf, levels, faithful, backend)
    out.backward(cot)
    return out.detach(), leaf.grad


def _bits(t):
    return t.view(torch.int32 if t.dtype == torch.float32 else torch.int64)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("faithful", [False, True])
@pytest.mark.parametrize("levels, feat, n", [(1, 1, 5), (2, 2, 2051), (3, 4, 6143)])
def test_fused_is_bit_identical_to_the_reference(levels, feat, n, faithful, dtype):
    """The same operations in the same order: outputs and gradients equal to the bit (zero signs included), so a
    run's trajectory does not change with the kernel."""
    f, cot = _inputs(n, levels, feat, dtype)
    out_r, g_r = _run("torch", f, cot, levels, faithful)
    out_f, g_f = _run("numba", f, cot, levels, faithful)
    assert out_f.shape == (n, levels * feat)
    assert torch.equal(_bits(out_f), _bits(out_r))
    assert torch.equal(_bits(g_f), _bits(g_r))


@pytest.mark.parametrize("faithful", [False, True])
def test_gradcheck_float64(faithful):
    f, _ = _inputs(9, 2, 3, torch.float64)
    assert torch.autograd.gradcheck(lambda x: VmProductFn.apply(x, 2, faithful), [f.requires_grad_()],
                                    eps=1e-6, atol=1e-8)


def test_analytic_case():
    """One level, one feature: planes (1, 2, 3), lines (4, 5, 6). True VM: 1·4 + 2·5 + 3·6 = 32, ∂/∂planes = lines,
    ∂/∂lines = planes; faithful: (1 + 2 + 3)(4 + 5 + 6) = 90, ∂/∂plane_k = 15, ∂/∂line_k = 6."""
    f = torch.tensor([[[1.0], [2.0], [3.0], [4.0], [5.0], [6.0]]])
    for faithful, value, grad in ((False, 32.0, [4.0, 5.0, 6.0, 1.0, 2.0, 3.0]),
                                  (True, 90.0, [15.0, 15.0, 15.0, 6.0, 6.0, 6.0])):
        leaf = f.clone().requires_grad_()
        out = vm_product(leaf, 1, faithful, "numba")
        out.backward(torch.ones_like(out))
        assert out.item() == value
        assert leaf.grad.reshape(-1).tolist() == grad


def test_independent_of_threads():
    f, cot = _inputs(8209, 2, 2)
    runs = []
    for n in (1, 2):
        with thread_scope(n):
            runs.append(_run("numba", f, cot, 2, False))
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])


def test_nan_propagates_as_in_the_reference():
    f, cot = _inputs(30, 2, 2)
    f[4, 1, 0] = float("nan")
    f[6, 8, 1] = float("inf")
    out_r, g_r = _run("torch", f, cot, 2, False)
    out_f, g_f = _run("numba", f, cot, 2, False)
    torch.testing.assert_close(out_f, out_r, rtol=0, atol=0, equal_nan=True)
    torch.testing.assert_close(g_f, g_r, rtol=0, atol=0, equal_nan=True)


def test_dispatch_and_bad_input():
    f, _ = _inputs(20, 2, 2)
    leaf = f.clone().requires_grad_()
    assert vm_product(leaf, 2, False).grad_fn.name() == "VmProductFnBackward"  # CPU floats: fused
    with kernels.second_order():  # a create_graph backward may follow: the differentiable reference
        y = vm_product(leaf, 2, False, "numba")
        assert "VmProductFn" not in y.grad_fn.name()
        (g,) = torch.autograd.grad(y.square().sum(), leaf, create_graph=True)
        assert g.requires_grad
    assert "VmProductFn" not in vm_product(leaf, 2, False, "torch").grad_fn.name()
    assert torch.equal(vm_product(f.half(), 2, False), vm_product_torch(f.half(), 2, False))  # auto: reference
    with pytest.raises(ValueError, match=r"\(N, 12, F\) for 2 level"):
        vm_product(f[:, :11], 2, False)
    with pytest.raises(ValueError, match="unknown kernel backend"):
        vm_product(f, 2, False, "cuda")
    with pytest.raises(ValueError, match="float32/float64"):
        vm_product(f.half(), 2, False, "numba")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("levels, feat, n", [(1, 1, 5), (2, 2, 2051), (3, 4, 6143)])
def test_plane_sum_is_bit_identical_to_the_reference(levels, feat, n, dtype):
    f, cot = _inputs(n, levels, feat, dtype, per_level=3)
    runs = []
    for backend in ("torch", "numba"):
        leaf = f.clone().requires_grad_()
        out = plane_sum(leaf, levels, backend)
        out.backward(cot)
        runs.append((out.detach(), leaf.grad))
    (out_r, g_r), (out_f, g_f) = runs
    assert out_f.shape == (n, levels * feat)
    assert torch.equal(_bits(out_f), _bits(out_r))
    assert torch.equal(_bits(g_f), _bits(g_r))


def test_plane_sum_gradcheck_analytic_threads_and_dispatch():
    """gradcheck in float64; by hand: planes (1, 2, 3) and (4, 5, 6) over two levels sum to (6, 15), and each plane's
    gradient is its level's; any thread count the same bits; the reference inside `second_order()`; bad shapes."""
    f, _ = _inputs(9, 2, 3, torch.float64, per_level=3)
    assert torch.autograd.gradcheck(lambda x: PlaneSumFn.apply(x, 2), [f.requires_grad_()], eps=1e-6, atol=1e-8)
    leaf = torch.tensor([[[1.0], [2.0], [3.0], [4.0], [5.0], [6.0]]], requires_grad=True)
    out = plane_sum(leaf, 2, "numba")
    out.backward(torch.tensor([[10.0, -1.0]]))
    assert out.tolist() == [[6.0, 15.0]]
    assert leaf.grad.reshape(-1).tolist() == [10.0, 10.0, 10.0, -1.0, -1.0, -1.0]
    big, _ = _inputs(8209, 2, 2, per_level=3)
    outs = []
    for n in (1, 2):
        with thread_scope(n):
            outs.append(plane_sum(big, 2, "numba"))
    assert torch.equal(outs[0], outs[1])
    x = big.clone().requires_grad_()
    assert plane_sum(x, 2).grad_fn.name() == "PlaneSumFnBackward"
    with kernels.second_order():
        assert "PlaneSumFn" not in plane_sum(x, 2, "numba").grad_fn.name()
    assert torch.equal(plane_sum(big.half(), 2), plane_sum_torch(big.half(), 2))
    with pytest.raises(ValueError, match=r"\(N, 6, F\) for 2 level"):
        plane_sum(big[:, :5], 2)


@pytest.mark.parametrize("encoder, reference", [
    (lambda: TriPlaneEncoder(SIZES, 2, False, 0.1, KernelChoice.AUTO), lambda f: plane_sum_torch(f, 2)),
    (lambda: TensoRFEncoder(SIZES, 2, False, 0.1, KernelChoice.AUTO), lambda f: vm_product_torch(f, 2, False)),
    (lambda: TensoRFEncoder(SIZES, 2, True, 0.1, KernelChoice.AUTO), lambda f: vm_product_torch(f, 2, True))],
    ids=["tri-plane", "tensorf", "tensorf-faithful"])
def test_encoder_combines_its_lookup_as_the_reference(encoder, reference):
    """The encoders (kernel auto: fused lookup and combination) give the reference combination of their own lookup,
    and the same table and input gradients, bit for bit."""
    torch.manual_seed(0)
    enc = encoder()
    p = torch.rand(500, 3)
    grads = []
    for combine in ("encoder", "reference"):
        enc.zero_grad()
        x = p.clone().requires_grad_()
        out = enc(x) if combine == "encoder" else reference(enc.lookup(x))
        out.square().sum().backward()
        grads.append((out.detach(), enc.table.grad.to_dense(), x.grad))
    for a, b in zip(*grads):
        assert torch.equal(a, b)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA"))])
def test_auto_runs_on_any_device_and_matches_the_reference(device):
    f, cot = _inputs(300, 2, 2)
    f, cot = f.to(device), cot.to(device)
    out_a, g_a = _run("auto", f, cot, 2, False)
    out_r, g_r = _run("torch", f, cot, 2, False)
    assert out_a.device.type == device
    assert torch.equal(out_a, out_r) and torch.equal(g_a, g_r)

