"""Fused plane decoder ``relu(relu(x W1^T + b1) W2^T + b2) W3^T + b3`` (three layers with biases) for CPU tensors.

The tri-plane and TensoRF fields decode with this MLP (7 -> 32 -> 32 -> 1..3 at `paper` settings). As the grid
decoder's kernel (``fields.kernels.mlp``) does, the numba kernels cut the samples into blocks (``mlp.block_rows``:
256 samples for the 32 x 32 middle layer), run each block's matrix products through BLAS (``np.dot``) and the biases,
ReLUs and ReLU masks in place on the block, so a block's two (block, 32) hidden arrays stay in cache; the backward
recomputes them instead of storing them, except where only the input needs a gradient (tracking: the map is frozen),
whose forward keeps both ReLU masks, one byte per unit and sample, for the backward to read (``mlp.KEEP_MASK``
switches both decoders' masks; the same values either way). The reference is ``mlp3_torch``; ``mlp3`` dispatches.
Results do not depend on the thread count: every block is one set of BLAS calls no larger than OpenBLAS's
single-thread size (a larger product inside the parallel loop would start OpenBLAS's own threads) and the weight and
bias gradients' per-block partial sums are added in block order.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from inrslam.fields.kernels.function import cpu_floats, fused_backward
from inrslam.fields.kernels.mlp import (
    FASTMATH,
    blas_fits,
    block_rows,
    keeps_mask,
    relu_inplace,
    relu_keep_mask,
    relu_mask_inplace,
    resolve_backend,
    zero_where_masked,
)
from inrslam.fields.kernels.subnormal import flush_inplace, tiny_of


@njit(inline="always", cache=True, fastmath=FASTMATH)
def _add_bias(h, b):  # pragma: no cover - numba
    """h (m, H) += b (H,) on every row."""
    for k in range(h.shape[0]):
        for j in range(h.shape[1]):
            h[k, j] += b[j]


@njit(inline="always", cache=True, fastmath=FASTMATH)
def _col_sum(g, out):  # pragma: no cover - numba
    """out (H,) = Σ_k g[k, :] (rows in order)."""
    for j in range(g.shape[1]):
        out[j] = 0.0
    for k in range(g.shape[0]):
        for j in range(g.shape[1]):
            out[j] += g[k, j]


@njit(inline="always", cache=True, fastmath=FASTMATH)
def _hidden(xb, w1t, b1, w2t, b2):  # pragma: no cover - numba
    """The block's two hidden activations a1 = relu(xb w1t + b1) (m, H1), a2 = relu(a1 w2t + b2) (m, H2)."""
    a1 = np.dot(xb, w1t)
    _add_bias(a1, b1)
    relu_inplace(a1)
    a2 = np.dot(a1, w2t)
    _add_bias(a2, b2)
    relu_inplace(a2)
    return a1, a2


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _forward(x, w1t, b1, w2t, b2, w3t, b3, block, out):  # pragma: no cover - numba
    """x (N, I), w1t (I, H1), w2t (H1, H2), w3t (H2, O), biases (H1,), (H2,), (O,) -> out (N, O), `block` samples at
    a time."""
    n_pts = x.shape[0]
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        _a1, a2 = _hidden(x[n0:n1], w1t, b1, w2t, b2)
        y = np.dot(a2, w3t)
        _add_bias(y, b3)
        out[n0:n1] = y


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _forward_mask(x, w1t, b1, w2t, b2, w3t, b3, block, out, m1, m2):  # pragma: no cover - numba
    """`_forward`, also writing the two ReLU masks m1 (N, H1), m2 (N, H2) (`mlp.relu_keep_mask`)."""
    n_pts = x.shape[0]
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        a1 = np.dot(x[n0:n1], w1t)
        _add_bias(a1, b1)
        relu_keep_mask(a1, m1[n0:n1])
        a2 = np.dot(a1, w2t)
        _add_bias(a2, b2)
        relu_keep_mask(a2, m2[n0:n1])
        y = np.dot(a2, w3t)
        _add_bias(y, b3)
        out[n0:n1] = y


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _backward_mask(m1, m2, w1t, w2t, w3t, gy, block, tiny, gx):  # pragma: no cover - numba
    """The input gradient gx (N, I) of `_backward` from the forward's ReLU masks instead of recomputed hidden
    layers: the same products on the same blocks, so the same values."""
    n_pts = gy.shape[0]
    w3 = np.ascontiguousarray(w3t.T)
    w2 = np.ascontiguousarray(w2t.T)
    w1 = np.ascontiguousarray(w1t.T)
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        gyb = gy[n0:n1].copy()
        flush_inplace(gyb, tiny)
        g2 = np.dot(gyb, w3)
        zero_where_masked(g2, m2[n0:n1])
        g1 = np.dot(g2, w2)
        zero_where_masked(g1, m1[n0:n1])
        gxb = np.dot(g1, w1)
        flush_inplace(gxb, tiny)
        gx[n0:n1] = gxb


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _backward(x, w1t, b1, w2t, b2, w3t, gy, block, need_x, need_w, tiny, gx, gw1t_p, gb1_p, gw2t_p, gb2_p, gw3t_p,
              gb3_p):  # pragma: no cover - numba
    """Gradients for the output gradient gy (N, O): gx (N, I) when need_x, and per-block partial weight and bias
    gradients (gw1t_p (B, I, H1), gb1_p (B, H1), ... gb3_p (B, O)) when need_w (summed over blocks by the caller).
    A ReLU passes its gradient where its pre-activation is > 0, or NaN (as torch's). Subnormal values of gy
    (|v| < tiny) count as zero, and those of gx are set to zero (``subnormal``)."""
    n_pts = x.shape[0]
    w3 = np.ascontiguousarray(w3t.T)  # (O, H2)
    w2 = np.ascontiguousarray(w2t.T)  # (H2, H1)
    w1 = np.ascontiguousarray(w1t.T)  # (H1, I)
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        xb = x[n0:n1]
        gyb = gy[n0:n1].copy()
        flush_inplace(gyb, tiny)
        a1, a2 = _hidden(xb, w1t, b1, w2t, b2)
        g2 = np.dot(gyb, w3)  # (m, H2): gradient of a2
        relu_mask_inplace(a2, g2)  # -> the pre-activation's gradient (a2 is already 0 there)
        g1 = np.dot(g2, w2)  # (m, H1): gradient of a1
        relu_mask_inplace(a1, g1)
        if need_x:
            gxb = np.dot(g1, w1)
            flush_inplace(gxb, tiny)
            gx[n0:n1] = gxb
        if need_w:
            gw3t_p[b] = np.dot(a2.T, gyb)
            _col_sum(gyb, gb3_p[b])
            gw2t_p[b] = np.dot(a1.T, g2)
            _col_sum(g2, gb2_p[b])
            gw1t_p[b] = np.dot(xb.T, g1)
            _col_sum(g1, gb1_p[b])


