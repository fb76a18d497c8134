"""Second-order (``create_graph``) backward of the fused lookups (``InputGradFn``) vs the PyTorch reference: values and
gradients on fresh random inputs, float64 gradcheck, an analytic trilinear case, and ``input_grad_only``."""

import contextlib

import numpy as np
import pytest
import torch

from inrslam.fields.kernels import (
    InputGradFn,
    MultilinearJacFn,
    TableLayout,
    function,
    input_grad_only,
    multilinear,
    second_order,
)
from inrslam.fields.resolution import grid_entries, line_entries, plane_entries, plane_sizes

EXTENT = np.array([1.2, 1.0, 0.8])
ENTRIES = {
    "dense": grid_entries(EXTENT, 0.3, 0.1, 2, False, 19, False),
    "hash": grid_entries(EXTENT, 0.3, 0.05, 3, True, 10, False),  # level 2 hashed
    "planes": plane_entries(plane_sizes(EXTENT, 0.3, 0.1, 2, False), False),
    "planes+lines": (plane_entries(plane_sizes(EXTENT, 0.3, 0.1, 2, False), False)
                     + line_entries(plane_sizes(EXTENT, 0.3, 0.1, 2, False), False)),
}


def _normals_loss_grads(backend, layout, table, x, w, cot, sparse, scoped=False):
    """A NeuS-like use: s = tanh(features)·w, n = ∂s/∂x (create_graph), loss = ⟨n, cot⟩ + Σ s n_0. ``scoped``: the
    lookup inside ``second_order`` (``MultilinearJacFn``) and the normals inside ``input_grad_only``, as
    `render_rays` does; else ``MultilinearFn`` with ``InputGradFn``."""
    t = table.clone().requires_grad_()
    p = x.clone().requires_grad_()
    with second_order() if scoped else contextlib.nullcontext():
        feat = multilinear(p, t, layout, backend, sparse=sparse)
    s = torch.tanh(feat.reshape(x.shape[0], -1)) @ w
    with input_grad_only() if scoped else contextlib.nullcontext():
        (n,) = torch.autograd.grad(s.sum(), p, create_graph=True)
    ((n * cot).sum() + (s * n[:, 0]).sum()).backward()
    gt = t.grad.to_dense() if t.grad.is_sparse else t.grad
    return n.detach(), p.grad, gt


#: (entries, sparse table gradient, scoped): every layout on both table-gradient layouts through
#: ``MultilinearJacFn`` (what `render_rays` uses), and ``InputGradFn`` on a grid and on planes + lines
CASES = ([(name, sparse, True) for name in ENTRIES for sparse in (False, True)]
         + [("dense", True, False), ("planes+lines", False, False)])


@pytest.mark.parametrize("name,sparse,scoped", CASES)
def test_second_order_matches_reference(name, sparse, scoped):
    layout = TableLayout.build(ENTRIES[name])
    table = torch.randn(layout.total_rows, 3, dtype=torch.float64)
    x = torch.rand(200, 3, dtype=torch.float64) * 1.2 - 0.1  # some points outside the box (clamped)
    w = torch.randn(layout.n_entries * 3, dtype=torch.float64)
    cot = torch.randn(200, 3, dtype=torch.float64)
    fused = _normals_loss_grads("numba", layout, table, x, w, cot, sparse, scoped)
    ref = _normals_loss_grads("torch", layout, table, x, w, cot, None)
    for a, b, what in zip(fused, ref, ("normals", "d/dx", "d/dtable")):
        assert b.abs().sum() > 0, what
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * b.abs().max().item(), msg=what)


