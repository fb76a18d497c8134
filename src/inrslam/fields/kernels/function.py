"""Autograd wrapper of the fused kernels and the backend dispatch ``multilinear``."""

from __future__ import annotations

import contextlib
import threading
import weakref

import numba
import numpy as np
import torch

from inrslam.fields.kernels import generic, sparse_rows, trilinear
from inrslam.fields.kernels.compact import nonzero_points
from inrslam.fields.kernels.layout import TableLayout
from inrslam.fields.kernels.torch_interp import interp_torch

#: Tables with more rows than this get a sparse (COO, unique rows) gradient from the fused backward;
#: smaller ones get a dense gradient (cheaper when most rows are touched anyway).
DENSE_GRAD_MAX_ROWS = 1 << 16


#: Sparse table gradients of trilinear tables up to this size (M·F·itemsize) are accumulated in a kept dense
#: (M,F) scratch array and drained row-sorted (hash grids); larger ones (fine dense grids) use the row-slot kernels.
ACCUMULATOR_MAX_BYTES = 64 << 20


#: Tables of fewer rows than this keep their row numbers and row slots in int32 (half the memory traffic of int64),
#: larger ones in int64 (``row_index_dtype``).
INT32_MAX_ROWS = 1 << 31


def row_index_dtype(n_rows: int) -> np.dtype:
    """The integer dtype of the (M,) row → slot map and of the row numbers of the sparse backward's scratch for a
    table of ``n_rows`` rows: int32 below ``INT32_MAX_ROWS`` (2^31) rows, else int64 (the kernels are compiled for
    each). Both kinds of value are below n_rows: a row number is, and a slot counts the distinct rows one work item
    touched (at most min(N·2^D, rows of its entry)); −1 marks a free slot."""
    return np.dtype(np.int32) if n_rows < INT32_MAX_ROWS else np.dtype(np.int64)


def row_slots(layout: TableLayout) -> np.ndarray:
    """The (M,) row → slot array (``row_index_dtype``; all −1 between uses) of the row-compaction kernels, created on
    first use."""
    ws = layout.workspace
    dtype = row_index_dtype(layout.total_rows)
    if ws.slots is None or ws.slots.shape[0] != layout.total_rows or ws.slots.dtype != dtype:
        ws.slots = np.full(layout.total_rows, -1, dtype=dtype)
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
    """(cap_off (P·E,), rows (C,) of ``row_index_dtype``, values (C,F)) scratch of the sparse table backward, kept
    in the workspace and reused while it is large enough; item i = p·E + e holds at most min(N·2^D_e, rows of part p
    of entry e) rows (blocks of 2^PART_LOG2 rows dealt round-robin to P parts). Never zeroed (kernels write on first
    touch), so a backward pays neither a large allocation nor its page faults."""
    blk = 1 << PART_LOG2
    part_rows = layout.rows if parts == 1 else -(-layout.rows // blk) // parts * blk + blk
    caps = np.minimum(n_points * (1 << layout.ndim), np.minimum(part_rows, layout.rows))
    caps = np.tile(caps, parts).astype(np.int64)
    cap_off = np.zeros_like(caps)
    cap_off[1:] = np.cumsum(caps)[:-1]
    need = int(caps.sum())
    index = row_index_dtype(layout.total_rows)
    out = layout.workspace.sparse_out
    if out is not None and (out[0].dtype != index or out[1].dtype != np.dtype(dtype)):
        out = None  # other dtypes: start again
    if out is None or out[0].shape[0] < need or out[1].shape[1] != n_feat:
        # grow to the largest capacity needed so far (capped by the table size)
        cap = max(need, out[0].shape[0] if out is not None else 0)
        out = (np.empty(cap, index), np.empty((cap, n_feat), dtype=dtype))
        layout.workspace.sparse_out = out
    return cap_off, out[0], out[1]


#: The nine layout arrays a kernel takes after its points and table (``_meta``, ``tri_meta``): a fixed-length tuple,
#: so that mypy can match ``kernel(xn, table, *_meta(layout), out)`` against the kernel's parameters.
_LayoutArrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                      np.ndarray]


