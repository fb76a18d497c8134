"""Table-based encoders: multi-resolution dense / hash grids, tri-planes, TensoRF (VM), all over one (M,F) table.

Every encoder maps normalised p̂ (N,3) to features (N, out_dim). Lookups clamp p̂ to [0,1]^3 (points outside
the box read the box face: border extension, never wrap-around); the gradient w.r.t. p̂ of a clamped axis is 0.
Every ``TableEncoder.table`` is updated row-wise by ``make_optimizer``'s lazy Adam.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from inrslam.fields.config import KernelChoice, TouchedRows
from inrslam.fields.kernels import TableLayout, multilinear
from inrslam.fields.kernels.combine import plane_sum, vm_product
from inrslam.fields.resolution import grid_entries, line_entries, plane_entries


class TableEncoder(nn.Module):
    """Base: ``table (M,F)`` Parameter + ``layout`` (the E lookup entries); ``lookup(p̂) -> (N,E,F)``."""

    out_dim: int  # features per point of ``forward`` (N, out_dim), set by each subclass

    def __init__(self, entries: list[dict], feature_dim: int, kernel: KernelChoice):
        super().__init__()
        self.layout = TableLayout.build(entries)
        self.feature_dim = feature_dim
        self.kernel = KernelChoice(kernel)
        self.touched = TouchedRows.READ  # rows a lazy-Adam step updates (`TouchedRows`); an owner may change it
        self.table = nn.Parameter(torch.empty(self.layout.total_rows, feature_dim))

    def lookup(self, p: torch.Tensor) -> torch.Tensor:
        return multilinear(p, self.table, self.layout, self.kernel.value, touched=TouchedRows(self.touched).value)

    def extra_repr(self) -> str:
        res = [tuple(int(v) for v in r[:d]) for r, d in zip(self.layout.res, self.layout.ndim)]
        return f"rows={self.layout.total_rows}, F={self.feature_dim}, res={res}, kernel={self.kernel.value}"


class GridEncoder(TableEncoder):
    """Multi-resolution dense or hash grid: trilinear per level, levels concatenated -> (N, L·F)
    (docs/spec.md §3.4–3.5)."""

    def __init__(self, extent: np.ndarray, coarse: float, fine: float, levels: int, feature_dim: int, hashed: bool,
                 log2_hashmap_size: int, faithful: bool, init: float, kernel: KernelChoice):
        super().__init__(grid_entries(extent, coarse, fine, levels, hashed, log2_hashmap_size, faithful),
                         feature_dim, kernel)
        self.out_dim = levels * feature_dim
        nn.init.uniform_(self.table, -init, init)

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        return self.lookup(p).reshape(p.shape[0], self.out_dim)  # (0, L·F) for no points, too


class TriPlaneEncoder(TableEncoder):
    """Tri-plane: f_l(p) = P_xy(x,y) + P_xz(x,z) + P_yz(y,z) (bilinear), levels concatenated -> (N, L·F) (§3.6)."""

    def __init__(self, sizes: list[list[int]], feature_dim: int, faithful: bool, init_std: float,
                 kernel: KernelChoice):
        super().__init__(plane_entries(sizes, faithful), feature_dim, kernel)
        self.levels = len(sizes)
        self.out_dim = self.levels * feature_dim
        nn.init.normal_(self.table, 0.0, init_std)

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        # the per-level sums by `field.kernel`: fused on CPU, bit-identical to the reference (`kernels.combine`)
        return plane_sum(self.lookup(p), self.levels, self.kernel.value)


class TensoRFEncoder(TableEncoder):
    """TensoRF vector-matrix factorisation per level (§3.7, bug 6 fixed):

    f_l(p) = P_xy(x,y)⊙ℓ_z(z) + P_xz(x,z)⊙ℓ_y(y) + P_yz(y,z)⊙ℓ_x(x)      (default, true VM)
    f_l(p) = (P_xy + P_xz + P_yz)(p) ⊙ (ℓ_z + ℓ_y + ℓ_x)(p)                 (faithful: sum of planes × sum of lines)
    Planes and lines share one table; levels concatenated -> (N, L·F).
    """

    def __init__(self, sizes: list[list[int]], feature_dim: int, faithful: bool, init_std: float,
                 kernel: KernelChoice):
        super().__init__(plane_entries(sizes, faithful) + line_entries(sizes, faithful), feature_dim, kernel)
        self.levels = len(sizes)
        self.faithful = faithful
        self.out_dim = self.levels * feature_dim
        nn.init.normal_(self.table, 0.0, init_std)

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        # the per-level products by `field.kernel`: fused on CPU, bit-identical to the reference (`kernels.combine`)
        return vm_product(self.lookup(p), self.levels, self.faithful, self.kernel.value)