@pytest.mark.parametrize("name", ["dense", "hash", "planes+lines"])
def test_jac_fn_gradcheck_float64(name):
    """(out, J) of ``MultilinearJacFn`` and their fused backward against numerical derivatives."""
    layout = TableLayout.build(ENTRIES[name])
    x = (torch.rand(10, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    table = torch.randn(layout.total_rows, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x_, t_: MultilinearJacFn.apply(x_, t_, layout, False), (x, table),
                                    eps=1e-6, atol=1e-6, fast_mode=True)
    assert torch.autograd.gradcheck(lambda x_, t_: MultilinearJacFn.apply(x_, t_, layout, False)[1], (x, table),
                                    eps=1e-6, atol=1e-6, fast_mode=True)


@pytest.mark.parametrize("name", ["dense", "hash", "planes+lines"])
def test_input_grad_fn_gradcheck_float64(name):
    layout = TableLayout.build(ENTRIES[name])
    n = 10
    g = torch.randn(n, layout.n_entries, 2, dtype=torch.float64, requires_grad=True)
    x = (torch.rand(n, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    table = torch.randn(layout.total_rows, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda g_, x_, t_: InputGradFn.apply(g_, x_, t_, layout, None, False),
                                    (g, x, table), eps=1e-6, atol=1e-6, fast_mode=True)


def test_trilinear_hessian_of_a_product_is_analytic():
    """A dense level holding u_x·u_y·u_z at its vertices interpolates it exactly: ∂²f/∂p̂_x∂p̂_y = s_x s_y u_z and
    ∂²f/∂p̂_x² = 0 (s_a = du_a/dp̂_a, the level's scale)."""
    layout = TableLayout.build([dict(axes=[0, 1, 2], res=[5, 6, 7], scale=[4.0, 5.0, 6.0], offset=[0.0, 0.0, 0.0],
                                     rows=None, hashed=False)])
    ii, jj, kk = torch.meshgrid(*(torch.arange(r, dtype=torch.float64) for r in (5, 6, 7)), indexing="ij")
    table = (ii * jj * kk).permute(2, 1, 0).reshape(-1, 1).clone().requires_grad_()  # row = i + 5 j + 30 k
    x = (torch.rand(40, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    f = multilinear(x, table, layout, "numba", sparse=False)[:, 0, 0]
    (gx,) = torch.autograd.grad(f.sum(), x, create_graph=True)
    (hx,) = torch.autograd.grad(gx[:, 0].sum(), x)
    u = x.detach() * torch.tensor([4.0, 5.0, 6.0], dtype=torch.float64)
    torch.testing.assert_close(f, u.prod(-1))
    torch.testing.assert_close(hx, torch.stack([torch.zeros_like(u[:, 0]), 20.0 * u[:, 2], 24.0 * u[:, 1]], -1))


def test_input_grad_only_skips_the_table_gradient(monkeypatch):
    """Inside the scope the fused backward computes no table gradient (none is asked for); the input gradient and
    what a later backward gives the table are unchanged."""
    calls = []
    real = function.table_grad_numba
    monkeypatch.setattr(function, "table_grad_numba", lambda *a, **k: calls.append(1) or real(*a, **k))
    layout = TableLayout.build(ENTRIES["dense"])
    table = torch.randn(layout.total_rows, 2, requires_grad=True)
    x = torch.rand(50, 3, requires_grad=True)
    res = []
    for scoped in (False, True):
        table.grad = None
        out = multilinear(x, table, layout, "numba").square().sum()
        calls.clear()
        if scoped:
            with input_grad_only():
                (gx,) = torch.autograd.grad(out, x, retain_graph=True)
        else:
            (gx,) = torch.autograd.grad(out, x, retain_graph=True)
        assert len(calls) == (0 if scoped else 1)
        out.backward()
        res.append((gx, table.grad.to_dense()))
    torch.testing.assert_close(res[0][0], res[1][0], rtol=0, atol=0)
    torch.testing.assert_close(res[0][1], res[1][1], rtol=0, atol=0)
    assert res[1][1].abs().sum() > 0


def _row_slot_case(layout: TableLayout) -> tuple[torch.Tensor, ...]:
    """Fresh float64 (table, points partly outside the box, decoder weights, normals' cotangent) for 200 points."""
    table = torch.randn(layout.total_rows, 2, dtype=torch.float64)
    x = torch.rand(200, 3, dtype=torch.float64) * 1.2 - 0.1
    w = torch.randn(layout.n_entries * 2, dtype=torch.float64)
    cot = torch.randn(200, 3, dtype=torch.float64)
    return table, x, w, cot


@pytest.mark.parametrize("name", ["dense", "hash"])
def test_second_order_row_slot_path_matches_reference(monkeypatch, name):
    """Tables too large for the accumulator (fine dense grids) take the row-slot scatter."""
    monkeypatch.setattr(function, "ACCUMULATOR_MAX_BYTES", 0)
    layout = TableLayout.build(ENTRIES[name])
    table, x, w, cot = _row_slot_case(layout)
    fused = _normals_loss_grads("numba", layout, table, x, w, cot, True, scoped=True)
    ref = _normals_loss_grads("torch", layout, table, x, w, cot, None)
    for a, b, what in zip(fused, ref, ("normals", "d/dx", "d/dtable")):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * b.abs().max().item(), msg=what)


@pytest.mark.parametrize("name", ["dense", "planes+lines"])
def test_second_order_row_slot_path_with_int64_row_indices(monkeypatch, name):
    """The row-slot scatters of the second-order table gradient (trilinear and generic) with int64 row numbers and
    slots, as tables of 2^31 rows or more get them (forced here): bit for bit the int32 results and the reference's."""
    monkeypatch.setattr(function, "ACCUMULATOR_MAX_BYTES", 0)
    layout = TableLayout.build(ENTRIES[name])
    table, x, w, cot = _row_slot_case(layout)
    fused = []
    for index in (np.int32, np.int64):
        if index is np.int64:
            monkeypatch.setattr(function, "INT32_MAX_ROWS", 0)  # every table counts as large
        fused.append(_normals_loss_grads("numba", layout, table, x, w, cot, True, scoped=True))
        assert layout.workspace.slots.dtype == layout.workspace.sparse_out[0].dtype == np.dtype(index)
        assert np.all(layout.workspace.slots == -1)
    ref = _normals_loss_grads("torch", layout, table, x, w, cot, None)
    for a, b, c, what in zip(fused[1], fused[0], ref, ("normals", "d/dx", "d/dtable")):
        assert torch.equal(a, b), what
        torch.testing.assert_close(a, c, rtol=1e-9, atol=1e-9 * c.abs().max().item(), msg=what)
