"""Optimiser of a field: Adam for dense (decoder) parameters, lazy row-wise Adam for encoder tables.

Lazy Adam (``torch.optim.SparseAdam`` semantics with ``torch.optim.Adam``'s update formula): at step t of a table
only its touched rows r are updated,

    m_r ← β1 m_r + (1−β1) g_r,   v_r ← β2 v_r + (1−β2) g_r²,
    p_r ← p_r − lr/(1−β1^t) · m_r / (√v_r / √(1−β2^t) + ε),

rows not touched keep their parameters and moments; t counts the steps in which the table had a gradient.
Touched rows are the rows of a sparse gradient (fused kernels: rows read with a non-zero interpolation weight)
or the non-zero rows of a dense one (reference path; identical except for exactly cancelling gradients), so the
cost of a step scales with the rows touched, not with the table size (CPU: fused numba update).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from inrslam.fields.kernels import sparse_rows
from inrslam.fields.kernels.function import row_index_dtype, row_slots, unique_rows_of


def is_lazy(p: torch.Tensor) -> bool:
    """True for parameters tagged as row-sparse tables (``p._inr_lazy = True``)."""
    return bool(getattr(p, "_inr_lazy", False))


def _table_layouts(module: nn.Module) -> dict[int, object]:
    """id(table) -> TableLayout of every ``TableEncoder`` in ``module`` (found by structure, survives deepcopy)."""
    from inrslam.fields.encoders import TableEncoder  # encoders import kernels only; avoid a cycle at import

    return {id(m.table): m.layout for m in module.modules() if isinstance(m, TableEncoder)}


class LazyAdam(torch.optim.Optimizer):
    """Adam(β1, β2, ε); parameter groups with ``lazy=True`` get row-wise lazy updates (see module docstring)."""

    def __init__(self, params, lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 layouts: dict | None = None):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps, lazy=False))
        self._slots: dict[int, np.ndarray] = {}
        self._layouts = dict(layouts or {})  # id(table) -> TableLayout: share the kernels' (M,) scratch array

    def _slot(self, p: torch.Tensor) -> np.ndarray:
        layout = self._layouts.get(id(p))
        if layout is not None and layout.total_rows == p.shape[0]:
            return row_slots(layout)
        ws = self._slots.get(id(p))
        if ws is None or ws.shape[0] != p.shape[0]:
            ws = self._slots[id(p)] = np.full(p.shape[0], -1, dtype=row_index_dtype(p.shape[0]))
        return ws

    def _touched(self, p: torch.Tensor, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(rows (K,) int64 unique, summed gradients (K, ...)) of a table gradient."""
        if g.is_sparse:
            if g.is_coalesced() or g.device.type != "cpu":
                g = g.coalesce()
                return g.indices()[0], g.values()
            rows, vals = g._indices()[0].contiguous(), g._values().contiguous()
            layout = self._layouts.get(id(p))
            if layout is not None and unique_rows_of(layout, rows, vals):
                return rows, vals  # straight from one fused backward: rows already unique
            vals2 = vals.reshape(vals.shape[0], -1)
            out_rows = np.empty(rows.shape[0], np.int64)
            out_vals = np.zeros(vals2.shape, dtype=vals2.numpy().dtype)
            k = sparse_rows.unique_rows_sum(rows.numpy(), vals2.numpy(), self._slot(p), out_rows, out_vals)
            return torch.from_numpy(out_rows[:k]), torch.from_numpy(out_vals[:k]).reshape((k,) + vals.shape[1:])
        rows = torch.nonzero(g.reshape(g.shape[0], -1).ne(0).any(1))[:, 0]
        return rows, g[rows]

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            lr, (b1, b2), eps = group["lr"], group["betas"], group["eps"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["step"] += 1
                t = state["step"]
                step_size = lr / (1.0 - b1 ** t)
                bc2_sqrt = math.sqrt(1.0 - b2 ** t)
                m, v = state["exp_avg"], state["exp_avg_sq"]
                if not group["lazy"]:
                    g = p.grad.to_dense() if p.grad.is_sparse else p.grad
                    m.mul_(b1).add_(g, alpha=1.0 - b1)
                    v.mul_(b2).addcmul_(g, g, value=1.0 - b2)
                    p.addcdiv_(m, (v.sqrt() / bc2_sqrt).add_(eps), value=-step_size)
                    continue
                rows, vals = self._touched(p, p.grad)
                if rows.numel() == 0:
                    continue
                if p.device.type == "cpu" and p.is_contiguous() and m.is_contiguous() and v.is_contiguous():
                    M = p.shape[0]
                    sparse_rows.lazy_adam_rows(p.detach().reshape(M, -1).numpy(), m.reshape(M, -1).numpy(),
                                      v.reshape(M, -1).numpy(), rows.numpy(),
                                      vals.reshape(rows.shape[0], -1).contiguous().numpy(), step_size, b1, b2, eps,
                                      bc2_sqrt)
                    torch.autograd.graph.increment_version(p)
                else:
                    mr = m[rows].mul_(b1).add_(vals, alpha=1.0 - b1)
                    vr = v[rows].mul_(b2).addcmul_(vals, vals, value=1.0 - b2)
                    m[rows] = mr
                    v[rows] = vr
                    p[rows] = p[rows].addcdiv(mr, (vr.sqrt() / bc2_sqrt).add_(eps), value=-step_size)
        return loss


def make_optimizer(field: nn.Module, lr: float) -> LazyAdam:
    """Adam(0.9, 0.999, 1e-8) over all field parameters: group "decoder" (dense Adam) and group "tables"
    (lazy row-wise Adam); each group has 'lr' (the SLAM loop may set it to 0)."""
    layouts = _table_layouts(field)
    dense = [p for p in field.parameters() if p.requires_grad and not (is_lazy(p) or id(p) in layouts)]
    lazy = [p for p in field.parameters() if p.requires_grad and (is_lazy(p) or id(p) in layouts)]
    groups = []
    if dense:
        groups.append(dict(params=dense, name="decoder", lazy=False))
    if lazy:
        groups.append(dict(params=lazy, name="tables", lazy=True))
    return LazyAdam(groups, lr=lr, layouts=layouts)
