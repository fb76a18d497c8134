"""Autograd wrapper of the fused kernels and the backend dispatch ``multilinear``."""

from __future__ import annotations

import weakref

import numba
import numpy as np
import torch

from inrslam.fields.kernels import generic, sparse_rows, trilinear
from inrslam.fields.kernels.layout import TableLayout
from inrslam.fields.kernels.torch_interp import interp_torch

#: Tables with more rows than this get a sparse (COO, unique rows) gradient from the fused backward;
#: smaller ones get a dense gradient (cheaper when most rows are touched anyway).
DENSE_GRAD_MAX_ROWS = 1 << 16


#: Sparse table gradients of trilinear tables up to this size (M·F·itemsize) are accumulated in a kept dense
#: (M,F) scratch array and drained row-sorted (hash grids); larger ones (fine dense grids) use the row-slot kernels.
ACCUMULATOR_MAX_BYTES = 64 << 20


def row_slots(layout: TableLayout) -> np.ndarray:
    """The (M,) int32 row → slot array (all −1 between uses) of the row-compaction kernels, created on first use."""
    ws = layout.workspace
    if ws.slots is None or ws.slots.shape[0] != layout.total_rows:
        ws.slots = np.full(layout.total_rows, -1, dtype=np.int32)
    return ws.slots


