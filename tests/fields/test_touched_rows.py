"""`TouchedRows`: which table rows the fused backward hands to lazy Adam. "read" (every F's default): every row read
with a non-zero weight; "gradient": only rows read by a point whose output gradient is not zero (the points with a
zero gradient are dropped first, `fields.kernels.compact.nonzero_points`, against its torch reference)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.fields.config import TouchedRows
from inrslam.fields.encoders import GridEncoder
from inrslam.fields.kernels import TableLayout, function, interp_torch, multilinear
from inrslam.fields.kernels.compact import nonzero_points, nonzero_points_torch
from inrslam.fields.optim import make_optimizer
from inrslam.fields.resolution import grid_entries, plane_entries, plane_sizes

EXTENT = np.array([1.2, 1.0, 0.8])


def _gradient_with_zero_runs(n: int, shape: tuple[int, ...], seed: int) -> torch.Tensor:
    """Random (n, *shape) gradient whose points are zero in runs (as the tails of rays behind a surface)."""
    g = torch.Generator().manual_seed(seed)
    out = torch.randn((n,) + shape, generator=g)
    run = torch.randint(0, 2, ((n + 6) // 7,), generator=g).repeat_interleave(7)[:n].bool()
    out[run] = 0.0
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_nonzero_points_equal_the_reference(seed, dtype):
    g = _gradient_with_zero_runs(500, (2, 3), seed).to(dtype)
    g[3, 1, 2] = float("nan")  # a NaN gradient is kept (it must still reach the table)
    g[10] = 0.0
    g[10, 0, 0] = -0.0  # negative zero is zero
    xn = torch.rand(500, 3, generator=torch.Generator().manual_seed(seed + 5), dtype=dtype)
    x_k, g_k = nonzero_points(xn.numpy(), g.numpy())
    x_r, g_r = nonzero_points_torch(xn, g)
    assert 0 < x_r.shape[0] < 500 and x_k.flags["C_CONTIGUOUS"] and g_k.flags["C_CONTIGUOUS"]
    assert torch.equal(torch.from_numpy(x_k), x_r)
    torch.testing.assert_close(torch.from_numpy(g_k), g_r, rtol=0, atol=0, equal_nan=True)
    assert bool(torch.isnan(torch.from_numpy(g_k)).any()) and 10 not in set(torch.nonzero(
        (xn[:, None] == torch.from_numpy(x_k)[None]).all(-1))[:, 0].tolist())


def test_nonzero_points_all_kept_and_none_kept():
    xn = np.random.default_rng(0).random((20, 3), dtype=np.float32)
    g = np.ones((20, 1, 2), np.float32)
    x_k, g_k = nonzero_points(xn, g)
    assert x_k is xn and g_k is g  # nothing to drop: no copy
    x0, g0 = nonzero_points(xn, np.zeros_like(g))
    assert x0.shape == (0, 3) and g0.shape == (0, 1, 2)


def _table_grad(touched: str, layout, table, x, cot, backend="numba", sparse=True):
    t = table.clone().requires_grad_()
    multilinear(x, t, layout, backend, sparse=sparse, touched=touched).backward(cot)
    return t.grad


LAYOUTS = {"dense": lambda: grid_entries(EXTENT, 0.3, 0.1, 2, False, 19, False),
           "planes": lambda: plane_entries(plane_sizes(EXTENT, 0.3, 0.1, 2, False), False)}


@pytest.mark.parametrize("name", list(LAYOUTS))
@pytest.mark.parametrize("sparse, accumulator", [(True, True), (True, False), (False, False)])
def test_gradient_rows_are_the_rows_of_points_with_a_gradient(name, sparse, accumulator, monkeypatch):
    """Every fused backward: the accumulator kernel, the slot kernels of large tables
    (forced here by a zero accumulator budget), the generic (plane) kernels and the dense gradient."""
    if not accumulator:
        monkeypatch.setattr(function, "ACCUMULATOR_MAX_BYTES", 0)
    layout = TableLayout.build(LAYOUTS[name]())
    table = torch.randn(layout.total_rows, 2)
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(3))
    cot = _gradient_with_zero_runs(300, (layout.n_entries, 2), 4)
    ref = table.clone().requires_grad_()
    interp_torch(x, ref, layout).backward(cot)
    for touched in ("read", "gradient"):
        gt = _table_grad(touched, layout, table, x, cot, sparse=sparse)
        torch.testing.assert_close(gt.to_dense(), ref.grad, rtol=1e-5, atol=1e-6)  # same values either way
    g_read = _table_grad("read", layout, table, x, cot).coalesce()
    g_grad = _table_grad("gradient", layout, table, x, cot).coalesce()
    # rows: "read" = every row the points read; "gradient" = only the rows read by points with a gradient
    read_rows = set(g_read.indices()[0].tolist())
    keep = (cot.reshape(300, -1) != 0).any(1)
    t_keep = table.clone().requires_grad_()
    interp_torch(x[keep], t_keep, layout).sum().backward()  # weights are positive: non-zero rows = rows read
    expected = set(torch.nonzero(t_keep.grad.abs().sum(1) > 0)[:, 0].tolist())
    assert set(g_grad.indices()[0].tolist()) == expected
    assert expected < read_rows  # the zero-gradient points read rows nobody else reads
    assert bool((g_read.to_dense()[sorted(read_rows - expected)] == 0).all())


def test_lazy_adam_leaves_rows_of_zero_gradient_points_alone_only_with_gradient():
    """After a first step moved every row the points read (moments non-zero), a second step whose only gradient
    comes from some of them: with "read" every row read moves (its momentum), with "gradient" the rows read only by
    the zero-gradient points keep parameters and moments. (A table small enough for a dense gradient, at most
    DENSE_GRAD_MAX_ROWS rows, updates its non-zero rows either way.)"""
    x = torch.rand(200, 3, generator=torch.Generator().manual_seed(0))
    results = {}
    for touched in ("read", "gradient"):
        torch.manual_seed(0)
        # 2 cm cells: 127k rows, more than DENSE_GRAD_MAX_ROWS, so the fused backward gives a sparse gradient
        enc = GridEncoder(EXTENT, 0.02, 0.02, 1, 2, hashed=False, log2_hashmap_size=19, faithful=False, init=0.1,
                          kernel="numba")
        enc.touched = TouchedRows(touched)
        opt = make_optimizer(enc, 0.01)
        opt.zero_grad()
        enc(x).sum().backward()
        opt.step()
        before = enc.table.detach().clone()
        m_before = opt.state[enc.table]["exp_avg"].clone()
        opt.zero_grad()
        w = torch.zeros(200, 1)
        w[:20] = 1.0  # only the first 20 points carry gradient
        (enc(x) * w).sum().backward()
        opt.step()
        moved = (enc.table.detach() != before).any(1)
        results[touched] = (moved, (opt.state[enc.table]["exp_avg"] != m_before).any(1))
    layout = enc.layout
    t_keep = torch.zeros_like(enc.table, requires_grad=True)
    interp_torch(x[:20], t_keep, layout).sum().backward()  # weights are positive: non-zero rows = rows read
    rows_grad = t_keep.grad.abs().sum(1) > 0
    t_all = torch.zeros_like(enc.table, requires_grad=True)
    interp_torch(x, t_all, layout).sum().backward()
    rows_read = t_all.grad.abs().sum(1) > 0
    assert bool((rows_read & ~rows_grad).any())
    assert torch.equal(results["gradient"][0], rows_grad) and torch.equal(results["gradient"][1], rows_grad)
    assert torch.equal(results["read"][0], rows_read) and torch.equal(results["read"][1], rows_read)


def test_unknown_touched_rows_is_a_clear_error():
    layout = TableLayout.build(grid_entries(EXTENT, 0.3, 0.1, 1, False, 19, False))
    with pytest.raises(ValueError, match="touched rows 'all'"):
        multilinear(torch.rand(4, 3), torch.randn(layout.total_rows, 2), layout, "numba", touched="all")


@pytest.mark.parametrize("backend,touched", [("torch", "read"), ("numba", "read"), ("numba", "gradient")])
@pytest.mark.parametrize("sparse", [False, True])
def test_an_empty_batch_of_points_reads_and_differentiates(backend, touched, sparse):
    # a batch whose rays hit nothing (the EHE map before any voxel is allocated) has no sample points at all
    layout = TableLayout.build(grid_entries(np.array([1.0, 1.0, 1.0]), 0.3, 0.1, 2, False, 19, False))
    table = torch.randn(layout.total_rows, 2, requires_grad=True)
    x = torch.rand(0, 3, requires_grad=True)
    out = multilinear(x, table, layout, backend, sparse=sparse, touched=touched)
    assert out.shape[0] == 0
    out.sum().backward()
    assert x.grad.shape == (0, 3) and not table.grad.to_dense().any()
    enc = GridEncoder(np.array([1.0, 1.0, 1.0]), 0.3, 0.1, 2, 2, False, 19, False, 1e-4, backend)
    assert enc(torch.rand(0, 3)).shape == (0, 4)


def test_nonzero_points_of_no_points():
    xn, g = np.zeros((0, 3)), np.zeros((0, 2, 2))
    kept_x, kept_g = nonzero_points(xn, g)
    assert kept_x.shape == (0, 3) and kept_g.shape == (0, 2, 2)
