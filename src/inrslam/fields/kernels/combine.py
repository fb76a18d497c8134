"""Fused per-level combinations of plane and line features on CPU tensors (docs/speed.md).

A plane encoder's lookup gives, per point and level l, three plane features P_l,k (k = xy, xz, yz) and, for TensoRF,
three line features ℓ_l,k (z, y, x), F each. The encoders combine them per level:

    tri-plane:             f_l = Σ_k P_l,k                                        (`plane_sum`)
    TensoRF, true VM:      f_l = Σ_k P_l,k ⊙ ℓ_l,k                                (`vm_product`)
    TensoRF, faithful:     f_l = (Σ_k P_l,k) ⊙ (Σ_k ℓ_l,k)

In autograd these are products and reductions over a size-3 axis of (strided) views, forward and backward: on a
mapping batch of 122,880 samples 6-13 ms for TensoRF's and 5 ms for tri-plane's, against about 2 and 1 ms for the
kernels (benchmarks/bench_fields.py). One numba pass each way
does the same floating-point operations in the same order as the references (`plane_sum_torch`, `vm_product_torch`:
products rounded, then (a0 + a1) + a2; fastmath off, so no fused multiply-add), so outputs and gradients are
bit-identical to them and a run does not change when the kernels are used. Points are independent: results never
depend on the thread count.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from inrslam.fields.kernels.function import cpu_floats, fused_backward, resolve_kernel


def plane_sum_torch(f: torch.Tensor, levels: int) -> torch.Tensor:
    """The reference: plane features f (N, 3L, F) (level-major) -> (N, L·F), the sum of each level's three."""
    n = f.shape[0]
    return f.reshape(n, levels, 3, f.shape[2]).sum(2).reshape(n, levels * f.shape[2])


def vm_product_torch(f: torch.Tensor, levels: int, faithful: bool) -> torch.Tensor:
    """The reference: lookup features f (N, 6L, F) (3L planes, then 3L lines, level-major) -> (N, L·F)."""
    n, F = f.shape[0], f.shape[2]
    planes = f[:, : 3 * levels].reshape(n, levels, 3, F)
    lines = f[:, 3 * levels :].reshape(n, levels, 3, F)
    out = planes.sum(2) * lines.sum(2) if faithful else (planes * lines).sum(2)
    return out.reshape(n, levels * F)


@njit(parallel=True, cache=True, fastmath=False)
def _sum_forward(f, levels, out):  # pragma: no cover - numba
    """out (N, L, F) from f (N, 3L, F) as `plane_sum_torch`."""
    n_pts, n_feat = f.shape[0], f.shape[2]
    for n in prange(n_pts):
        for lv in range(levels):
            p = 3 * lv
            for c in range(n_feat):
                out[n, lv, c] = (f[n, p, c] + f[n, p + 1, c]) + f[n, p + 2, c]


@njit(parallel=True, cache=True, fastmath=False)
def _sum_backward(g, levels, gf):  # pragma: no cover - numba
    """gf (N, 3L, F): each plane's gradient is its level's output gradient g (N, L, F) (autograd's expand)."""
    n_pts, n_feat = g.shape[0], g.shape[2]
    for n in prange(n_pts):
        for lv in range(levels):
            for k in range(3):
                for c in range(n_feat):
                    gf[n, 3 * lv + k, c] = g[n, lv, c]


@njit(parallel=True, cache=True, fastmath=False)
def _vm_forward(f, levels, faithful, out):  # pragma: no cover - numba
    """out (N, L, F) from f (N, 6L, F) as `vm_product_torch`."""
    n_pts, n_feat = f.shape[0], f.shape[2]
    for n in prange(n_pts):
        for lv in range(levels):
            p = 3 * lv
            q = 3 * levels + 3 * lv
            for c in range(n_feat):
                if faithful:
                    out[n, lv, c] = (((f[n, p, c] + f[n, p + 1, c]) + f[n, p + 2, c])
                                     * ((f[n, q, c] + f[n, q + 1, c]) + f[n, q + 2, c]))
                else:
                    out[n, lv, c] = ((f[n, p, c] * f[n, q, c] + f[n, p + 1, c] * f[n, q + 1, c])
                                     + f[n, p + 2, c] * f[n, q + 2, c])