def _meta(layout: TableLayout) -> _LayoutArrays:
    return (layout.ndim, layout.axes, layout.res, layout.scale, layout.offset, layout.stride, layout.hashed,
            layout.rows, layout.row_off)


def tri_meta(layout: TableLayout) -> _LayoutArrays:
    """The layout arrays the trilinear kernels take: (res, scale, offset, lo, hi, stride, hashed, rows, row_off)."""
    return (layout.res, layout.scale, layout.offset, layout.lo, layout.hi, layout.stride, layout.hashed,
            layout.rows, layout.row_off)


def _sparse_grad(layout: TableLayout, shape, dtype, nnz: int, fill) -> torch.Tensor:
    """Sparse COO (M,F) table gradient of nnz unique rows, written into (rows, vals) by ``fill(rows, vals)``.
    Both arrays come from the workspace's ``BufferPool``: a steady stream of backward passes reuses the same memory."""
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


def _drained_grad(layout: TableLayout, shape, dtype, acc: np.ndarray, mark_off: np.ndarray,
                  mark: np.ndarray) -> torch.Tensor:
    """The accumulator's marked rows as the sparse gradient (``_sparse_grad``): counted once, in parallel runs of the
    bitmap (``sparse_rows.marked_runs``), then drained run by run; acc and mark are left all zero."""
    runs, dst = sparse_rows.marked_runs(layout.rows, mark_off, mark)
    return _sparse_grad(layout, shape, dtype, int(dst[-1]),
                        lambda rows, vals: sparse_rows.drain_marked_rows(layout.row_off, mark_off, acc, mark, runs,
                                                                         dst, rows, vals))


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


def table_grad_numba(xn: np.ndarray, g: np.ndarray, layout: TableLayout, shape, dtype, sparse: bool,
                     skip_zero: bool = False) -> torch.Tensor:
    """∂L/∂T from the fused kernel: sparse COO with unique rows (``sparse``) or dense (M,F). ``skip_zero``
    (`TouchedRows.GRADIENT`): only the points whose output gradient is not all zero reach the kernels
    (`compact.nonzero_points`), so the others touch no row."""
    M, F = shape
    if skip_zero:
        xn, g = nonzero_points(xn, g)
    if not sparse:
        grad = torch.zeros(M, F, dtype=dtype)
        if layout.trilinear:
            trilinear.tri_backward_table_dense(xn, g, *tri_meta(layout), grad.numpy())
        else:
            generic.interp_backward_table_dense(xn, g, *_meta(layout), grad.numpy())
        return grad
    if layout.trilinear and M * F * g.itemsize <= ACCUMULATOR_MAX_BYTES:
        acc, mark_off, mark = _accumulator(layout, F, g.dtype)
        gT = _level_major(g, layout)  # (E,N,F): each level reads its gradient contiguously
        trilinear.tri_backward_table_acc(xn, gT, *tri_meta(layout), mark_off, acc, mark)
        return _drained_grad(layout, shape, g.dtype, acc, mark_off, mark)
    if layout.trilinear:
        parts = _row_parts(layout)
        cap_off, out_rows, out_vals = _sparse_out(layout, xn.shape[0], F, g.dtype, parts)
        counts = np.zeros(layout.n_entries * parts, np.int64)
        trilinear.tri_backward_table_sparse(xn, g, *tri_meta(layout), row_slots(layout), parts, PART_LOG2, cap_off,
                                            out_rows, out_vals, counts)
    else:
        cap_off, out_rows, out_vals = _sparse_out(layout, xn.shape[0], F, g.dtype)
        counts = np.zeros(layout.n_entries, np.int64)
        generic.interp_backward_table_sparse(xn, g, *_meta(layout), row_slots(layout), cap_off, out_rows, out_vals,
                                             counts)
    return _sparse_grad(layout, shape, g.dtype, int(counts.sum()),
                        lambda rows, vals: sparse_rows.compact_entries(cap_off, counts, out_rows, out_vals, rows, vals))


class _Scopes(threading.local):
    """Depths of the nested ``input_grad_only`` / ``second_order`` scopes of the current thread (the autograd engine
    runs a CPU backward pass on the thread that started it, so a scope around ``autograd.grad`` reaches it)."""

    input_grad_only = 0
    second_order = 0


