"""Fused grid decoder ``relu(x W1^T) W2^T`` (no biases) for CPU tensors.

In autograd this small MLP (7 -> 32 -> 1..3 at `paper` settings) spends most of its time writing and re-reading
(N, 32) hidden tensors: the matmuls, the ReLU and its mask, forward and backward. The numba kernels cut the samples
into blocks (``block_rows``), run each block's three small matrix products through BLAS (``np.dot``: hidden layer,
output, and in the backward the input and weight gradients) and the ReLU and its mask in place on the block, so a
block's (block, 32) hidden array stays in cache; the backward recomputes it instead of storing it, except where only
the input needs a gradient (tracking: the map is frozen), whose forward keeps the ReLU mask, one byte per unit and
sample, for the backward to read (`KEEP_MASK`; the same values). The reference is
``mlp2_torch``; ``mlp2`` dispatches. Results do not depend on the thread count: every block is one set of BLAS
calls small enough that OpenBLAS runs each on one thread (M·N·K ≤ 262 144: the block size follows from the layer
shapes, ``block_rows``; the backward's from its padded shapes, ``backward_block_rows``) and the weight gradients'
per-block partial sums are added in block order. (An earlier per-sample kernel, the hidden vector in a scratch array,
ran at 0.37x this speed.) The plane decoders' kernel, three layers with biases, is ``fields.kernels.mlp3``.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from inrslam.fields.kernels.function import cpu_floats, fused_backward, resolve_kernel
from inrslam.fields.kernels.subnormal import flush_inplace, tiny_of

#: Samples per block of the parallel loops at most (`block_rows`: fixed by the layer shapes, so that the weight
#: gradients sum in the same order on any number of threads).
BLOCK = 1024

#: OpenBLAS runs a matrix product M x K by K x N on one thread when M·N·K is at most this (its SMP threshold,
#: 65536 x GEMM_MULTITHREAD_THRESHOLD 4); a larger product inside numba's parallel loop would start OpenBLAS's own
#: threads there (oversubscription, and results that depend on the thread count).
BLAS_SINGLE_THREAD_MNK = 262144


def widest(*weights) -> int:
    """The most in x out weights of any of the layers' 2-D weight arrays (tensors or arrays, transposed or not)."""
    return max((w.shape[0] * w.shape[1] for w in weights), default=0)