@njit(parallel=True, cache=True, fastmath=False)
def _vm_backward(f, g, levels, faithful, gf):  # pragma: no cover - numba
    """gf (N, 6L, F) = ∂⟨g, out⟩/∂f for the output gradient g (N, L, F): a plane's gradient is g times its line
    (faithful: times the sum of the level's lines), and the other way round. Autograd adds the planes' and the
    lines' gradients of f (each zero in the other's half), so a -0 product becomes +0 there: + 0.0 does the same."""
    n_pts, n_feat = f.shape[0], f.shape[2]
    for n in prange(n_pts):
        for lv in range(levels):
            p = 3 * lv
            q = 3 * levels + 3 * lv
            for c in range(n_feat):
                gv = g[n, lv, c]
                if faithful:
                    sp = (f[n, p, c] + f[n, p + 1, c]) + f[n, p + 2, c]
                    sl = (f[n, q, c] + f[n, q + 1, c]) + f[n, q + 2, c]
                    gp = gv * sl + 0.0  # + 0.0 as the reference's sum of the two slices' gradients: -0 -> +0
                    gl = gv * sp + 0.0
                    for k in range(3):
                        gf[n, p + k, c] = gp
                        gf[n, q + k, c] = gl
                else:
                    for k in range(3):
                        gf[n, p + k, c] = gv * f[n, q + k, c] + 0.0
                        gf[n, q + k, c] = gv * f[n, p + k, c] + 0.0


class PlaneSumFn(torch.autograd.Function):
    """`plane_sum_torch` in one numba pass each way (once differentiable; a ``create_graph`` backward
    differentiates the reference, `function.fused_backward`)."""

    @staticmethod
    def forward(ctx, f, levels):
        fc = f.detach().contiguous()
        out = np.empty((fc.shape[0], levels, fc.shape[2]), dtype=fc.numpy().dtype)
        _sum_forward(fc.numpy(), levels, out)
        ctx.levels, ctx.shape = levels, fc.shape
        ctx.save_for_backward(f)
        ctx.n_own, ctx.args = 0, (levels,)
        return torch.from_numpy(out).reshape(fc.shape[0], levels * fc.shape[2])

    @staticmethod
    @fused_backward(plane_sum_torch)
    def backward(ctx, g):
        n, _, n_feat = ctx.shape
        gc = g.detach().reshape(n, ctx.levels, n_feat).contiguous()
        gf = np.empty(ctx.shape, dtype=gc.numpy().dtype)
        _sum_backward(gc.numpy(), ctx.levels, gf)
        return torch.from_numpy(gf), None


class VmProductFn(torch.autograd.Function):
    """`vm_product_torch` in one numba pass each way (once differentiable; a ``create_graph`` backward
    differentiates the reference)."""

    @staticmethod
    def forward(ctx, f, levels, faithful):
        fc = f.detach().contiguous()
        out = np.empty((fc.shape[0], levels, fc.shape[2]), dtype=fc.numpy().dtype)
        _vm_forward(fc.numpy(), levels, faithful, out)
        ctx.save_for_backward(fc, f)
        ctx.levels, ctx.faithful = levels, faithful
        ctx.n_own, ctx.args = 1, (levels, faithful)
        return torch.from_numpy(out).reshape(fc.shape[0], levels * fc.shape[2])

    @staticmethod
    @fused_backward(vm_product_torch)
    def backward(ctx, g):
        fc = ctx.saved_tensors[0]
        gc = g.detach().to(fc.dtype).reshape(fc.shape[0], ctx.levels, fc.shape[2]).contiguous()
        gf = np.empty(fc.shape, dtype=fc.numpy().dtype)
        _vm_backward(fc.numpy(), gc.numpy(), ctx.levels, ctx.faithful, gf)
        return torch.from_numpy(gf), None, None


def _fused(f: torch.Tensor, backend: str) -> bool:
    """Whether the numba kernel runs for `backend` (`function.resolve_kernel`: auto on CPU float32/float64, never
    inside `kernels.second_order()`)."""
    return resolve_kernel(backend, cpu_floats(f), "kernel backend", "CPU float32/float64 tensors") == "numba"


def plane_sum(f: torch.Tensor, levels: int, backend: str = "auto") -> torch.Tensor:
    """Tri-plane's per-level sum of plane features f (N, 3L, F) -> (N, L·F) (module docstring); backend as
    `vm_product`."""
    if f.dim() != 3 or f.shape[1] != 3 * levels:
        raise ValueError(f"plane_sum: expected plane features (N, {3 * levels}, F) for {levels} level(s), "
                         f"got {tuple(f.shape)}")
    return PlaneSumFn.apply(f, levels) if _fused(f, backend) else plane_sum_torch(f, levels)


def vm_product(f: torch.Tensor, levels: int, faithful: bool, backend: str = "auto") -> torch.Tensor:
    """TensoRF's per-level combination of lookup features f (N, 6L, F) -> (N, L·F) (module docstring).

    backend: "numba" (fused; CPU float32/float64), "torch" (the reference) or "auto" (numba where it can run).
    Inside ``kernels.second_order()`` (a ``create_graph`` backward may follow) the reference runs."""
    if f.dim() != 3 or f.shape[1] != 6 * levels:
        raise ValueError(f"vm_product: expected lookup features (N, {6 * levels}, F) for {levels} level(s), "
                         f"got {tuple(f.shape)}")
    return VmProductFn.apply(f, levels, faithful) if _fused(f, backend) else vm_product_torch(f, levels, faithful)