_SCOPES = _Scopes()


@contextlib.contextmanager
def second_order():
    """Within this scope, fused lookups whose points need a gradient (grad mode on) are ``MultilinearJacFn``: they
    also output their input Jacobian, so that a ``create_graph`` input gradient taken from them (SDF normals) is
    differentiated again by the same fused node, in one table scatter. Lookups outside are unchanged."""
    _SCOPES.second_order += 1
    try:
        yield
    finally:
        _SCOPES.second_order -= 1


def second_order_active() -> bool:
    """True inside ``second_order()`` on this thread (a ``create_graph`` backward may follow)."""
    return _SCOPES.second_order > 0


def reference_grads(reference, inputs: tuple, needs: tuple, grads: tuple) -> tuple:
    """The backward of a fused once-differentiable Function inside a ``create_graph`` backward (grad mode on):
    the gradients of ``reference(*inputs)`` against the output gradients `grads`, differentiable, so that second
    derivatives (an eikonal loss on the normals) reach every input instead of being dropped. `inputs` are the
    Function's own inputs as saved (their graphs intact; non-tensors passed through), `needs` its
    ``ctx.needs_input_grad``; None where a gradient is not needed."""
    with torch.enable_grad():
        out = reference(*inputs)
    outs = out if isinstance(out, tuple) else (out,)
    wanted = [t for t, n in zip(inputs, needs) if n]
    got = iter(torch.autograd.grad(outs, wanted, grads, create_graph=True, allow_unused=True) if wanted else ())
    return tuple(next(got) if n else None for n in needs)


def fused_backward(reference):
    """Decorator for the backward of a fused Function: the decorated (numba, once differentiable) backward, or,
    inside a ``create_graph`` backward, `reference_grads` of `reference` on the Function's inputs. The forward saves
    its inputs as given after its own tensors: ``ctx.save_for_backward(*own, *inputs)``, ``ctx.n_own = len(own)``,
    and its non-tensor arguments (the last ones) as ``ctx.args``."""
    once = torch.autograd.function.once_differentiable

    def wrap(fn):
        fused = once(fn)

        def backward(ctx, *grads):
            if torch.is_grad_enabled():
                inputs = tuple(ctx.saved_tensors[ctx.n_own:]) + tuple(ctx.args)
                return reference_grads(reference, inputs, ctx.needs_input_grad, grads)
            return fused(ctx, *grads)

        backward.__doc__ = fn.__doc__
        return backward

    return wrap


def resolve_kernel(backend: str, fusable: bool, what: str, needs: str) -> str:
    """The backend a fused kernel's dispatcher runs ("numba" or "torch"): the reference wherever a second-order
    backward may follow (inside ``second_order()``: NeuS normals), else numba for "auto" where ``fusable``; an
    unknown name, or "numba" where it cannot run, errors naming ``what`` (e.g. "decoder kernel") and what it
    ``needs``."""
    if backend not in ("auto", "torch", "numba"):
        raise ValueError(f"unknown {what} {backend!r} (choices: auto, torch, numba)")
    if second_order_active():
        return "torch"
    if backend == "auto":
        return "numba" if fusable else "torch"
    if backend == "numba" and not fusable:
        raise ValueError(f"{what} 'numba' needs {needs}; use 'auto' or 'torch' otherwise")
    return backend


def cpu_floats(*tensors: torch.Tensor) -> bool:
    """Whether the fused numba kernels can take these tensors: all on the CPU, of one dtype, float32 or float64."""
    return (all(t.device.type == "cpu" for t in tensors) and len({t.dtype for t in tensors}) == 1
            and tensors[0].dtype in (torch.float32, torch.float64))


@contextlib.contextmanager
def input_grad_only():
    """Within this scope, backward passes of ``MultilinearFn`` return no table gradient: for
    ``torch.autograd.grad(out, points)`` (SDF normals), where the engine discards the table's gradient anyway, so
    that neither the fused table backward nor (``create_graph``) the reference's runs for nothing. Per thread."""
    _SCOPES.input_grad_only += 1
    try:
        yield
    finally:
        _SCOPES.input_grad_only -= 1