def block_rows(*weights) -> int:
    """Samples per block for a decoder with these layer weights: every block product (block x in by in x out, and
    the weight gradients' in x block by block x out) stays at OpenBLAS's single-thread size. Depends on the shapes
    only, never on the thread count. E.g. 7 -> 32 -> 3: 1024; a 32 x 32 layer: 256."""
    return max(1, min(BLOCK, BLAS_SINGLE_THREAD_MNK // max(1, widest(*weights))))


#: LLVM may reorder sums and fuse multiply-adds (so the loops vectorise) but not assume finite values: a NaN input
#: stays NaN in the output, as in the reference.
FASTMATH = {"reassoc", "contract", "arcp", "nsz"}


@njit(inline="always", cache=True, fastmath=FASTMATH)
def relu_inplace(h):  # pragma: no cover - numba
    """h (m, H) <- relu(h); a NaN stays NaN (not max(): that would turn NaN into 0)."""
    for k in range(h.shape[0]):
        for j in range(h.shape[1]):
            if h[k, j] < 0.0:
                h[k, j] = 0.0


@njit(inline="always", cache=True, fastmath=FASTMATH)
def relu_mask_inplace(h, gh):  # pragma: no cover - numba
    """gh <- 0 and h <- 0 where the pre-activation h <= 0 (torch's ReLU backward: a NaN passes its gradient)."""
    for k in range(h.shape[0]):
        for j in range(h.shape[1]):
            if h[k, j] <= 0.0:
                h[k, j] = 0.0
                gh[k, j] = 0.0


@njit(inline="always", cache=True, fastmath=FASTMATH)
def _block_forward(xb, w1t, w2t):  # pragma: no cover - numba
    """One block: xb (m, I) C-ordered -> relu(xb w1t) w2t (m, O)."""
    h = np.dot(xb, w1t)
    relu_inplace(h)
    return np.dot(h, w2t)


#: Whether the backward's input-side products run 8 columns wide for inputs 5-7 wide (`padded_width`); False = as
#: wide as the input (`benchmarks/bench_decoder_padding.py` times both in one process).
PAD_NARROW = True


def padded_width(n_in: int) -> int:
    """Columns of the input-side products in the backward: 8 for an input 5-7 wide (with `PAD_NARROW`), else n_in.
    OpenBLAS (its Haswell kernels, as in the NumPy / SciPy wheels) runs a (m, H) x (H, 7) product and a (7, m) x
    (m, H) one at about 0.55-0.6x the speed of the same 8 columns wide; 7 is the paper grid decoders' input (4
    features and 3 coordinates). Measured per block (one thread, input and weight gradients): widths 5, 6, 7 padded
    to 8 gain 1.1-1.3x; 3 -> 4 or 8 is even, 9 -> 12 or 16 and 12 -> 16 lose, 19 -> 20 and 35 -> 36 gain < 8 %."""
    return 8 if PAD_NARROW and 4 < int(n_in) < 8 else int(n_in)


@njit(inline="always", cache=True, fastmath=FASTMATH)
def _block_backward(xb, gyb, w1t, w1p, w2, tiny, need_x, need_w):  # pragma: no cover - numba
    """One block's gradients of relu(xb w1t) w2^T for the output gradient gyb (m, O), flushed in place (subnormal
    values count as zero): (gxb (m, I) flushed, or a (0, I) array unless need_x; gw1t (I, H); gw2 (O, H); the last
    two (0, 0) unless need_w). w1p (H, P) is w1 with P - I zero columns (`padded_width`): the input-side products
    run P wide and their padding is dropped (it would only ever hold zeros)."""
    n_in = xb.shape[1]
    flush_inplace(gyb, tiny)
    h = np.dot(xb, w1t)  # (m, H) pre-activation
    gh = np.dot(gyb, w2)  # (m, H) gradient of the activation
    relu_mask_inplace(h, gh)  # h: the activation, gh: the pre-activation's gradient
    gxb = np.empty((0, n_in), xb.dtype)
    gw1t = np.empty((0, 0), xb.dtype)
    gw2 = np.empty((0, 0), xb.dtype)
    if need_x:
        gxp = np.dot(gh, w1p)  # (m, P)
        flush_inplace(gxp, tiny)
        gxb = gxp[:, :n_in]
    if need_w:
        xt = np.zeros((w1p.shape[1], xb.shape[0]), xb.dtype)  # (P, m): x^T and P - I rows of zeros
        xt[:n_in] = xb.T
        gw1t = np.dot(xt, gh)[:n_in]
        gw2 = np.dot(np.ascontiguousarray(gyb.T), h)
    return gxb, gw1t, gw2


def padded_w1(w1t: np.ndarray) -> np.ndarray:
    """(H, P) C-ordered: w1 = w1t^T (w1t (I, H)) with P - I zero columns (`padded_width`)."""
    n_in, n_hid = w1t.shape
    w1p = np.zeros((n_hid, padded_width(n_in)), w1t.dtype)
    w1p[:, :n_in] = w1t.T
    return w1p


def backward_block_rows(n_in: int, n_hid: int, n_out: int) -> int:
    """Samples per block of the backward: `block_rows` of its widest product, the padded input side included, so
    that every product stays at OpenBLAS's single-thread size (7 -> 64 -> 4: 8 x 64 wide, 512 samples; the
    forward's blocks follow the unpadded 7 x 64: 585)."""
    return block_rows(np.empty((padded_width(n_in), n_hid)), np.empty((n_out, n_hid)))


#: Whether a forward whose weights need no gradient (tracking: the map is frozen) keeps its ReLU masks (one byte per
#: hidden unit and sample), so that its backward skips recomputing the hidden layers: here and in the plane decoders
#: (``mlp3``); the same values either way (`benchmarks/bench_decoder_mask.py` times both in one process). False =
#: recompute, as a forward with weight gradients always does.
KEEP_MASK = True


@njit(inline="always", cache=True, fastmath=FASTMATH)
def relu_keep_mask(h, mb):  # pragma: no cover - numba
    """h (m, H) <- relu(h) as `relu_inplace` does (a zero of either sign stays as it is), and mb (m, H) uint8 <- 0
    where the pre-activation is <= 0 (where `relu_mask_inplace` zeroes the gradient; a NaN passes), else 1."""
    for k in range(h.shape[0]):
        for j in range(h.shape[1]):
            if h[k, j] <= 0.0:
                mb[k, j] = 0
                if h[k, j] < 0.0:
                    h[k, j] = 0.0
            else:
                mb[k, j] = 1


@njit(inline="always", cache=True, fastmath=FASTMATH)
def zero_where_masked(g, mb):  # pragma: no cover - numba
    """g (m, H) <- 0 where the ReLU mask mb (m, H) is 0 (`relu_keep_mask`)."""
    for k in range(g.shape[0]):
        for j in range(g.shape[1]):
            if mb[k, j] == 0:
                g[k, j] = 0.0


@njit(inline="always", cache=True, fastmath=FASTMATH)
def _block_forward_mask(xb, w1t, w2t, mb):  # pragma: no cover - numba
    """`_block_forward`, also writing the ReLU mask mb (m, H) (`relu_keep_mask`)."""
    h = np.dot(xb, w1t)
    relu_keep_mask(h, mb)
    return np.dot(h, w2t)


@njit(inline="always", cache=True, fastmath=FASTMATH)
def _block_backward_mask(gyb, mb, w1p, w2, tiny, n_in):  # pragma: no cover - numba
    """The input gradient (m, n_in) of `_block_backward` (flushed as there) from the forward's ReLU mask mb (m, H)
    instead of a recomputed hidden layer: the same products on the same blocks, so the same values."""
    flush_inplace(gyb, tiny)
    gh = np.dot(gyb, w2)
    zero_where_masked(gh, mb)
    gxp = np.dot(gh, w1p)
    flush_inplace(gxp, tiny)
    return gxp[:, :n_in]


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _forward(x, w1t, w2, block, out):  # pragma: no cover - numba
    """x (N, I), w1t (I, H), w2 (O, H) -> out (N, O) = relu(x w1t) w2^T, `block` samples at a time."""
    n_pts = x.shape[0]
    w2t = np.ascontiguousarray(w2.T)
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        out[n0:n1] = _block_forward(x[n0:n1], w1t, w2t)


@njit(inline="always", cache=True)
def _joined(a, b, n0, n1):  # pragma: no cover - numba
    """Rows n0..n1 of [a, b] (columns of a, then of b) as one C-ordered (n1 - n0, Ia + Ib) block."""
    out = np.empty((n1 - n0, a.shape[1] + b.shape[1]), a.dtype)
    out[:, :a.shape[1]] = a[n0:n1]
    out[:, a.shape[1]:] = b[n0:n1]
    return out


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _forward_split(xa, xb, w1t, w2, block, ya, yb):  # pragma: no cover - numba
    """`_forward` of the input [xa, xb] (N, Ia + Ib) into the output [ya, yb] (N, Oa + Ob), each block's input
    assembled and its output split in cache (no (N, I) or (N, O) array): the same products, the same values."""
    n_pts, oa = xa.shape[0], ya.shape[1]
    w2t = np.ascontiguousarray(w2.T)
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        out = _block_forward(_joined(xa, xb, n0, n1), w1t, w2t)
        ya[n0:n1] = out[:, :oa]
        yb[n0:n1] = out[:, oa:]


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _forward_mask(x, w1t, w2, block, out, mask):  # pragma: no cover - numba
    """`_forward`, also writing the ReLU mask (N, H) uint8 (`_block_forward_mask`)."""
    n_pts = x.shape[0]
    w2t = np.ascontiguousarray(w2.T)
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        out[n0:n1] = _block_forward_mask(x[n0:n1], w1t, w2t, mask[n0:n1])


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _forward_split_mask(xa, xb, w1t, w2, block, ya, yb, mask):  # pragma: no cover - numba
    """`_forward_split`, also writing the ReLU mask (N, H) uint8 (`_block_forward_mask`)."""
    n_pts, oa = xa.shape[0], ya.shape[1]
    w2t = np.ascontiguousarray(w2.T)
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        out = _block_forward_mask(_joined(xa, xb, n0, n1), w1t, w2t, mask[n0:n1])
        ya[n0:n1] = out[:, :oa]
        yb[n0:n1] = out[:, oa:]


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _backward_mask(mask, w1p, w2, gy, block, tiny, gx):  # pragma: no cover - numba
    """The input gradient gx (N, I) of `_backward` from the forward's ReLU mask (N, H) (`_block_backward_mask`)."""
    n_pts = gy.shape[0]
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        gx[n0:n1] = _block_backward_mask(gy[n0:n1].copy(), mask[n0:n1], w1p, w2, tiny, gx.shape[1])


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _backward_split_mask(mask, w1p, w2, gya, gyb, block, ia, n_in, need_xa, need_xb, tiny, gxa,
                         gxb):  # pragma: no cover - numba
    """The input gradients gxa (N, ia) / gxb (N, n_in - ia) of `_backward_split`, each when needed, from the
    forward's ReLU mask (N, H) (`_block_backward_mask`)."""
    n_pts = gya.shape[0]
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        gx = _block_backward_mask(_joined(gya, gyb, n0, n1), mask[n0:n1], w1p, w2, tiny, n_in)
        if need_xa:
            gxa[n0:n1] = gx[:, :ia]
        if need_xb:
            gxb[n0:n1] = gx[:, ia:]


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _backward(x, w1t, w1p, w2, gy, block, need_x, need_w, tiny, gx, gw1t_parts, gw2_parts):  # pragma: no cover
    """Gradients of out = relu(x w1t) w2^T for the output gradient gy (N, O): gx (N, I) when need_x, and per-block
    weight gradients gw1t_parts (B, I, H), gw2_parts (B, O, H) when need_w (summed over blocks by the caller).
    w1p: `padded_w1(w1t)` (C-ordered: BLAS is faster on it here, 1.1-1.35x per call, and padded). Subnormal values
    of gy (|v| < tiny) count as zero, and those of gx are set to zero (``subnormal``)."""
    n_pts = x.shape[0]
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        gxb, gw1t, gw2 = _block_backward(x[n0:n1], gy[n0:n1].copy(), w1t, w1p, w2, tiny, need_x, need_w)
        if need_x:
            gx[n0:n1] = gxb
        if need_w:
            gw1t_parts[b] = gw1t
            gw2_parts[b] = gw2


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _backward_split(xa, xb, w1t, w1p, w2, gya, gyb, block, need_xa, need_xb, need_w, tiny, gxa, gxb, gw1t_parts,
                    gw2_parts):  # pragma: no cover - numba
    """`_backward` of the input [xa, xb] and the output gradient [gya, gyb], both assembled per block in cache, the
    input gradient split into gxa (N, Ia) when need_xa and gxb (N, Ib) when need_xb: the same values."""
    n_pts, ia = xa.shape[0], xa.shape[1]
    need_x = need_xa or need_xb
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        gx, gw1t, gw2 = _block_backward(_joined(xa, xb, n0, n1), _joined(gya, gyb, n0, n1), w1t, w1p, w2, tiny,
                                        need_x, need_w)
        if need_xa:
            gxa[n0:n1] = gx[:, :ia]
        if need_xb:
            gxb[n0:n1] = gx[:, ia:]
        if need_w:
            gw1t_parts[b] = gw1t
            gw2_parts[b] = gw2


def blas_fits(*weights) -> bool:
    """Whether one sample's product with every layer (in x out weights) is within OpenBLAS's single-thread size, so
    that some block size keeps every product there (`block_rows`); a larger layer runs the reference."""
    return widest(*weights) <= BLAS_SINGLE_THREAD_MNK


def keeps_mask(need_inputs, need_weights) -> bool:
    """Whether a fused decoder's forward keeps the ReLU mask (`KEEP_MASK`): some input needs a gradient and no weight
    does (tracking), so the backward computes the input gradient alone, from the mask. (A Function's forward cannot
    tell whether a graph is being recorded, so a forward under ``no_grad`` on such inputs also writes a mask, which
    is dropped with the call: tracking's one final evaluation per frame.)"""
    return KEEP_MASK and any(need_inputs) and not any(need_weights)


def mlp2_torch(x: torch.Tensor, w1: torch.Tensor, w2: torch.Tensor) -> torch.Tensor:
    """Reference: x (N, I), w1 (H, I), w2 (O, H) -> (N, O) = relu(x w1^T) w2^T (any device, fully differentiable)."""
    return torch.relu(x @ w1.t()) @ w2.t()


def mlp2_split_torch(xa: torch.Tensor, xb: torch.Tensor, w1: torch.Tensor, w2: torch.Tensor,
                     n_a: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference of `Mlp2SplitFn`: `mlp2_torch` of [xa, xb], split into its first `n_a` columns and the rest."""
    y = mlp2_torch(torch.cat([xa, xb], dim=1), w1, w2)
    return y[:, :n_a], y[:, n_a:]


class Mlp2Fn(torch.autograd.Function):
    """Fused ``relu(x W1^T) W2^T`` on CPU tensors: forward and one backward (to x and to both weights, each only
    when needed; subnormal output and input gradients count as zero). Once differentiable: a second-order backward
    (``create_graph``) differentiates ``mlp2_torch`` instead (`function.fused_backward`)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, w1: torch.Tensor, w2: torch.Tensor) -> torch.Tensor:
        xc = x.detach().contiguous()
        w1t = w1.detach().t().contiguous()
        w2c = w2.detach().contiguous()
        out = np.empty((xc.shape[0], w2c.shape[0]), dtype=w1t.numpy().dtype)
        ctx.mask = None
        if keeps_mask(ctx.needs_input_grad[:1], ctx.needs_input_grad[1:3]):
            ctx.mask = np.empty((xc.shape[0], w1t.shape[1]), dtype=np.uint8)
            _forward_mask(xc.numpy(), w1t.numpy(), w2c.numpy(), block_rows(w1t, w2c), out, ctx.mask)
        else:
            _forward(xc.numpy(), w1t.numpy(), w2c.numpy(), block_rows(w1t, w2c), out)
        ctx.save_for_backward(xc, w1t, w2c, x, w1, w2)
        ctx.n_own, ctx.args = 3, ()
        return torch.from_numpy(out)

    @staticmethod
    @fused_backward(mlp2_torch)
    def backward(ctx, gy: torch.Tensor):
        xc, w1t, w2c = ctx.saved_tensors[:3]
        need_x, need_w1, need_w2 = ctx.needs_input_grad
        need_w = need_w1 or need_w2
        n, n_in = xc.shape
        n_hid, n_out = w1t.shape[1], w2c.shape[0]
        dtype = w1t.numpy().dtype
        w1p = padded_w1(w1t.numpy())
        block = backward_block_rows(n_in, n_hid, n_out)
        if ctx.mask is not None:  # only the input gradient, from the forward's ReLU mask
            gx = np.empty((n, n_in), dtype=dtype)
            _backward_mask(ctx.mask, w1p, w2c.numpy(), gy.detach().to(w1t.dtype).contiguous().numpy(), block,
                           tiny_of(dtype), gx)
            return torch.from_numpy(gx), None, None
        n_blocks = (n + block - 1) // block if need_w else 0
        gx = np.empty((n if need_x else 0, n_in), dtype=dtype)
        gw1t = np.zeros((n_blocks, n_in, n_hid), dtype=dtype)
        gw2 = np.zeros((n_blocks, n_out, n_hid), dtype=dtype)
        _backward(xc.numpy(), w1t.numpy(), w1p, w2c.numpy(), gy.detach().to(w1t.dtype).contiguous().numpy(), block,
                  need_x, need_w, tiny_of(dtype), gx, gw1t, gw2)
        gx_t = torch.from_numpy(gx) if need_x else None
        gw1_t = torch.from_numpy(gw1t.sum(axis=0)).t().contiguous() if need_w1 else None  # blocks summed in
        gw2_t = torch.from_numpy(gw2.sum(axis=0)) if need_w2 else None  # a fixed order: any thread count
        return gx_t, gw1_t, gw2_t


def mlp2(x: torch.Tensor, w1: torch.Tensor, w2: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """relu(x W1^T) W2^T: x (N, I), w1 (H, I), w2 (O, H) -> (N, O).

    backend: "numba" (fused, CPU float32/float64 tensors, once differentiable), "torch" (reference) or "auto"
    (numba on CPU tensors of those dtypes). Inside ``kernels.second_order()`` (a ``create_graph`` backward may
    follow) both run the reference."""
    if x.dim() != 2 or w1.dim() != 2 or w2.dim() != 2 or x.shape[1] != w1.shape[1] or w2.shape[1] != w1.shape[0]:
        raise ValueError(f"mlp2: shapes x {tuple(x.shape)}, w1 {tuple(w1.shape)}, w2 {tuple(w2.shape)} do not chain "
                         "(expected (N, I), (H, I), (O, H))")
    backend = resolve_backend(backend, cpu_floats(x, w1, w2) and blas_fits(w1, w2))
    if backend == "torch":
        return mlp2_torch(x, w1, w2)
    return Mlp2Fn.apply(x, w1, w2)


class Mlp2SplitFn(torch.autograd.Function):
    """``Mlp2Fn`` on the input [xa, xb] with the output split as [ya, yb] (the first `n_a` columns, the rest),
    without the concatenated (N, I) input, the (N, O) output and their gradients ever existing: each kernel block
    assembles its rows in cache, so the values equal ``Mlp2Fn``'s on the concatenation bit for bit, and the input
    gradients come back as two contiguous arrays. Once differentiable, as ``Mlp2Fn`` (reference: `mlp2_split_torch`)."""

    @staticmethod
    def forward(ctx, xa: torch.Tensor, xb: torch.Tensor, w1: torch.Tensor, w2: torch.Tensor,
                n_a: int) -> tuple[torch.Tensor, torch.Tensor]:
        xac, xbc = xa.detach().contiguous(), xb.detach().contiguous()
        w1t = w1.detach().t().contiguous()
        w2c = w2.detach().contiguous()
        dtype = w1t.numpy().dtype
        ya = np.empty((xac.shape[0], n_a), dtype=dtype)
        yb = np.empty((xac.shape[0], w2c.shape[0] - n_a), dtype=dtype)
        ctx.mask = None
        if keeps_mask(ctx.needs_input_grad[:2], ctx.needs_input_grad[2:4]):
            ctx.mask = np.empty((xac.shape[0], w1t.shape[1]), dtype=np.uint8)
            _forward_split_mask(xac.numpy(), xbc.numpy(), w1t.numpy(), w2c.numpy(), block_rows(w1t, w2c), ya, yb,
                                ctx.mask)
        else:
            _forward_split(xac.numpy(), xbc.numpy(), w1t.numpy(), w2c.numpy(), block_rows(w1t, w2c), ya, yb)
        ctx.save_for_backward(xac, xbc, w1t, w2c, xa, xb, w1, w2)
        ctx.n_own, ctx.args = 4, (n_a,)
        return torch.from_numpy(ya), torch.from_numpy(yb)

    @staticmethod
    @fused_backward(mlp2_split_torch)
    def backward(ctx, gya: torch.Tensor, gyb: torch.Tensor):
        xac, xbc, w1t, w2c = ctx.saved_tensors[:4]
        need_xa, need_xb, need_w1, need_w2 = ctx.needs_input_grad[:4]
        need_w = need_w1 or need_w2
        n = xac.shape[0]
        n_hid, n_out = w1t.shape[1], w2c.shape[0]
        dtype = w1t.numpy().dtype
        w1p = padded_w1(w1t.numpy())
        block = backward_block_rows(w1t.shape[0], n_hid, n_out)
        gxa = np.empty((n if need_xa else 0, xac.shape[1]), dtype=dtype)
        gxb = np.empty((n if need_xb else 0, xbc.shape[1]), dtype=dtype)
        if ctx.mask is not None:  # only input gradients, from the forward's ReLU mask
            gya_np, gyb_np = (g.detach().to(w1t.dtype).contiguous().numpy() for g in (gya, gyb))
            _backward_split_mask(ctx.mask, w1p, w2c.numpy(), gya_np, gyb_np, block, xac.shape[1], w1t.shape[0],
                                 need_xa, need_xb, tiny_of(dtype), gxa, gxb)
            return (torch.from_numpy(gxa) if need_xa else None, torch.from_numpy(gxb) if need_xb else None, None, None,
                    None)
        n_blocks = (n + block - 1) // block if need_w else 0
        gw1t = np.zeros((n_blocks, w1t.shape[0], n_hid), dtype=dtype)
        gw2 = np.zeros((n_blocks, n_out, n_hid), dtype=dtype)
        gya_np, gyb_np = (g.detach().to(w1t.dtype).contiguous().numpy() for g in (gya, gyb))
        _backward_split(xac.numpy(), xbc.numpy(), w1t.numpy(), w1p, w2c.numpy(), gya_np, gyb_np,
                        block, need_xa, need_xb, need_w, tiny_of(dtype), gxa, gxb, gw1t, gw2)
        gw1_t = torch.from_numpy(gw1t.sum(axis=0)).t().contiguous() if need_w1 else None  # as in `Mlp2Fn`
        gw2_t = torch.from_numpy(gw2.sum(axis=0)) if need_w2 else None
        return (torch.from_numpy(gxa) if need_xa else None, torch.from_numpy(gxb) if need_xb else None, gw1_t, gw2_t,
                None)


def mlp2_pair(xa: torch.Tensor, xb: torch.Tensor, w1a: torch.Tensor, w2a: torch.Tensor, w1b: torch.Tensor,
              w2b: torch.Tensor, backend: str = "auto") -> tuple[torch.Tensor, torch.Tensor] | None:
    """Two decoders on the same input x = [xa, xb], (relu(x W1a^T) W2a^T, relu(x W1b^T) W2b^T): xa (N, Ia), xb (N,
    Ib), w1a (Ha, Ia + Ib), w2a (Oa, Ha), w1b (Hb, Ia + Ib), w2b (Ob, Hb) -> (N, Oa), (N, Ob), through one fused
    kernel call each way: the first layers stacked (Ha + Hb, I) and the second ones block-diagonal (Oa + Ob, Ha +
    Hb), so the samples are read, and the input gradient written, once for both; x is never concatenated
    (`Mlp2SplitFn`: each block of samples is assembled in cache, and the outputs and input gradients come back as
    separate contiguous arrays). Same maths as two `mlp2` calls on the concatenation, rounded differently (e.g. the
    input gradient is one sum over both hidden layers).
    Returns None where `backend` resolves to the reference (the caller runs its decoders as before)."""
    n_in = xa.shape[1] + xb.shape[1] if xa.dim() == 2 and xb.dim() == 2 else -1
    if n_in < 0 or xa.shape[0] != xb.shape[0]:
        raise ValueError(f"mlp2_pair: inputs xa {tuple(xa.shape)} and xb {tuple(xb.shape)} must be (N, Ia) and (N, Ib)")
    fusable = cpu_floats(xa, xb, w1a, w2a, w1b, w2b) and n_in == w1a.shape[1] == w1b.shape[1]
    if resolve_backend(backend, fusable) == "torch":
        return None
    w1 = torch.cat([w1a, w1b])
    w2 = torch.block_diag(w2a, w2b)
    if not blas_fits(w1.t(), w2):
        return None
    return Mlp2SplitFn.apply(xa, xb, w1, w2, w2a.shape[0])


def resolve_backend(backend: str, fusable: bool) -> str:
    """`function.resolve_kernel` for the decoder kernels (`field.decoder_kernel`)."""
    return resolve_kernel(backend, fusable, "decoder kernel", "CPU float32/float64 tensors of one dtype and layers "
                          f"of at most {BLAS_SINGLE_THREAD_MNK} weights")