def _accumulator(layout: TableLayout, n_feat: int, dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(acc (M,F), mark_off (E,), mark bitmap uint8) scratch of the accumulator table backward, all zero between
    uses; entry e's row bits start at byte mark_off[e] (byte-aligned per entry, so threads never share a byte)."""
    acc = layout.workspace.accumulator
    if acc is None or acc[0].shape != (layout.total_rows, n_feat) or acc[0].dtype != np.dtype(dtype):
        nbytes = (layout.rows + 7) // 8
        mark_off = np.zeros_like(nbytes)
        mark_off[1:] = np.cumsum(nbytes)[:-1]
        acc = (np.zeros((layout.total_rows, n_feat), dtype=dtype), mark_off, np.zeros(int(nbytes.sum()), np.uint8))
        layout.workspace.accumulator = acc
    return acc


#: Row-block size (log2) of the row parts of the trilinear sparse backward (see ``_row_parts``).
PART_LOG2 = 12


def _row_parts(layout: TableLayout) -> int:
    """Row parts P per entry of the trilinear sparse backward: one per thread when there are too few entries to
    keep every thread busy (a 2-level dense grid), else 1 (entries alone balance the load)."""
    threads = numba.get_num_threads()
    return threads if layout.n_entries < 2 * threads else 1


def _sparse_out(layout: TableLayout, n_points: int, n_feat: int, dtype, parts: int = 1) -> tuple[np.ndarray, ...]:
    """(cap_off (P·E,), rows (C,) int32, values (C,F)) scratch of the sparse table backward, kept in the workspace
    and reused while it is large enough; item i = p·E + e holds at most min(N·2^D_e, rows of part p of entry e) rows
    (blocks of 2^PART_LOG2 rows dealt round-robin to P parts). Never zeroed (kernels write on first touch), so a
    backward pays neither a large allocation nor its page faults."""
    blk = 1 << PART_LOG2
    part_rows = layout.rows if parts == 1 else -(-layout.rows // blk) // parts * blk + blk
    caps = np.minimum(n_points * (1 << layout.ndim), np.minimum(part_rows, layout.rows))
    caps = np.tile(caps, parts).astype(np.int64)
    cap_off = np.zeros_like(caps)
    cap_off[1:] = np.cumsum(caps)[:-1]
    need = int(caps.sum())
    out = layout.workspace.sparse_out
    if out is None or out[0].shape[0] < need or out[1].shape[1] != n_feat or out[1].dtype != np.dtype(dtype):
        # grow to the largest capacity needed so far (capped by the table size)
        cap = max(need, out[0].shape[0] if out is not None and out[1].dtype == np.dtype(dtype) else 0)
        out = (np.empty(cap, np.int32), np.empty((cap, n_feat), dtype=dtype))  # rows < 2^31 (as the slots)
        layout.workspace.sparse_out = out
    return cap_off, out[0], out[1]


def _meta(layout: TableLayout):
    return (layout.ndim, layout.axes, layout.res, layout.scale, layout.offset, layout.stride, layout.hashed,
            layout.rows, layout.row_off)


def _tri_meta(layout: TableLayout):
    return (layout.res, layout.scale, layout.offset, layout.lo, layout.hi, layout.stride, layout.hashed,
            layout.rows, layout.row_off)


def _sparse_grad(layout: TableLayout, shape, dtype, counts: np.ndarray, fill) -> torch.Tensor:
    """Sparse COO (M,F) table gradient of Σ counts unique rows, written into (rows, vals) by ``fill(rows, vals)``.
    Both arrays come from the workspace's ``BufferPool``: a steady stream of backward passes reuses the same memory."""
    nnz = int(counts.sum())
    if nnz == 0:  # torch-owned empty arrays: a later accumulation may resize them in place
        return torch.sparse_coo_tensor(torch.empty((1, 0), dtype=torch.int64),
                                       torch.from_numpy(np.empty((0, shape[1]), dtype)).clone(), shape,
                                       check_invariants=False)
    pool = layout.workspace.grad_pool
    rows = pool.take((nnz,), np.int64)
    vals = pool.take((nnz, shape[1]), dtype)
    fill(rows, vals)
    # lets the optimizer skip de-duplicating this exact gradient (the weak references die with its memory)
    layout.workspace.last_grad = (weakref.ref(rows), weakref.ref(vals))
    return torch.sparse_coo_tensor(torch.from_numpy(rows)[None], torch.from_numpy(vals), shape,
                                   check_invariants=False)


def unique_rows_of(layout: TableLayout, rows: torch.Tensor, values: torch.Tensor) -> bool:
    """True if ``rows`` (K,) and ``values`` (K,F) (a sparse gradient's) are those of the last fused sparse gradient
    of ``layout``, whose rows are unique."""
    refs = layout.workspace.last_grad
    if refs is None or rows.device.type != "cpu" or values.device.type != "cpu":
        return False
    r, v = refs[0](), refs[1]()
    return (r is not None and v is not None and r.ctypes.data == rows.data_ptr() and r.shape == tuple(rows.shape)
            and v.ctypes.data == values.data_ptr() and v.shape == tuple(values.shape) and values.is_contiguous()
            and rows.is_contiguous())


def _level_major(g: np.ndarray, layout: TableLayout) -> np.ndarray:
    """(E,N,F) copy of g (N,E,F) in a scratch array kept in the workspace (grown, never shrunk)."""
    buf = layout.workspace.level_major
    if buf is None or buf.dtype != g.dtype or buf.size < g.size:
        buf = layout.workspace.level_major = np.empty(g.size, g.dtype)
    gT = buf[: g.size].reshape(g.shape[1], g.shape[0], g.shape[2])
    trilinear.level_major(g, gT)
    return gT


def table_grad_numba(xn: np.ndarray, g: np.ndarray, layout: TableLayout, shape, dtype, sparse: bool) -> torch.Tensor:
    """∂L/∂T from the fused kernel: sparse COO with unique rows (``sparse``) or dense (M,F)."""
    M, F = shape
    if not sparse:
        grad = torch.zeros(M, F, dtype=dtype)
        if layout.trilinear:
            trilinear.tri_backward_table_dense(xn, g, *_tri_meta(layout), grad.numpy())
        else:
            generic.interp_backward_table_dense(xn, g, *_meta(layout), grad.numpy())
        return grad
    if layout.trilinear and M * F * g.itemsize <= ACCUMULATOR_MAX_BYTES:
        acc, mark_off, mark = _accumulator(layout, F, g.dtype)
        gT = _level_major(g, layout)  # (E,N,F): each level reads its gradient contiguously
        counts = np.zeros(layout.n_entries, np.int64)
        trilinear.tri_backward_table_acc(xn, gT, *_tri_meta(layout), mark_off, acc, mark, counts)
        return _sparse_grad(layout, shape, g.dtype, counts,
                            lambda rows, vals: sparse_rows.drain_marked_rows(layout.rows, layout.row_off, mark_off,
                                                                             counts, acc, mark, rows, vals))
    if layout.trilinear:
        parts = _row_parts(layout)
        cap_off, out_rows, out_vals = _sparse_out(layout, xn.shape[0], F, g.dtype, parts)
        counts = np.zeros(layout.n_entries * parts, np.int64)
        trilinear.tri_backward_table_sparse(xn, g, *_tri_meta(layout), row_slots(layout), parts, PART_LOG2, cap_off,
                                            out_rows, out_vals, counts)
    else:
        cap_off, out_rows, out_vals = _sparse_out(layout, xn.shape[0], F, g.dtype)
        counts = np.zeros(layout.n_entries, np.int64)
        generic.interp_backward_table_sparse(xn, g, *_meta(layout), row_slots(layout), cap_off, out_rows, out_vals,
                                             counts)
    return _sparse_grad(layout, shape, g.dtype, counts,
                        lambda rows, vals: sparse_rows.compact_entries(cap_off, counts, out_rows, out_vals, rows, vals))


class MultilinearFn(torch.autograd.Function):
    """Fused lookup: forward (N,E,F); backward to xn (dense) and to the table (sparse rows or dense).

    Double backward (``create_graph=True``, e.g. losses on SDF normals) recomputes through the reference.
    """

    @staticmethod
    def forward(ctx, xn: torch.Tensor, table: torch.Tensor, layout: TableLayout, sparse: bool) -> torch.Tensor:
        tab = table.detach()
        xn_np = xn.detach().contiguous().numpy()
        ctx.jac = None
        if layout.trilinear:
            out = torch.empty(xn.shape[0], layout.n_entries, tab.shape[1], dtype=tab.dtype)
            # one lookup for both: keep ∂out/∂xn for the input backward (an empty array: no Jacobian)
            jac = np.empty((xn.shape[0] if ctx.needs_input_grad[0] else 0, layout.n_entries, tab.shape[1], 3),
                           dtype=xn_np.dtype)
            trilinear.tri_forward(xn_np, tab.numpy(), *_tri_meta(layout), out.numpy(), jac)
            ctx.jac = jac if ctx.needs_input_grad[0] else None
        else:
            out = torch.zeros(xn.shape[0], layout.n_entries, tab.shape[1], dtype=tab.dtype)
            generic.interp_forward(xn_np, tab.numpy(), *_meta(layout), out.numpy())
        ctx.save_for_backward(xn, table)
        ctx.layout = layout
        ctx.sparse = sparse
        return out

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        xn, table = ctx.saved_tensors
        layout = ctx.layout
        need_x, need_t = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if torch.is_grad_enabled():  # create_graph: differentiate the (twice-differentiable) reference
            inputs = [v for v, need in ((xn, need_x), (table, need_t)) if need]
            out = interp_torch(xn, table, layout)
            grads = list(torch.autograd.grad(out, inputs, g, create_graph=True, allow_unused=True))
            gx = grads.pop(0) if need_x else None
            gt = grads.pop(0) if need_t else None
            return gx, gt, None, None
        g_np = g.contiguous().numpy()
        xn_np = xn.detach().contiguous().numpy()
        gx = gt = None
        if need_x:
            gx64 = np.zeros((xn.shape[0], 3), np.float64)
            if ctx.jac is not None:  # trilinear: the forward kept the Jacobian (it knew the input grad was needed)
                trilinear.tri_backward_x_jac(ctx.jac, g_np, gx64)
            else:
                generic.interp_backward_x(xn_np, table.detach().numpy(), g_np, *_meta(layout), gx64)
            gx = torch.from_numpy(gx64).to(xn.dtype)
        if need_t:
            gt = table_grad_numba(xn_np, g_np, layout, tuple(table.shape), table.dtype, ctx.sparse)
        return gx, gt, None, None


def multilinear(xn: torch.Tensor, table: torch.Tensor, layout: TableLayout, backend: str = "auto",
                sparse: bool | None = None) -> torch.Tensor:
    """Multilinear lookup of E entries: xn (N,3) in [0,1] (clamped; ±inf too), table (M,F) -> (N,E,F).

    A point with a NaN coordinate gets NaN features and no gradient (a loss over it turns NaN, which the SLAM loop
    treats as a failed step), on every backend.
    backend: "numba" (fused CPU kernel), "torch" (reference, any device) or "auto" (numba on CPU tensors).
    sparse: table-gradient layout of the fused path; None = sparse iff M > DENSE_GRAD_MAX_ROWS.
    """
    if backend == "auto":
        backend = "numba" if table.device.type == "cpu" else "torch"
    if backend not in ("torch", "numba"):
        raise ValueError(f"unknown kernel backend {backend!r} (choices: auto, torch, numba)")
    if xn.dim() != 2 or xn.shape[-1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {tuple(xn.shape)}")
    if xn.device.type == "cpu" and not bool(torch.isnan(xn).any()):  # (on a GPU: no host sync to find out)
        return _lookup(xn, table, layout, backend, sparse)
    nan = torch.isnan(xn).any(dim=1)
    out = _lookup(torch.where(nan[:, None], torch.zeros_like(xn), xn), table, layout, backend, sparse)
    return out.masked_fill(nan[:, None, None], float("nan"))


def _lookup(xn: torch.Tensor, table: torch.Tensor, layout: TableLayout, backend: str, sparse: bool | None
            ) -> torch.Tensor:
    if backend == "torch":
        return interp_torch(xn.to(table.dtype), table, layout)
    if table.device.type != "cpu" or xn.device.type != "cpu":
        raise ValueError("kernel='numba' needs CPU tensors; use kernel='auto' or 'torch' on other devices")
    if table.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"kernel='numba' supports float32/float64 tables, got {table.dtype}")
    if sparse is None:
        sparse = table.shape[0] > DENSE_GRAD_MAX_ROWS
    xn = xn.to(table.dtype)
    if not torch.is_grad_enabled():  # no graph is recorded: don't let the forward prepare an input backward
        xn = xn.detach()
    return MultilinearFn.apply(xn, table, layout, bool(sparse))