def _table_grad_coo(rows: np.ndarray, vals: np.ndarray, shape, sparse: bool) -> torch.Tensor:
    """(M,F) table gradient from per-corner rows (...,) int64 (−1: none) and values (..., F): an uncoalesced
    sparse COO tensor (``sparse``; the optimizer sums duplicate rows) or a dense one."""
    r = torch.from_numpy(rows.reshape(-1))
    v = torch.from_numpy(vals.reshape(-1, shape[1]))
    keep = r >= 0
    r, v = r[keep], v[keep]
    if sparse:
        return torch.sparse_coo_tensor(r[None], v, shape, check_invariants=False)
    return torch.zeros(shape, dtype=v.dtype).index_add_(0, r, v)


def _input_grad(xn: torch.Tensor, table: torch.Tensor, layout: TableLayout, jac: np.ndarray | None,
                g_np: np.ndarray) -> torch.Tensor:
    """gx[n,a] = Σ_{e,f} g[n,e,f] ∂out[n,e,f]/∂p̂_a, (N,3) in xn's dtype: the contraction with the Jacobian the
    trilinear forward kept (summed in float64 and written straight in xn's dtype, the same rounding as one cast of
    the float64 sum, without an (N,3) float64 array to zero and convert), else the generic kernel's float64 sum."""
    xn_np = xn.detach().contiguous().numpy()
    if jac is not None:
        gx = np.empty((xn.shape[0], 3), xn_np.dtype)
        trilinear.tri_backward_x_jac(jac, g_np, gx)
        return torch.from_numpy(gx)
    gx64 = np.zeros((xn.shape[0], 3), np.float64)
    generic.interp_backward_x(xn_np, table.detach().numpy(), g_np, *_meta(layout), gx64)
    return torch.from_numpy(gx64).to(xn.dtype)


class InputGradFn(torch.autograd.Function):
    """The input gradient of the lookup as a differentiable function: gx[n,a] = Σ_{e,f} g[n,e,f] ∂out[n,e,f]/∂p̂_a
    (g (N,E,F) the lookup's output gradient, xn (N,3), table (M,F) -> (N,3)), with a fused backward to g, xn and
    the table (``generic.interp_backward_x_backward``). This is what makes ``create_graph`` backward passes (NeuS
    normals) fused: the second derivatives of the interpolation are its cross terms, the table gradient is a
    scatter with derivative weights. Once differentiable (no third derivatives)."""

    @staticmethod
    def forward(ctx, g: torch.Tensor, xn: torch.Tensor, table: torch.Tensor, layout: TableLayout, jac, sparse: bool
                ) -> torch.Tensor:
        gx = _input_grad(xn, table, layout, jac, g.detach().contiguous().numpy())
        ctx.save_for_backward(g, xn, table)
        ctx.layout = layout
        ctx.sparse = sparse
        return gx

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, ggx: torch.Tensor):
        g, xn, table = ctx.saved_tensors
        layout = ctx.layout
        need_g, need_x, need_t = ctx.needs_input_grad[0], ctx.needs_input_grad[1], ctx.needs_input_grad[2]
        N, E, F = g.shape
        C = 1 << int(layout.ndim.max())
        tab = table.detach().numpy()
        grad_g = np.empty((N if need_g else 0, E, F), tab.dtype)
        gxx = np.zeros((N, 3), np.float64)
        out_rows = np.empty((N if need_t else 0, E, C), np.int64)
        out_vals = np.empty((N if need_t else 0, E, C, F), tab.dtype)
        generic.interp_backward_x_backward(xn.detach().contiguous().numpy(), tab, g.detach().contiguous().numpy(),
                                           ggx.detach().to(torch.float64).contiguous().numpy(), *_meta(layout),
                                           need_g, grad_g, gxx, out_rows, out_vals)
        gg = torch.from_numpy(grad_g) if need_g else None
        gx = torch.from_numpy(gxx).to(xn.dtype) if need_x else None
        gt = _table_grad_coo(out_rows, out_vals, tuple(table.shape), ctx.sparse) if need_t else None
        return gg, gx, gt, None, None, None


