"""Blocked MLP of the MLP representation for CPU tensors: sin(x B) (optional), then Linear-ReLU layers, then a Linear.

autograd runs each operation of the MLP representation over all N samples at once. At a tracking batch (61,440
samples, trunk width 256) every hidden activation is a 63 MB tensor, twice the last-level cache; each layer writes
and re-reads it several times (product, bias, ReLU; ReLU gradient, product) on memory freshly mapped from the OS at
each call (glibc maps blocks this large directly, so every call pays their page faults), and the heads' products
with a 32-wide side run at half BLAS speed on such tall arrays. `BlockedMlpFn` runs the whole network on one block of
`block_rows` samples (about 4 MB of activation per layer) before the next, so a block's activations stay in cache
from layer to layer. The products run in torch's BLAS, the weights transposed once per call into contiguous arrays
(MKL's fastest layout for these shapes); the activations kept for the backward (as autograd keeps them) and the
outputs live in buffers reused from call to call (`MlpScratch`). The backward walks the blocks the same way: ReLU
gradient (torch's ``threshold_backward``: a NaN passes its gradient, as in autograd), input-side product and, for
each weight and bias that needs one, its gradient summed block by block in block order (the same sums on any
thread count, rounded differently from autograd's single product over all samples).

The network: ``h_0 = sin(x B)`` with a fixed (3, F) matrix B (the Gaussian Fourier features, given as ``freq``) or
``h_0 = x``; ``h_i = relu(h_{i-1} W_i^T + b_i)`` for i < L; output ``h_{L-1} W_L^T + b_L`` (no ReLU). The MLP
representation's trunk and heads are one such network (`fields.models.MLPField`: the two heads side by side, their
first layers stacked and second layers block-diagonal). The reference is ``blocked_mlp_torch`` (plain autograd);
``blocked_mlp`` dispatches. Once differentiable: a second-order backward (``create_graph``, NeuS normals)
differentiates the reference.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch

from inrslam.fields.kernels.function import cpu_floats, fused_backward
from inrslam.fields.kernels.mlp import resolve_backend
from inrslam.fields.kernels.pool import BufferPool

#: Bytes of one block's activation per layer (`block_rows`): small enough for a block's activations to stay in the
#: last-level cache from layer to layer, large enough for the products to run at BLAS speed (measured on the trunk,
#: width 256: 1024 to 4096 rows even, 512 and 8192 slower).
BLOCK_BYTES = 4 << 20


def block_rows(width: int, dtype: torch.dtype) -> int:
    """Samples per block for activations `width` wide in `dtype`: BLOCK_BYTES of activation (4096 rows of 256
    float32), at least 64."""
    return max(64, BLOCK_BYTES // (max(1, width) * torch.empty(0, dtype=dtype).element_size()))


class MlpScratch:
    """Buffers one network reuses from call to call (activations, outputs, input gradients). A buffer is reused
    only once every tensor sharing its memory has been freed (`pool.BufferPool`), so two graphs alive at once never
    share one. Copies and pickles start empty. Not thread-safe: one network serves one thread at a time."""

    def __init__(self, max_buffers: int = 16):
        self.pool = BufferPool(max_buffers)

    def take(self, rows: int, cols: int, dtype: torch.dtype) -> torch.Tensor:
        """An uninitialised (rows, cols) CPU tensor that nothing else uses."""
        return torch.from_numpy(self.pool.take((rows, cols), torch.empty(0, dtype=dtype).numpy().dtype))

    def __getstate__(self) -> dict:
        return {"max_buffers": self.pool.max_buffers}

    def __setstate__(self, state: dict) -> None:
        self.pool = BufferPool(state["max_buffers"])

    def __deepcopy__(self, memo: dict) -> "MlpScratch":
        return MlpScratch(self.pool.max_buffers)


def blocked_mlp_torch(x: torch.Tensor, params: Sequence[torch.Tensor],
                      freq: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Reference, in autograd: x (N, I) -> (N, O); params = (W1, b1, ..., W_L, b_L), W_i (out, in); `freq` (3, F)
    makes the input sin(x freq) (x then (N, 3))."""
    h = x if freq is None else torch.sin(x @ freq)
    weights, biases = params[0::2], params[1::2]
    for i, (w, b) in enumerate(zip(weights, biases)):
        h = torch.nn.functional.linear(h, w, b)
        if i < len(weights) - 1:
            h = torch.relu(h)
    return h


