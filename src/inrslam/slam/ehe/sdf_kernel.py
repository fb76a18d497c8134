"""Fused EHE SDF on CPU tensors (docs/ehe.md §3): s = s_prior(x) + D_s([f, p̂]) in one numba pass each way.

The reference is the composition `VoxelGrid.prior_at(x) + D_s(cat[f, p̂])` (the voxel priors' trilinear lookup
through the table kernels, then the decoder), which `EheField.sdf_from` runs with `field.kernel=torch` or
`field.decoder_kernel=torch`; the tests compare the two (values and every gradient). Fusing saves the priors' own
lookup pass and its backward, the decoder input's concatenation and, in the backward, the input gradient of p̂
(the sample positions are given: no gradient flows to them).

The decoder runs block by block through BLAS as `fields.kernels.mlp` (the block's inputs [f, p̂] gathered into one
array); the priors' interpolation and, in the backward, their scatter run per sample. Determinism: the decoder's
weight gradients are summed per block of samples (`mlp.block_rows`), blocks in order, and the priors' gradient is
scattered in sample order by one thread, so results do not depend on the thread count. (The kernels inline helpers
of `fields.kernels.trilinear` and `.mlp`: numba's cache does not see edits there, see `fields.kernels.indexing`.)
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from inrslam.fields.kernels.function import cpu_floats, second_order_active, tri_meta
from inrslam.fields.kernels.mlp import FASTMATH, blas_fits, block_rows, relu_inplace, relu_mask_inplace
from inrslam.fields.kernels.trilinear import tri_corners, tri_weights


@njit(inline="always", cache=True)
def _corners(x, n, origin, extent, res, scale, offset, lo, hi, stride, hashed, rows, row_off):
    """Rows r0..r7 and weights wx, wy, wz (`tri_weights`) of sample n in the voxel-vertex lattice, as
    `VoxelGrid.prior_at`: p = (x − origin) / extent in x's precision, then the table kernels' corner rule."""
    p0 = np.float64((x[n, 0] - origin[0]) / extent[0])
    p1 = np.float64((x[n, 1] - origin[1]) / extent[1])
    p2 = np.float64((x[n, 2] - origin[2]) / extent[2])
    r0, r1, r2, r3, r4, r5, r6, r7, wx, wy, wz, _a, _b, _c = tri_corners(p0, p1, p2, 0, res, scale, offset, lo, hi,
                                                                        stride, hashed, rows, row_off)
    return r0, r1, r2, r3, r4, r5, r6, r7, wx, wy, wz


@njit(inline="always", cache=True)
def _finite3(x, n):
    return x[n, 0] == x[n, 0] and x[n, 1] == x[n, 1] and x[n, 2] == x[n, 2]


@njit(inline="always", cache=True)
def _inputs(x, f, p, n0, n1, xin):
    """xin[:m] = [f, p] of samples n0..n1−1 (m = n1 − n0), a zero row for a sample whose x has a NaN."""
    nf = f.shape[1]
    for k in range(n1 - n0):
        n = n0 + k
        ok = _finite3(x, n)
        for i in range(nf):
            xin[k, i] = f[n, i] if ok else 0.0
        for i in range(p.shape[1]):
            xin[k, nf + i] = p[n, i] if ok else 0.0


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _forward(x, origin, extent, res, scale, offset, lo, hi, stride, hashed, rows, row_off, prior, f, p, w1t, w2,
             block, out):  # pragma: no cover - numba
    """out (N,) = Σ_c w_c prior[r_c] + relu([f, p] w1t) · w2[0]; NaN where x has a NaN coordinate. The decoder runs
    block by block through BLAS, as `mlp._forward`."""
    n_pts = x.shape[0]
    w2t = np.ascontiguousarray(w2.T)
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        xin = np.empty((n1 - n0, w1t.shape[0]), dtype=w1t.dtype)
        _inputs(x, f, p, n0, n1, xin)
        h = np.dot(xin, w1t)
        relu_inplace(h)
        d = np.dot(h, w2t)
        for k in range(n1 - n0):
            n = n0 + k
            if not _finite3(x, n):
                out[n] = np.nan
                continue
            r0, r1, r2, r3, r4, r5, r6, r7, wx, wy, wz = _corners(x, n, origin, extent, res, scale, offset, lo, hi,
                                                                  stride, hashed, rows, row_off)
            w = tri_weights(wx, wy, wz)
            s = (w[0] * prior[r0, 0] + w[1] * prior[r1, 0] + w[2] * prior[r2, 0] + w[3] * prior[r3, 0]
                 + w[4] * prior[r4, 0] + w[5] * prior[r5, 0] + w[6] * prior[r6, 0] + w[7] * prior[r7, 0])
            out[n] = s + d[k, 0]


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def _backward(x, origin, extent, res, scale, offset, lo, hi, stride, hashed, rows, row_off, f, p, w1t, w2, g,
              block, g_prior, g_f, gw1t_parts, gw2_parts):  # pragma: no cover - numba
    """For the output gradient g (N,): g_prior (V, 1) (pre-zeroed, += w_c g), g_f (N, F) and per-block weight
    gradients gw1t_parts (B, I, H), gw2_parts (B, 1, H) (pre-zeroed). Samples with a NaN coordinate contribute
    nothing; samples with a zero gradient contribute zeros and are left out of the block's products (on EHE's rays
    about a third: behind the surface, where no loss term reaches)."""
    n_pts = x.shape[0]
    nf = f.shape[1]
    n_in = w1t.shape[0]
    w1f = np.ascontiguousarray(w1t[:nf])  # (F, H): the rows of the feature inputs
    for b in prange((n_pts + block - 1) // block):
        n0 = b * block
        n1 = min(n_pts, n0 + block)
        idx = np.empty(n1 - n0, np.int64)
        m = 0
        for n in range(n0, n1):
            g_f[n, :] = 0.0
            if g[n] != 0.0 and _finite3(x, n):  # (a NaN gradient is kept: it reaches the weights, as in torch)
                idx[m] = n
                m += 1
        if m == 0:
            continue
        xin = np.empty((m, n_in), dtype=w1t.dtype)
        gb = np.empty((m, 1), dtype=w1t.dtype)
        for k in range(m):
            n = idx[k]
            for i in range(nf):
                xin[k, i] = f[n, i]
            for i in range(p.shape[1]):
                xin[k, nf + i] = p[n, i]
            gb[k, 0] = g[n]
        h = np.dot(xin, w1t)
        gh = np.dot(gb, w2)
        relu_mask_inplace(h, gh)
        gfb = np.dot(gh, w1f.T)
        for k in range(m):
            g_f[idx[k], :] = gfb[k, :]
        gw1t_parts[b] = np.dot(xin.T, gh)
        gw2_parts[b] = np.dot(gb.T, h)
    for n in range(n_pts):  # the priors: one thread, sample order
        gn = np.float64(g[n])
        if gn == 0.0 or not _finite3(x, n):  # a zero gradient adds ±0 to a row (the same sums): skipped
            continue
        r0, r1, r2, r3, r4, r5, r6, r7, wx, wy, wz = _corners(x, n, origin, extent, res, scale, offset, lo, hi,
                                                              stride, hashed, rows, row_off)
        w = tri_weights(wx, wy, wz)
        g_prior[r0, 0] += w[0] * gn
        g_prior[r1, 0] += w[1] * gn
        g_prior[r2, 0] += w[2] * gn
        g_prior[r3, 0] += w[3] * gn
        g_prior[r4, 0] += w[4] * gn
        g_prior[r5, 0] += w[5] * gn
        g_prior[r6, 0] += w[6] * gn
        g_prior[r7, 0] += w[7] * gn


class EheSdfFn(torch.autograd.Function):
    """s (N,) of world samples x (N, 3), dense-level features f (N, F) and p̂ (N, 3); differentiable in f, the
    prior table (V, 1) and both decoder weights (x and p̂ get no gradient). Once differentiable."""

    @staticmethod
    def forward(ctx, x, f, p, prior, w1, w2, voxels):
        xc, fc, pc = x.detach().contiguous(), f.detach().contiguous(), p.detach().contiguous()
        w1t = w1.detach().t().contiguous()
        w2c = w2.detach().contiguous()
        extent = voxels.origin.new_tensor(voxels.dims) * voxels.voxel_size
        origin = voxels.origin.detach().contiguous()
        meta = tri_meta(voxels.priors.layout)
        out = np.empty(xc.shape[0], dtype=w1t.numpy().dtype)
        _forward(xc.numpy(), origin.numpy(), extent.numpy(), *meta, prior.detach().numpy(), fc.numpy(), pc.numpy(),
                 w1t.numpy(), w2c.numpy(), block_rows(w1t, w2c), out)
        ctx.save_for_backward(xc, fc, pc, w1t, w2c, origin, extent)
        ctx.meta = meta
        ctx.n_prior = prior.shape[0]
        return torch.from_numpy(out)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        xc, fc, pc, w1t, w2c, origin, extent = ctx.saved_tensors
        dtype = w1t.numpy().dtype
        n, n_hid = xc.shape[0], w1t.shape[1]
        block = block_rows(w1t, w2c)
        n_blocks = (n + block - 1) // block
        g_prior = np.zeros((ctx.n_prior, 1), dtype=dtype)
        g_f = np.empty(fc.shape, dtype=dtype)
        gw1t = np.zeros((n_blocks, w1t.shape[0], n_hid), dtype=dtype)
        gw2 = np.zeros((n_blocks, 1, n_hid), dtype=dtype)
        _backward(xc.numpy(), origin.numpy(), extent.numpy(), *ctx.meta, fc.numpy(), pc.numpy(), w1t.numpy(),
                  w2c.numpy(), g.detach().to(w1t.dtype).contiguous().numpy(), block, g_prior, g_f, gw1t, gw2)
        gw1 = torch.from_numpy(gw1t.sum(axis=0)).t().contiguous()  # blocks summed in a fixed order
        gw2_t = torch.from_numpy(gw2.sum(axis=0))
        return None, torch.from_numpy(g_f), None, torch.from_numpy(g_prior), gw1, gw2_t, None


def fusable(x: torch.Tensor, f: torch.Tensor, prior: torch.Tensor, w1: torch.Tensor, w2: torch.Tensor) -> bool:
    """True where `ehe_sdf` can run: CPU float32/float64 tensors of one dtype, a one-output decoder whose hidden
    layer fits OpenBLAS's single-thread size (`mlp.blas_fits`), first-order."""
    return (cpu_floats(x, f, prior, w1, w2) and blas_fits(w1) and w2.shape[0] == 1
            and not second_order_active())


def ehe_sdf(x: torch.Tensor, f: torch.Tensor, p: torch.Tensor, voxels, w1: torch.Tensor,
            w2: torch.Tensor) -> torch.Tensor:
    """s = prior(x) + relu([f, p̂] w1^T) w2^T, (N,) T-units, fused (check `fusable` first).

    Args: x (N, 3) world metres; f (N, F) dense-level features; p (N, 3) normalised positions; voxels the
    `VoxelGrid` (its prior table and lattice); w1 (H, F + 3), w2 (1, H) the SDF decoder's weights."""
    return EheSdfFn.apply(x, f, p, voxels.priors.table, w1, w2, voxels)