def mlp3_torch(x: torch.Tensor, w1: torch.Tensor, b1: torch.Tensor, w2: torch.Tensor, b2: torch.Tensor,
               w3: torch.Tensor, b3: torch.Tensor) -> torch.Tensor:
    """Reference: x (N, I), w1 (H1, I), w2 (H2, H1), w3 (O, H2), biases (H1,), (H2,), (O,) -> (N, O) (any device,
    fully differentiable; the same operations as `nn.Sequential(Linear, ReLU, Linear, ReLU, Linear)`)."""
    h = torch.relu(torch.nn.functional.linear(x, w1, b1))
    h = torch.relu(torch.nn.functional.linear(h, w2, b2))
    return torch.nn.functional.linear(h, w3, b3)


class Mlp3Fn(torch.autograd.Function):
    """Fused three-layer MLP with biases on CPU tensors: forward and one backward (to x and to the weights and
    biases, each only when needed; subnormal output and input gradients count as zero). Once differentiable: a
    second-order backward differentiates ``mlp3_torch`` instead (`function.fused_backward`)."""

    @staticmethod
    def forward(ctx, x, w1, b1, w2, b2, w3, b3):
        xc = x.detach().contiguous()
        wt = [w.detach().t().contiguous() for w in (w1, w2, w3)]
        bs = [b.detach().contiguous() for b in (b1, b2, b3)]
        out = np.empty((xc.shape[0], w3.shape[0]), dtype=wt[0].numpy().dtype)
        x_, (w1t, w2t, w3t), (b1_, b2_, b3_) = xc.numpy(), [w.numpy() for w in wt], [b.numpy() for b in bs]
        ctx.masks = None
        if keeps_mask(ctx.needs_input_grad[:1], ctx.needs_input_grad[1:]):
            m1, m2 = (np.empty((xc.shape[0], w.shape[0]), dtype=np.uint8) for w in (w1, w2))
            _forward_mask(x_, w1t, b1_, w2t, b2_, w3t, b3_, block_rows(*wt), out, m1, m2)
            ctx.masks = (m1, m2)
        else:
            _forward(x_, w1t, b1_, w2t, b2_, w3t, b3_, block_rows(*wt), out)
        ctx.save_for_backward(xc, *wt, *bs, x, w1, b1, w2, b2, w3, b3)
        ctx.n_own, ctx.args = 7, ()
        return torch.from_numpy(out)

    @staticmethod
    @fused_backward(mlp3_torch)
    def backward(ctx, gy: torch.Tensor):
        xc, w1t, w2t, w3t, b1, b2, _b3 = ctx.saved_tensors[:7]
        need = ctx.needs_input_grad
        need_x, need_w = need[0], any(need[1:])
        dtype = w1t.numpy().dtype
        n, n_in = xc.shape
        h1, h2, n_out = w1t.shape[1], w2t.shape[1], w3t.shape[1]
        block = block_rows(w1t, w2t, w3t)
        if ctx.masks is not None:  # only the input gradient, from the forward's ReLU masks
            gx = np.empty((n, n_in), dtype=dtype)
            m1, m2 = ctx.masks
            gy_np = gy.detach().to(w1t.dtype).contiguous().numpy()
            _backward_mask(m1, m2, w1t.numpy(), w2t.numpy(), w3t.numpy(), gy_np, block, tiny_of(dtype), gx)
            return (torch.from_numpy(gx),) + (None,) * 6
        nb = (n + block - 1) // block if need_w else 0
        gx = np.empty((n if need_x else 0, n_in), dtype=dtype)
        parts = [np.zeros(s, dtype=dtype) for s in ((nb, n_in, h1), (nb, h1), (nb, h1, h2), (nb, h2), (nb, h2, n_out),
                                                       (nb, n_out))]
        _backward(xc.numpy(), w1t.numpy(), b1.numpy(), w2t.numpy(), b2.numpy(), w3t.numpy(),
                  gy.detach().to(w1t.dtype).contiguous().numpy(), block, need_x, need_w, tiny_of(dtype), gx, *parts)
        # blocks summed in a fixed order (any thread count); transposed weights back to (out, in)
        sums = [torch.from_numpy(p.sum(axis=0)) for p in parts] if need_w else [None] * 6
        grads = [torch.from_numpy(gx) if need_x else None]
        for k, s in enumerate(sums):
            want = need[1 + k]
            grads.append((s.t().contiguous() if k % 2 == 0 else s) if want and s is not None else None)
        return tuple(grads)