class MultilinearFn(torch.autograd.Function):
    """Fused lookup: forward (N,E,F); backward to xn (dense) and to the table (sparse rows or dense; none inside
    ``input_grad_only``).

    Double backward (``create_graph=True``, e.g. losses on SDF normals): the input gradient is ``InputGradFn``
    (fused, differentiable once more); the table gradient is recomputed through the reference, or skipped inside
    ``input_grad_only``.
    """

    @staticmethod
    def forward(ctx, xn: torch.Tensor, table: torch.Tensor, layout: TableLayout, sparse: bool,
                skip_zero: bool = False) -> torch.Tensor:
        tab = table.detach()
        xn_np = xn.detach().contiguous().numpy()
        ctx.jac = None
        if layout.trilinear:
            out = torch.empty(xn.shape[0], layout.n_entries, tab.shape[1], dtype=tab.dtype)
            # one lookup for both: keep ∂out/∂xn for the input backward (an empty array: no Jacobian)
            jac = np.empty((xn.shape[0] if ctx.needs_input_grad[0] else 0, layout.n_entries, tab.shape[1], 3),
                           dtype=xn_np.dtype)
            trilinear.tri_forward(xn_np, tab.numpy(), *tri_meta(layout), out.numpy(), jac)
            ctx.jac = jac if ctx.needs_input_grad[0] else None
        else:
            out = torch.zeros(xn.shape[0], layout.n_entries, tab.shape[1], dtype=tab.dtype)
            generic.interp_forward(xn_np, tab.numpy(), *_meta(layout), out.numpy())
        ctx.save_for_backward(xn, table)
        ctx.layout = layout
        ctx.sparse = sparse
        ctx.skip_zero = skip_zero
        return out

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        xn, table = ctx.saved_tensors
        layout = ctx.layout
        need_x, need_t = ctx.needs_input_grad[0], ctx.needs_input_grad[1] and not _SCOPES.input_grad_only
        if torch.is_grad_enabled():  # create_graph: a differentiable input gradient
            gx = InputGradFn.apply(g, xn, table, layout, ctx.jac, ctx.sparse) if need_x else None
            gt = None
            if need_t:  # a differentiable table gradient: through the reference
                out = interp_torch(xn.detach(), table, layout)
                (gt,) = torch.autograd.grad(out, table, g, create_graph=True)
            return gx, gt, None, None, None
        g_np = g.contiguous().numpy()
        xn_np = xn.detach().contiguous().numpy()
        gx = gt = None
        if need_x:  # (trilinear: the forward kept the Jacobian, as it knew the input gradient was needed)
            gx = _input_grad(xn, table, layout, ctx.jac, g_np)
        if need_t:
            gt = table_grad_numba(xn_np, g_np, layout, tuple(table.shape), table.dtype, ctx.sparse, ctx.skip_zero)
        return gx, gt, None, None, None


