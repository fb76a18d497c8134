"""Fused plane decoder relu(relu(x W1^T + b1) W2^T + b2) W3^T + b3 (numba) vs the PyTorch reference: outputs,
gradients, gradcheck, an analytic case, thread independence, dispatch and the module it replaces."""

import numpy as np
import pytest
import torch

from inrslam.fields import kernels
from inrslam.fields.kernels.mlp import BLAS_SINGLE_THREAD_MNK, block_rows
from inrslam.fields.kernels.mlp3 import Mlp3Fn, mlp3, mlp3_torch
from inrslam.fields.kernels.threads import thread_scope
from inrslam.fields.models import plane_decoder, run_plane_decoder

BLOCK = block_rows(torch.empty(7, 32), torch.empty(32, 32), torch.empty(32, 3))  # the default plane decoder's: 256


def _inputs(n, n_in=7, h1=32, h2=32, n_out=3, dtype=torch.float32, seed=None):
    """x, the six parameters (w1, b1, w2, b2, w3, b3) and an output cotangent, fresh random per call."""
    g = torch.Generator().manual_seed(int(np.random.SeedSequence(seed).generate_state(1)[0]))
    x = torch.randn(n, n_in, dtype=dtype, generator=g)
    params = []
    for i, o in ((n_in, h1), (h1, h2), (h2, n_out)):
        params += [torch.randn(o, i, dtype=dtype, generator=g) / i ** 0.5,
                   0.3 * torch.randn(o, dtype=dtype, generator=g)]
    cot = torch.randn(n, n_out, dtype=dtype, generator=g)
    return x, params, cot


def _grads(backend, x, params, cot, need=(True,) * 7):
    leaves = [t.clone().requires_grad_(r) for t, r in zip((x, *params), need)]
    out = mlp3(*leaves, backend=backend)
    out.backward(cot)
    return out.detach(), [t.grad for t in leaves]


@pytest.mark.parametrize("n_out", [1, 3])
@pytest.mark.parametrize("n", [1, BLOCK - 1, 3 * BLOCK + 37])
def test_fused_matches_reference(n, n_out):
    x, params, cot = _inputs(n, n_out=n_out)
    out_r, grads_r = _grads("torch", x, params, cot)
    out_f, grads_f = _grads("numba", x, params, cot)
    torch.testing.assert_close(out_f, out_r, rtol=1e-5, atol=1e-5)
    for gf, gr in zip(grads_f, grads_r):
        torch.testing.assert_close(gf, gr, rtol=1e-4, atol=1e-4 * max(1.0, float(gr.abs().max())))


@pytest.mark.parametrize("need", [(True,) + (False,) * 6, (False,) + (True,) * 6, (False, False, True, False, False,
                                                                                   True, False)])
def test_only_requested_gradients(need):
    x, params, cot = _inputs(600)
    _, grads_r = _grads("torch", x, params, cot, need)
    _, grads_f = _grads("numba", x, params, cot, need)
    for gf, gr, wanted in zip(grads_f, grads_r, need):
        assert (gf is None) == (not wanted)
        if wanted:
            torch.testing.assert_close(gf, gr, rtol=1e-4, atol=1e-4)


def test_gradcheck_float64():
    """Input gradient on a few samples; weight and bias gradients over several blocks (their per-block sums)."""
    for n, need_x in ((5, True), (2 * BLOCK + 3, False)):
        x, params, _ = _inputs(2 * n, n_in=4, h1=6, h2=5, n_out=2, dtype=torch.float64)
        # a finite-difference step of 1e-6 across a ReLU kink breaks the numerical Jacobian (1 run in 100 failed):
        # keep samples whose pre-activations of both hidden layers are 1e-3 away from 0
        w1, b1, w2, b2 = params[:4]
        pre1 = torch.nn.functional.linear(x, w1, b1)
        pre2 = torch.nn.functional.linear(torch.relu(pre1), w2, b2)
        x = x[torch.minimum(pre1.abs().amin(dim=1), pre2.abs().amin(dim=1)) > 1e-3][:n]
        assert x.shape[0] == n
        args = [x.clone().requires_grad_(need_x)] + [p.clone().requires_grad_() for p in params]
        assert torch.autograd.gradcheck(lambda *a: Mlp3Fn.apply(*a), args, eps=1e-6, atol=1e-6)


def test_analytic_case():
    """By hand: x = [1, -2]; W1 = I, b1 = (0, 1) -> pre (1, -1), hidden (1, 0); W2 = [[2, 5]], b2 = (-1) -> pre 1,
    hidden 1; W3 = [[3]], b3 = (0.5) -> y = 3.5. dy/dx = W1^T (mask1 * W2^T (mask2 * W3^T)) = (6, 0);
    dy/dW3 = hidden2 = 1, dy/db3 = 1; dy/dW2 = 3 · hidden1 = (3, 0), dy/db2 = 3; dy/dW1 = [[6, -12], [0, 0]],
    dy/db1 = (6, 0)."""
    x = torch.tensor([[1.0, -2.0]], requires_grad=True)
    params = [torch.eye(2), torch.tensor([0.0, 1.0]), torch.tensor([[2.0, 5.0]]), torch.tensor([-1.0]),
              torch.tensor([[3.0]]), torch.tensor([0.5])]
    params = [p.requires_grad_() for p in params]
    y = mlp3(x, *params, backend="numba")
    y.backward(torch.ones_like(y))
    assert y.item() == 3.5
    assert x.grad.tolist() == [[6.0, 0.0]]
    assert [p.grad.tolist() for p in params] == [[[6.0, -12.0], [0.0, 0.0]], [6.0, 0.0], [[3.0, 0.0]], [3.0], [[1.0]],
                                                 [1.0]]


