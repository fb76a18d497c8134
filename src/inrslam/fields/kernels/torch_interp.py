"""Pure-PyTorch reference of the multilinear table lookup (gather + weights; any device, twice differentiable).

Same maths as the fused kernels (see ``layout.py``); gradients come from autograd (dense table gradient).
"""

from __future__ import annotations

import torch

from inrslam.fields.kernels.layout import PRIMES, TableLayout

_CORNERS: dict[tuple[int, str], torch.Tensor] = {}


def _corners(d: int, device: torch.device) -> torch.Tensor:
    """(2^d, d) int64 corner offsets, bit k of row c = offset along axis k."""
    key = (d, str(device))
    if key not in _CORNERS:
        c = torch.arange(1 << d)
        _CORNERS[key] = torch.stack([(c >> k) & 1 for k in range(d)], dim=1).to(device)
    return _CORNERS[key]


def interp_torch(xn: torch.Tensor, table: torch.Tensor, layout: TableLayout) -> torch.Tensor:
    """Reference lookup. xn (N,3) normalised coordinates, table (M,F) -> (N,E,F)."""
    t = layout.torch_arrays(xn.device)
    # Grid coordinates in float64 (as the fused kernels): float32 u loses ~1e-4 cells at 2000 vertices.
    p = xn.clamp(0.0, 1.0).to(torch.float64)
    outs = []
    for e in range(layout.n_entries):
        d = int(layout.ndim[e])
        ax = [int(a) for a in layout.axes[e, :d]]
        scale = t["scale"][e, :d]
        offset = t["offset"][e, :d]
        res = t["res"][e, :d]
        u = p[:, ax] * scale + offset
        u = torch.clamp(u, min=torch.zeros_like(scale), max=(res - 1).to(p.dtype))
        i = torch.minimum(torch.floor(u.detach()), (res - 2).to(p.dtype))
        w = (u - i).to(table.dtype)  # (N,d)
        corners = _corners(d, xn.device)  # (C,d)
        ic = i.long()[:, None, :] + corners[None]  # (N,C,d)
        wc = torch.where(corners.bool()[None], w[:, None, :], 1.0 - w[:, None, :]).prod(-1)  # (N,C)
        if layout.hashed[e]:
            h = ic[..., 0] * PRIMES[0]
            for k in range(1, d):
                h = h ^ (ic[..., k] * PRIMES[k])
            h = h & (int(layout.rows[e]) - 1)
        else:
            h = (ic * t["stride"][e, :d]).sum(-1)
        # index_select, not table[rows]: the latter's CPU backward adds atomically in no fixed order (not deterministic)
        feats = table.index_select(0, (h + int(layout.row_off[e])).reshape(-1)).reshape(h.shape + table.shape[1:])
        outs.append((wc.unsqueeze(-1) * feats).sum(1))
    return torch.stack(outs, dim=1)