def _forward_with_jac(xn_np: np.ndarray, tab_np: np.ndarray, layout: TableLayout
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(out (N,E,F), jac (N,E,F,3), hess (N,E,F,3)) of the fused lookup in the table's dtype: jac = ∂out/∂p̂, hess
    the mixed second derivatives ∂²out/∂p̂_a∂p̂_b of the pairs (xy, xz, yz)."""
    N, E, F = xn_np.shape[0], layout.n_entries, tab_np.shape[1]
    if layout.trilinear:
        out = np.empty((N, E, F), tab_np.dtype)
        jac = np.empty((N, E, F, 3), tab_np.dtype)
        hess = np.empty((N, E, F, 3), tab_np.dtype)
        trilinear.tri_forward_jac_hess(xn_np, tab_np, *tri_meta(layout), out, jac, hess)
    else:
        out = np.zeros((N, E, F), tab_np.dtype)
        jac = np.zeros((N, E, F, 3), tab_np.dtype)
        hess = np.zeros((N, E, F, 3), tab_np.dtype)
        generic.interp_forward_jac(xn_np, tab_np, *_meta(layout), out, jac, hess)
    return out, jac, hess


def table_grad_jac_numba(xn: np.ndarray, g: np.ndarray, gj: np.ndarray, layout: TableLayout, shape, dtype,
                         sparse: bool) -> torch.Tensor:
    """∂L/∂T of ``MultilinearJacFn`` in one scatter: Σ w_c g + Σ_a ∂w_c/∂p̂_a gj_a (sparse unique rows or dense)."""
    if not sparse:
        grad = torch.zeros(shape, dtype=dtype)
        generic.interp_backward_table_jac_dense(xn, g, gj, *_meta(layout), grad.numpy())
        return grad
    M, F = shape
    if layout.trilinear and M * F * g.itemsize <= ACCUMULATOR_MAX_BYTES:
        acc, mark_off, mark = _accumulator(layout, F, g.dtype)
        trilinear.tri_backward_table_jac_acc(xn, _level_major(g, layout), gj, *tri_meta(layout), mark_off, acc, mark)
        return _drained_grad(layout, shape, g.dtype, acc, mark_off, mark)
    if layout.trilinear:
        parts = _row_parts(layout)
        cap_off, out_rows, out_vals = _sparse_out(layout, xn.shape[0], shape[1], g.dtype, parts)
        counts = np.zeros(layout.n_entries * parts, np.int64)
        trilinear.tri_backward_table_jac_sparse(xn, g, gj, *tri_meta(layout), row_slots(layout), parts, PART_LOG2,
                                                cap_off, out_rows, out_vals, counts)
    else:
        cap_off, out_rows, out_vals = _sparse_out(layout, xn.shape[0], shape[1], g.dtype)
        counts = np.zeros(layout.n_entries, np.int64)
        generic.interp_backward_table_jac_sparse(xn, g, gj, *_meta(layout), row_slots(layout), cap_off, out_rows,
                                                 out_vals, counts)
    return _sparse_grad(layout, shape, g.dtype, int(counts.sum()),
                        lambda rows, vals: sparse_rows.compact_entries(cap_off, counts, out_rows, out_vals, rows, vals))


class MultilinearJacFn(torch.autograd.Function):
    """Fused lookup with its input Jacobian as a second, differentiable output: (out (N,E,F), J (N,E,F,3)),
    J[n,e,f,a] = ∂out[n,e,f]/∂p̂_a. The ``create_graph`` input gradient is gx = Σ_{e,f} g J in torch, on the saved J,
    so its own backward comes back to this node as the gradient gj of J; the plain backward then takes both:

        ∂L/∂p̂_b = Σ_{e,f} g J_b + Σ_{e,f,a≠b} gj_a ∂²out/∂p̂_a∂p̂_b      (cross terms of the interpolation's Hessian,
                                                                       kept by the forward: no second table read)
        ∂L/∂T[r_c] = Σ w_c g + Σ_a ∂w_c/∂p̂_a gj_a                         (one scatter, unique rows)

    Same maths as differentiating the reference twice (tests/fields/test_kernels_second_order.py). Third
    derivatives are not provided (use the torch kernel)."""

    @staticmethod
    def forward(ctx, xn: torch.Tensor, table: torch.Tensor, layout: TableLayout, sparse: bool):
        xn_np = xn.detach().contiguous().numpy()
        out, jac, ctx.hess = _forward_with_jac(xn_np, table.detach().numpy(), layout)
        jac_t = torch.from_numpy(jac)
        ctx.save_for_backward(xn, table, jac_t)
        ctx.layout = layout
        ctx.sparse = sparse
        ctx.set_materialize_grads(False)
        return torch.from_numpy(out), jac_t

    @staticmethod
    def backward(ctx, g, gj):
        xn, table, jac = ctx.saved_tensors
        layout = ctx.layout
        need_x, need_t = ctx.needs_input_grad[0], ctx.needs_input_grad[1] and not _SCOPES.input_grad_only
        if torch.is_grad_enabled():  # create_graph: gx on the saved J, whose gradient comes back here as gj
            if gj is not None or g is None:
                raise NotImplementedError("third derivatives of the fused lookup are not provided; use "
                                          "field.kernel=torch")
            gx = (g.unsqueeze(-1) * jac).sum(dim=(1, 2)) if need_x else None
            gt = None
            if need_t:  # a differentiable table gradient: through the reference
                (gt,) = torch.autograd.grad(interp_torch(xn.detach(), table, layout), table, g, create_graph=True)
            return gx, gt, None, None
        if g is None and gj is None:
            return None, None, None, None
        xn_np = xn.detach().contiguous().numpy()
        N, E, F = jac.shape[:3]
        g_np = g.contiguous().numpy() if g is not None else np.zeros((N, E, F), jac.detach().numpy().dtype)
        gx = gt = None
        if need_x:
            gx64 = np.zeros((N, 3), np.float64)
            if g is not None:
                trilinear.tri_backward_x_jac(jac.detach().numpy(), g_np, gx64)
            if gj is not None:
                trilinear.hess_backward_x(ctx.hess, gj.contiguous().numpy(), gx64)
            gx = torch.from_numpy(gx64).to(xn.dtype)
        if need_t:
            if gj is None:
                gt = table_grad_numba(xn_np, g_np, layout, tuple(table.shape), table.dtype, ctx.sparse)
            else:
                gt = table_grad_jac_numba(xn_np, g_np, gj.contiguous().numpy(), layout, tuple(table.shape),
                                          table.dtype, ctx.sparse)
        return gx, gt, None, None


def multilinear(xn: torch.Tensor, table: torch.Tensor, layout: TableLayout, backend: str = "auto",
                sparse: bool | None = None, touched: str = "read") -> torch.Tensor:
    """Multilinear lookup of E entries: xn (N,3) in [0,1] (clamped; ±inf too), table (M,F) -> (N,E,F).

    A point with a NaN coordinate gets NaN features and no gradient (a loss over it turns NaN, which the SLAM loop
    treats as a failed step), on every backend.
    backend: "numba" (fused CPU kernel), "torch" (reference, any device) or "auto" (numba on CPU float32 / float64
        tables).
    sparse: table-gradient layout of the fused path; None = sparse iff M > DENSE_GRAD_MAX_ROWS.
    touched: rows of the fused path's table gradient (`TouchedRows`): "read" every row read with a non-zero weight
    (a zero-valued gradient row included), "gradient" only the rows some point with a non-zero output gradient
    reads (the torch path's dense gradient gives the optimiser that set: its non-zero rows); the second-order
    lookup inside ``second_order()`` keeps "read".
    """
    if touched not in ("read", "gradient"):
        raise ValueError(f"unknown touched rows {touched!r} (choices: read, gradient)")
    if backend == "auto":  # numba where it runs: CPU float32 / float64 tables (bfloat16 / half: the reference)
        fusable = table.device.type == "cpu" and table.dtype in (torch.float32, torch.float64)
        backend = "numba" if fusable else "torch"
    if backend not in ("torch", "numba"):
        raise ValueError(f"unknown kernel backend {backend!r} (choices: auto, torch, numba)")
    if xn.dim() != 2 or xn.shape[-1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {tuple(xn.shape)}")
    if xn.device.type == "cpu" and not _may_have_nan(xn):  # (on a GPU: no host sync to find out)
        return _lookup(xn, table, layout, backend, sparse, touched == "gradient")
    nan = torch.isnan(xn).any(dim=1)
    out = _lookup(torch.where(nan[:, None], torch.zeros_like(xn), xn), table, layout, backend, sparse,
                  touched == "gradient")
    return out.masked_fill(nan[:, None, None], float("nan"))


def _may_have_nan(x: torch.Tensor) -> bool:
    """False when no entry of x is NaN, found with one sum (NaN propagates through it; 10x faster than `isnan().any()`
    on a tracking batch). True also when x holds infinities that cancel or overflow to NaN in the sum: the caller's
    NaN-safe path then finds no NaN row and gives the same result."""
    return bool(torch.isnan(x.sum()))


def _lookup(xn: torch.Tensor, table: torch.Tensor, layout: TableLayout, backend: str, sparse: bool | None,
            skip_zero: bool = False) -> torch.Tensor:
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
    elif _SCOPES.second_order and xn.requires_grad:
        return MultilinearJacFn.apply(xn, table, layout, bool(sparse))[0]
    return MultilinearFn.apply(xn, table, layout, bool(sparse), skip_zero)