@pytest.mark.parametrize("n_in, hidden", [(7, 32), (35, 64)])
def test_gradients_independent_of_threads(n_in, hidden):
    """Any thread count gives the same bits, also for a wider decoder (35 inputs, 64 hidden units: 64 x 64 middle
    layer, so a smaller block keeps each product at OpenBLAS's single-thread size)."""
    x, params, cot = _inputs(9 * BLOCK + 11, n_in=n_in, h1=hidden, h2=hidden)
    block = block_rows(*params[::2])
    assert block * max(w.shape[0] * w.shape[1] for w in params[::2]) <= BLAS_SINGLE_THREAD_MNK
    assert block == (256 if hidden == 32 else 64)
    runs = []
    for n in (1, 2):
        with thread_scope(n):
            runs.append(_grads("numba", x, params, cot))
    assert torch.equal(runs[0][0], runs[1][0])
    for a, b in zip(runs[0][1], runs[1][1]):
        assert torch.equal(a, b)
    out_r, grads_r = _grads("torch", x, params, cot)
    torch.testing.assert_close(runs[0][0], out_r, rtol=1e-5, atol=1e-5)
    for a, b in zip(runs[0][1], grads_r):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * max(1.0, float(b.abs().max())))


def test_auto_dispatch():
    x, params, _ = _inputs(50)
    xr = x.clone().requires_grad_()
    assert mlp3(xr, *params).grad_fn.name() == "Mlp3FnBackward"  # CPU float tensors: fused
    with kernels.second_order():  # a create_graph backward may follow: the differentiable reference, even if asked
        y = mlp3(xr, *params, backend="numba")
        assert "Mlp3Fn" not in y.grad_fn.name()
        (gx,) = torch.autograd.grad(y.sum(), xr, create_graph=True)
        assert gx.requires_grad
    assert "Mlp3Fn" not in mlp3(xr, *params, backend="torch").grad_fn.name()
    half = [p.half() for p in params]
    assert torch.equal(mlp3(x.half(), *half), mlp3_torch(x.half(), *half))


def test_nan_and_inf_inputs_give_what_the_reference_gives():
    """A NaN or infinite input (the SLAM loop detects a failed step by its NaN loss) is not silently zeroed by a
    ReLU: outputs and all seven gradients equal the reference's, NaNs in the same places."""
    x, params, cot = _inputs(40)
    x[3, 2] = float("nan")
    x[7, 0] = float("inf")
    x[9, 1] = -float("inf")
    out_r, grads_r = _grads("torch", x, params, cot)
    out_f, grads_f = _grads("numba", x, params, cot)
    assert torch.isnan(out_f[3]).all() and torch.isnan(out_r[3]).all()
    torch.testing.assert_close(out_f, out_r, rtol=1e-5, atol=1e-5, equal_nan=True)
    for gf, gr in zip(grads_f, grads_r):
        assert torch.equal(torch.isnan(gf), torch.isnan(gr))
        torch.testing.assert_close(gf, gr, rtol=1e-4, atol=1e-4, equal_nan=True)


def test_bad_input_errors():
    x, params, _ = _inputs(10)
    with pytest.raises(ValueError, match="do not chain"):
        mlp3(x[:, :5], *params)
    with pytest.raises(ValueError, match="do not chain"):
        mlp3(x, params[0], params[1][:-1], *params[2:])
    with pytest.raises(ValueError, match="unknown decoder kernel"):
        mlp3(x, *params, backend="cuda")
    with pytest.raises(ValueError, match="float32/float64"):
        mlp3(x.half(), *[p.half() for p in params], backend="numba")


def test_a_layer_too_wide_for_single_threaded_blas_runs_the_reference():
    """One sample's product with a 600 x 600 layer exceeds OpenBLAS's single-thread size whatever the block: auto
    runs the reference, an explicit numba request says why it cannot."""
    x, params, _ = _inputs(20, h1=600, h2=600)
    assert "Mlp3Fn" not in mlp3(x.clone().requires_grad_(), *params).grad_fn.name()
    torch.testing.assert_close(mlp3(x, *params), mlp3_torch(x, *params))
    with pytest.raises(ValueError, match="262144 weights"):
        mlp3(x, *params, backend="numba")