def mlp3(x: torch.Tensor, w1: torch.Tensor, b1: torch.Tensor, w2: torch.Tensor, b2: torch.Tensor, w3: torch.Tensor,
         b3: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """relu(relu(x W1^T + b1) W2^T + b2) W3^T + b3: x (N, I), w1 (H1, I), w2 (H2, H1), w3 (O, H2) -> (N, O).

    backend: "numba" (fused, CPU float32/float64 tensors of one dtype, once differentiable), "torch" (reference)
    or "auto" (numba where it can run). Inside ``kernels.second_order()`` both run the reference."""
    ws, bs = (w1, w2, w3), (b1, b2, b3)
    if (x.dim() != 2 or any(w.dim() != 2 for w in ws) or any(b.dim() != 1 for b in bs)
            or x.shape[1] != w1.shape[1] or w2.shape[1] != w1.shape[0] or w3.shape[1] != w2.shape[0]
            or any(b.shape[0] != w.shape[0] for w, b in zip(ws, bs))):
        raise ValueError(f"mlp3: shapes x {tuple(x.shape)}, weights {[tuple(w.shape) for w in ws]}, biases "
                         f"{[tuple(b.shape) for b in bs]} do not chain (expected (N, I), (H1, I), (H2, H1), (O, H2) "
                         "and (H1,), (H2,), (O,))")
    if resolve_backend(backend, cpu_floats(x, *ws, *bs) and blas_fits(*ws)) == "torch":
        return mlp3_torch(x, w1, b1, w2, b2, w3, b3)
    return Mlp3Fn.apply(x, w1, b1, w2, b2, w3, b3)
