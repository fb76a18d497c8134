"""A ``create_graph`` backward through the fused decoders and plane / VM combinations outside
``kernels.second_order()`` (someone else's eikonal loss): the fused Functions differentiate their references
(`function.fused_backward`), so second derivatives reach every input, as with the plain-PyTorch path."""

import numpy as np
import pytest
import torch

from inrslam.fields.config import FieldConfig
from inrslam.fields.kernels.combine import PlaneSumFn, VmProductFn, plane_sum_torch, vm_product_torch
from inrslam.fields.kernels.mlp import Mlp2Fn, Mlp2SplitFn, mlp2_split_torch, mlp2_torch
from inrslam.fields.kernels.mlp3 import Mlp3Fn, mlp3_torch
from inrslam.fields.models import build_field


def _rand(*shape, g):
    return torch.randn(*shape, dtype=torch.float64, generator=g)


def _cases(g):
    """(fused Function's apply, reference, tensor inputs, non-tensor arguments) on fresh float64 inputs."""
    x, w1, w2 = _rand(9, 5, g=g), _rand(16, 5, g=g) / 3, _rand(4, 16, g=g) / 4
    xa, xb = _rand(9, 2, g=g), _rand(9, 3, g=g)
    w3 = [_rand(8, 5, g=g), _rand(8, g=g), _rand(8, 8, g=g), _rand(8, g=g), _rand(2, 8, g=g), _rand(2, g=g)]
    f3, f6 = _rand(9, 6, 3, g=g), _rand(9, 12, 3, g=g)
    return {
        "mlp2": (Mlp2Fn.apply, mlp2_torch, [x, w1, w2], []),
        "mlp2_split": (Mlp2SplitFn.apply, mlp2_split_torch, [xa, xb, w1, w2], [2]),
        "mlp3": (Mlp3Fn.apply, mlp3_torch, [x] + w3, []),
        "plane_sum": (PlaneSumFn.apply, plane_sum_torch, [f3], [2]),
        "vm_product": (VmProductFn.apply, vm_product_torch, [f6], [2, False]),
        "vm_product_faithful": (VmProductFn.apply, vm_product_torch, [f6], [2, True]),
    }


def _second_order_grads(fn, tensors, args, g):
    """Gradients of a loss on the input gradient ⟨∂⟨y, c⟩/∂x0, v⟩² + Σ y² w.r.t. every input."""
    leaves = [t.clone().requires_grad_() for t in tensors]
    out = fn(*leaves, *args)
    outs = out if isinstance(out, tuple) else (out,)
    cots = [torch.randn(o.shape, dtype=o.dtype, generator=g) for o in outs]
    (gx,) = torch.autograd.grad(outs, leaves[0], cots, create_graph=True)  # no graph for a linear map (plane sum)
    v = torch.randn(gx.shape, dtype=gx.dtype, generator=g)
    loss = (gx * v).sum() ** 2 + sum(o.square().sum() for o in outs)
    return torch.autograd.grad(loss, leaves, allow_unused=True)


@pytest.mark.parametrize("name", ["mlp2", "mlp2_split", "mlp3", "plane_sum", "vm_product", "vm_product_faithful"])
def test_second_order_through_the_fused_function_equals_the_reference(name):
    seed = int(np.random.SeedSequence().generate_state(1)[0])  # fresh inputs every run
    fused, reference, tensors, args = _cases(torch.Generator().manual_seed(seed))[name]
    got = _second_order_grads(fused, tensors, args, torch.Generator().manual_seed(seed + 1))
    want = _second_order_grads(reference, tensors, args, torch.Generator().manual_seed(seed + 1))
    for a, b in zip(got, want):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    leaves = [t.clone().requires_grad_() for t in tensors]
    assert torch.autograd.gradgradcheck(lambda *t: fused(*t, *args), leaves)


@pytest.mark.parametrize("encoding", ["dense", "hash", "triplane", "tensorf", "dense+tri", "hash+tri"])
def test_eikonal_loss_outside_second_order_reaches_the_decoders(encoding):
    """What the review found: with fused decoders every decoder weight got no gradient (grid fields) or the
    backward raised (plane fields); now each parameter's gradient equals the reference path's."""
    bounds = np.array([[0.0, 1.0]] * 3)
    grads = {}
    for kernel in ("torch", "numba"):
        torch.manual_seed(0)
        field = build_field(FieldConfig(encoding=encoding, kernel=kernel, decoder_kernel=kernel), bounds)
        x = torch.rand(48, 3, generator=torch.Generator().manual_seed(1), requires_grad=True)
        (n,) = torch.autograd.grad(field.sdf(x).sum(), x, create_graph=True)
        ((n.norm(dim=-1) - 1) ** 2).mean().backward()
        grads[kernel] = {k: p.grad.to_dense() for k, p in field.named_parameters() if p.grad is not None}
    assert set(grads["numba"]) == set(grads["torch"]) and any("net" in k for k in grads["torch"])
    for k, want in grads["torch"].items():
        torch.testing.assert_close(grads["numba"][k], want, rtol=1e-4, atol=1e-5 * float(want.abs().max()) + 1e-9)


@pytest.mark.parametrize("encoding", ["triplane", "tensorf", "dense+tri", "hash+tri"])
@pytest.mark.parametrize("kernel", ["torch", "numba"])
def test_plane_fields_take_an_empty_batch(encoding, kernel):
    field = build_field(FieldConfig(encoding=encoding, kernel=kernel, decoder_kernel=kernel),
                        np.array([[0.0, 1.0]] * 3))
    out = field(torch.empty(0, 3))
    assert out.sdf.shape == (0,) and out.rgb_logits.shape == (0, 3)
