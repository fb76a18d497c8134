"""BufferPool: a buffer handed to torch is never reused while a tensor still shares its memory."""

import numpy as np
import torch

from inrslam.fields.kernels import TableLayout, multilinear
from inrslam.fields.kernels.function import unique_rows_of
from inrslam.fields.kernels.pool import BufferPool
from inrslam.fields.resolution import grid_entries


def test_buffer_is_reused_only_after_torch_frees_it():
    pool = BufferPool(max_buffers=2)
    a = pool.take((100, 2), np.float32)
    a[:] = 1.0
    ta = torch.from_numpy(a)
    ptr = a.ctypes.data
    del a  # torch still holds the array
    b = pool.take((100, 2), np.float32)
    assert b.ctypes.data != ptr
    b[:] = 2.0
    assert torch.all(ta == 1.0)
    del ta  # the only user is gone: the same memory comes back
    c = pool.take((50,), np.int64)
    assert c.ctypes.data == ptr and c.shape == (50,) and c.dtype == np.int64 and c.flags.c_contiguous


def test_grows_and_falls_back_to_plain_arrays_when_all_are_busy():
    pool = BufferPool(max_buffers=1)
    a = pool.take((10,), np.float64)
    ptr = a.ctypes.data
    held = pool.take((10,), np.float64)  # the only buffer is in use: a plain array, not kept
    assert held.ctypes.data != ptr and pool.nbytes == pool._bases[0].nbytes
    del a
    again = pool.take((10,), np.float64)
    assert again.ctypes.data == ptr
    del again
    big = pool.take((1000, 3), np.float64)  # the freed buffer is too small: replaced by a larger one
    assert big.shape == (1000, 3) and pool.nbytes >= big.nbytes and len(pool._bases) == 1
    big[:] = 3.0
    assert np.all(big == 3.0)


def test_kept_sparse_gradient_is_not_overwritten_by_the_next_backward():
    layout = TableLayout.build(grid_entries(np.array([1.2, 1.0, 0.8]), 0.3, 0.05, 3, True, 10, False))
    table = torch.randn(layout.total_rows, 2, requires_grad=True)
    g = torch.Generator().manual_seed(0)
    x1, x2 = torch.rand(300, 3, generator=g), torch.rand(300, 3, generator=g)
    multilinear(x1, table, layout, "numba", sparse=True).sum().backward()
    kept = table.grad
    # straight from the fused backward: the optimizer trusts its rows
    assert unique_rows_of(layout, kept._indices()[0], kept._values())
    expected = kept.to_dense().clone()
    table.grad = None
    multilinear(x2, table, layout, "numba", sparse=True).square().sum().backward()
    torch.testing.assert_close(kept.to_dense(), expected, rtol=0, atol=0)  # memory of a live gradient untouched
    assert not torch.equal(table.grad.to_dense(), expected)
    # once both are dropped the pool reuses their memory: the third gradient is still exact
    del kept
    table.grad = None
    multilinear(x1, table, layout, "numba", sparse=True).sum().backward()
    torch.testing.assert_close(table.grad.to_dense(), expected, rtol=0, atol=0)
    vptr = table.grad._values().data_ptr()
    assert any(b.ctypes.data <= vptr < b.ctypes.data + b.nbytes for b in layout.workspace.grad_pool._bases)


def test_smallest_fitting_buffer_is_taken():
    pool = BufferPool()
    big, small = pool.take((1000,), np.float64), pool.take((10,), np.float64)
    big_ptr, small_ptr = big.ctypes.data, small.ctypes.data
    del big, small
    a = pool.take((8,), np.float64)  # fits both: the small one
    b = pool.take((900,), np.float64)  # only the big one fits
    assert (a.ctypes.data, b.ctypes.data) == (small_ptr, big_ptr) and len(pool._bases) == 2


def test_gradient_with_other_indices_on_the_same_values_is_not_trusted():
    layout = TableLayout.build(grid_entries(np.array([1.2, 1.0, 0.8]), 0.3, 0.05, 3, True, 10, False))
    table = torch.randn(layout.total_rows, 2, requires_grad=True)
    multilinear(torch.rand(100, 3), table, layout, "numba", sparse=True).sum().backward()
    g = table.grad
    idx = g._indices().clone()
    idx[0, 1] = idx[0, 0]  # a duplicate row, same values memory
    forged = torch.sparse_coo_tensor(idx, g._values(), g.shape, check_invariants=False)
    assert unique_rows_of(layout, g._indices()[0], g._values())
    assert not unique_rows_of(layout, forged._indices()[0], forged._values())


def test_empty_gradient_can_be_accumulated():
    layout = TableLayout.build(grid_entries(np.array([1.2, 1.0, 0.8]), 0.3, 0.05, 3, True, 10, False))
    table = torch.randn(layout.total_rows, 2, requires_grad=True)
    multilinear(torch.zeros(0, 3), table, layout, "numba", sparse=True).sum().backward()
    assert table.grad._nnz() == 0
    x = torch.rand(30, 3)
    multilinear(x, table, layout, "numba", sparse=True).sum().backward()  # accumulates into the empty gradient
    t2 = table.detach().clone().requires_grad_()
    multilinear(x, t2, layout, "torch").sum().backward()
    torch.testing.assert_close(table.grad.to_dense(), t2.grad)