def test_module_and_kernel_agree():
    """`run_plane_decoder` with numba computes what the `plane_decoder` module does, gradients of its parameters
    included; with torch it is the module itself, bit for bit."""
    torch.manual_seed(0)
    net = plane_decoder(7, 32, 3)
    x = torch.randn(700, 7)
    assert torch.equal(run_plane_decoder(net, x, "torch"), net(x))
    grads = {}
    for backend in ("torch", "numba"):
        net.zero_grad()
        out = run_plane_decoder(net, x, backend)
        out.square().sum().backward()
        grads[backend] = (out.detach(), [p.grad.clone() for p in net.parameters()])
    torch.testing.assert_close(grads["numba"][0], grads["torch"][0], rtol=1e-5, atol=1e-5)
    for a, b in zip(grads["numba"][1], grads["torch"][1]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA"))])
def test_auto_runs_on_any_device_and_matches_the_reference(device):
    x, params, cot = _inputs(700)
    x, cot, params = x.to(device), cot.to(device), [p.to(device) for p in params]
    out_a, grads_a = _grads("auto", x, params, cot)
    out_r, grads_r = _grads("torch", x, params, cot)
    assert out_a.device.type == device
    torch.testing.assert_close(out_a, out_r, rtol=1e-5, atol=1e-5)
    for a, b in zip(grads_a, grads_r):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [1, BLOCK - 1, 3 * BLOCK + 37])
def test_backward_from_the_relu_masks_equals_the_recomputing_one(monkeypatch, n, dtype):
    """Tracking (parameters frozen): the input gradient from the forward's two ReLU masks (`mlp.KEEP_MASK`) equals,
    bit for bit, that of the backward that recomputes both hidden layers; NaN inputs included."""
    import inrslam.fields.kernels.mlp as mlp

    x, params, cot = _inputs(n, dtype=dtype)
    x[::7, 2] = float("nan")
    runs = {}
    for keep in (False, True):
        monkeypatch.setattr(mlp, "KEEP_MASK", keep)
        leaf = x.clone().requires_grad_()
        out = mlp3(leaf, *params, backend="numba")
        assert (out.grad_fn.masks is not None) == keep
        out.backward(cot)
        runs[keep] = out.detach(), leaf.grad
    for a, b in zip(runs[True], runs[False]):
        assert torch.equal(a.nan_to_num(7.0), b.nan_to_num(7.0))


def test_the_relu_masks_are_kept_only_where_no_parameter_needs_a_gradient():
    """Tracking keeps one byte per hidden unit and sample for each hidden layer; mapping (parameters trained: their
    gradients read the hidden layers themselves) keeps none."""
    x, params, _ = _inputs(40, h1=32, h2=16)
    frozen = mlp3(x.clone().requires_grad_(), *params, backend="numba")
    assert [m.shape for m in frozen.grad_fn.masks] == [(40, 32), (40, 16)]
    assert all(m.dtype == np.uint8 for m in frozen.grad_fn.masks)
    one_trained = [p.clone().requires_grad_(k == 3) for k, p in enumerate(params)]
    assert mlp3(x.clone().requires_grad_(), *one_trained, backend="numba").grad_fn.masks is None


def test_relu_masks_backward_gradcheck_float64():
    """The mask path's input gradient against finite differences (parameters frozen), samples 1e-3 away from both
    layers' kinks (see `test_gradcheck_float64`)."""
    x, params, _ = _inputs(100, n_in=4, h1=6, h2=5, n_out=2, dtype=torch.float64)
    w1, b1, w2, b2 = params[:4]
    pre1 = torch.nn.functional.linear(x, w1, b1)
    pre2 = torch.nn.functional.linear(torch.relu(pre1), w2, b2)
    x = x[torch.minimum(pre1.abs().amin(dim=1), pre2.abs().amin(dim=1)) > 1e-3][:6]
    assert x.shape[0] == 6
    assert torch.autograd.gradcheck(lambda a: Mlp3Fn.apply(a, *params), [x.clone().requires_grad_()], eps=1e-6,
                                    atol=1e-6)


def test_relu_masks_analytic_case():
    """`test_analytic_case` with the parameters frozen (the mask path), and a second sample whose second hidden
    pre-activation is exactly 0: x = [0.5, -2] -> hidden1 (0.5, 0) -> pre2 = 2 · 0.5 - 1 = 0, so y = b3 = 0.5 and
    no gradient passes (torch's ReLU at 0)."""
    x = torch.tensor([[1.0, -2.0], [0.5, -2.0]], requires_grad=True)
    params = [torch.eye(2), torch.tensor([0.0, 1.0]), torch.tensor([[2.0, 5.0]]), torch.tensor([-1.0]),
              torch.tensor([[3.0]]), torch.tensor([0.5])]
    y = mlp3(x, *params, backend="numba")
    assert [m.tolist() for m in y.grad_fn.masks] == [[[1, 0], [1, 0]], [[1], [0]]]
    y.backward(torch.ones_like(y))
    assert y.detach().flatten().tolist() == [3.5, 0.5]
    assert x.grad.tolist() == [[6.0, 0.0], [0.0, 0.0]]