class BlockedMlpFn(torch.autograd.Function):
    """The blocked network: forward and one backward (to x and each parameter, each only when needed). Arguments:
    x, W1, b1, ..., W_L, b_L, then the non-tensors freq (or None) and the network's `MlpScratch`."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, *args) -> torch.Tensor:
        params, freq, scratch = args[:-2], args[-2], args[-1]
        weights = [w.detach() for w in params[0::2]]
        biases = [b.detach() for b in params[1::2]]
        wts = [w.t().contiguous() for w in weights]  # (in, out): the products' fastest layout
        xc = x.detach().contiguous()
        n, dtype, depth = xc.shape[0], xc.dtype, len(weights)
        rows = block_rows(max(w.shape[0] for w in weights[:-1]) if depth > 1 else weights[0].shape[0], dtype)
        need = ctx.needs_input_grad
        keep = any(need)  # else (no gradient wanted) one block's scratch per layer will do
        keep_feat = freq is not None and need[1]  # the features are the first layer's input: for its weight gradient

        def buffer(cols: int, full: bool) -> torch.Tensor:
            return scratch.take(n if full else min(n, rows), cols, dtype)

        feat = buffer(weights[0].shape[1], keep_feat) if freq is not None else None
        hidden = [buffer(w.shape[0], keep) for w in weights[:-1]]
        out = scratch.take(n, weights[-1].shape[0], dtype)
        for s in range(0, n, rows):
            m = min(rows, n - s)
            h = xc[s:s + m]
            if feat is not None:
                f = feat[s:s + m] if keep_feat else feat[:m]
                torch.mm(h, freq, out=f)
                f.sin_()
                h = f
            for i in range(depth):
                a = out[s:s + m] if i == depth - 1 else hidden[i][s:s + m] if keep else hidden[i][:m]
                torch.addmm(biases[i], h, wts[i], out=a)
                if i < depth - 1:
                    a.relu_()
                h = a
        ctx.hidden, ctx.feat = (hidden, feat if keep_feat else None) if keep else (None, None)
        ctx.rows = rows
        ctx.save_for_backward(xc, *weights, x, *params)
        ctx.n_own, ctx.args = 1 + depth, (freq, scratch)
        return out

    @staticmethod
    @fused_backward(lambda x, *rest: blocked_mlp_torch(x, rest[:-2], rest[-2]))
    def backward(ctx, g: torch.Tensor):
        saved = ctx.saved_tensors
        xc, weights = saved[0], saved[1:ctx.n_own]
        hidden, feat, (freq, scratch) = ctx.hidden, ctx.feat, ctx.args
        depth = len(weights)
        need = ctx.needs_input_grad
        need_x = need[0]
        need_w = [need[1 + 2 * i] for i in range(depth)]
        need_b = [need[2 + 2 * i] for i in range(depth)]
        # the lowest layer whose output gradient is needed: below it nothing asks for a gradient
        low = 0 if need_x else next((i for i in range(depth) if need_w[i] or need_b[i]), depth)
        g = g.detach().to(xc.dtype).contiguous()
        n, rows = xc.shape[0], ctx.rows
        gx = scratch.take(n, xc.shape[1], xc.dtype) if need_x else None
        gw = [torch.zeros_like(w) if need_w[i] else None for i, w in enumerate(weights)]
        gb = [torch.zeros(w.shape[0], dtype=w.dtype) if need_b[i] else None for i, w in enumerate(weights)]
        for s in range(0, n, rows):
            m = min(rows, n - s)
            gy = g[s:s + m]  # gradient of layer i's output (the activation for i < L)
            for i in range(depth - 1, low - 1, -1):
                gp = gy if i == depth - 1 else torch.ops.aten.threshold_backward(gy, hidden[i][s:s + m], 0)
                gw_i, gb_i = gw[i], gb[i]
                if gw_i is not None:
                    h_in = hidden[i - 1][s:s + m] if i > 0 else xc[s:s + m] if freq is None else feat[s:s + m]
                    gw_i.addmm_(gp.t(), h_in)
                if gb_i is not None:
                    gb_i.add_(gp.sum(0))
                if i > low:
                    gy = torch.mm(gp, weights[i])
                elif gx is not None and freq is None:  # i == low == 0
                    torch.mm(gp, weights[0], out=gx[s:s + m])
                elif gx is not None:  # through the features: d sin(x B) = cos(x B) (dx B)
                    gf = torch.mm(gp, weights[0]).mul_(torch.mm(xc[s:s + m], freq).cos_())
                    torch.mm(gf, freq.t(), out=gx[s:s + m])
        grads: list[Optional[torch.Tensor]] = [gx]
        for w, b in zip(gw, gb):
            grads += [w, b]
        return (*grads, None, None)


def blocked_mlp(x: torch.Tensor, params: Sequence[torch.Tensor], scratch: MlpScratch, backend: str = "auto",
                freq: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The network of the module docstring, x (N, I) (or (N, 3) with `freq` (3, F)) -> (N, O). backend "torch" runs
    the reference, "numba" / "auto" the blocked `BlockedMlpFn` on CPU float32/float64 tensors of one dtype ("auto"
    falls back to the reference elsewhere, "numba" errors); inside ``kernels.second_order()`` both run the
    reference."""
    weights = params[0::2]
    if len(params) % 2 or not params or x.dim() != 2:
        raise ValueError(f"blocked_mlp: expected x (N, I) and (weight, bias) pairs, got x {tuple(x.shape)} and "
                         f"{len(params)} parameters")
    if freq is not None and (freq.dim() != 2 or freq.shape[0] != x.shape[1]):
        raise ValueError(f"blocked_mlp: freq {tuple(freq.shape)} must be ({x.shape[1]}, F) for x {tuple(x.shape)}")
    n_in = x.shape[1] if freq is None else freq.shape[1]
    for w_prev, w in zip((None, *weights[:-1]), weights):
        if w.shape[1] != (n_in if w_prev is None else w_prev.shape[0]):
            raise ValueError(f"blocked_mlp: layer shapes {[tuple(w.shape) for w in weights]} do not chain from an "
                             f"input {n_in} wide")
    if resolve_backend(backend, cpu_floats(x, *params, *([] if freq is None else [freq]))) == "torch":
        return blocked_mlp_torch(x, params, freq)
    return BlockedMlpFn.apply(x, *params, freq, scratch)
