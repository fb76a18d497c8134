"""Fused TensoRF vector-matrix product on CPU tensors (`TensoRFEncoder`, docs/speed.md).

The lookup gives, per point and level l, three plane features P_l,k and three line features ℓ_l,k (k = xy·z, xz·y,
yz·x), F each. TensoRF combines them per level:

    true VM:   f_l = Σ_k P_l,k ⊙ ℓ_l,k                      faithful: f_l = (Σ_k P_l,k) ⊙ (Σ_k ℓ_l,k)

In autograd that is a product and a reduction over a size-3 axis of strided views, forward and backward: about
12 ms per mapping batch of 122,880 samples, a fifth of the encoder. One numba pass each way does it in the same
floating-point operations in the same order as the reference (`vm_product_torch`: products rounded, then
(a0 + a1) + a2; fastmath off, so no fused multiply-add), so outputs and gradients are bit-identical to it and a run
does not change when the kernel is used. Points are independent: results never depend on the thread count.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from inrslam.fields.kernels.function import cpu_floats, second_order_active

#: Points per block of the parallel loops.
BLOCK = 2048


def vm_product_torch(f: torch.Tensor, levels: int, faithful: bool) -> torch.Tensor:
    """The reference: lookup features f (N, 6L, F) (3L planes, then 3L lines, level-major) -> (N, L·F)."""
    n, F = f.shape[0], f.shape[2]
    planes = f[:, : 3 * levels].reshape(n, levels, 3, F)
    lines = f[:, 3 * levels :].reshape(n, levels, 3, F)
    out = planes.sum(2) * lines.sum(2) if faithful else (planes * lines).sum(2)
    return out.reshape(n, -1)


@njit(parallel=True, cache=True, fastmath=False)
def _forward(f, levels, faithful, out):  # pragma: no cover - numba
    """out (N, L, F) from f (N, 6L, F) as `vm_product_torch`."""
    n_pts, n_feat = f.shape[0], f.shape[2]
    for b in prange((n_pts + BLOCK - 1) // BLOCK):
        for n in range(b * BLOCK, min(n_pts, (b + 1) * BLOCK)):
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
def _backward(f, g, levels, faithful, gf):  # pragma: no cover - numba
    """gf (N, 6L, F) = ∂⟨g, out⟩/∂f for the output gradient g (N, L, F): a plane's gradient is g times its line
    (faithful: times the sum of the level's lines), and the other way round. Autograd adds the planes' and the
    lines' gradients of f (each zero in the other's half), so a -0 product becomes +0 there: + 0.0 does the same."""
    n_pts, n_feat = f.shape[0], f.shape[2]
    for b in prange((n_pts + BLOCK - 1) // BLOCK):
        for n in range(b * BLOCK, min(n_pts, (b + 1) * BLOCK)):
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


class VmProductFn(torch.autograd.Function):
    """`vm_product_torch` in one numba pass each way (once differentiable)."""

    @staticmethod
    def forward(ctx, f, levels, faithful):
        fc = f.detach().contiguous()
        out = np.empty((fc.shape[0], levels, fc.shape[2]), dtype=fc.numpy().dtype)
        _forward(fc.numpy(), levels, faithful, out)
        ctx.save_for_backward(fc)
        ctx.levels, ctx.faithful = levels, faithful
        return torch.from_numpy(out).reshape(fc.shape[0], -1)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        (fc,) = ctx.saved_tensors
        gc = g.detach().to(fc.dtype).reshape(fc.shape[0], ctx.levels, fc.shape[2]).contiguous()
        gf = np.empty(fc.shape, dtype=fc.numpy().dtype)
        _backward(fc.numpy(), gc.numpy(), ctx.levels, ctx.faithful, gf)
        return torch.from_numpy(gf), None, None


def vm_product(f: torch.Tensor, levels: int, faithful: bool, backend: str = "auto") -> torch.Tensor:
    """TensoRF's per-level combination of lookup features f (N, 6L, F) -> (N, L·F) (module docstring).

    backend: "numba" (fused; CPU float32/float64), "torch" (the reference) or "auto" (numba where it can run).
    Inside ``kernels.second_order()`` (a ``create_graph`` backward may follow) the reference runs."""
    if f.dim() != 3 or f.shape[1] != 6 * levels:
        raise ValueError(f"vm_product: expected lookup features (N, {6 * levels}, F) for {levels} level(s), "
                         f"got {tuple(f.shape)}")
    if backend not in ("auto", "torch", "numba"):
        raise ValueError(f"unknown kernel backend {backend!r} (choices: auto, torch, numba)")
    if backend == "torch" or second_order_active() or (backend == "auto" and not cpu_floats(f)):
        return vm_product_torch(f, levels, faithful)
    if not cpu_floats(f):
        raise ValueError("kernel 'numba' needs CPU float32/float64 tensors; use 'auto' or 'torch' otherwise")
    return VmProductFn.apply(f, levels, faithful)
