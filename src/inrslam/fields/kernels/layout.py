"""Description of a set of multilinear lookup tables ("entries") sharing one parameter table.

One entry is a D-dimensional vertex grid (D = 3: a grid level, D = 2: a plane, D = 1: a line) whose
vertex features live in rows ``row_off[e] .. row_off[e] + rows[e]`` of a single ``(M, F)`` table. A point
with normalised coordinates p̂ ∈ [0,1]^3 is looked up along the entry's axes ``axes[e, :D]``:

    u_k = clamp(clamp(p̂_{a_k}, 0, 1) · scale[e,k] + offset[e,k], 0, R_k − 1)      (grid coordinate)
    i_k = min(⌊u_k⌋, R_k − 2),  w_k = u_k − i_k                                      (corner, weight)
    f_e(p̂) = Σ_{c ∈ {0,1}^D} Π_k (c_k ? w_k : 1 − w_k) · T[row_off[e] + idx_e(i + c)]

with idx_e(i) = Σ_k i_k·stride[e,k] (direct indexing) or, for hashed entries,
idx_e(i) = (i_0·1 ⊕ i_1·2654435761 ⊕ i_2·805459861) mod rows[e] (rows[e] a power of two; tiny-cuda-nn's
"coherent prime" hash). Points outside the box are clamped to the box (border extension, no wrap-around).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch

from inrslam.fields.kernels.workspace import KernelWorkspace

PRIMES = (1, 2654435761, 805459861)


@dataclass(eq=False, slots=True)
class TableLayout:
    """Layout of E lookup entries over one (M, F) table: which rows each owns and how a point maps to them (numpy
    arrays, all of leading size E)."""

    ndim: np.ndarray  # (E,) int64, D ∈ {1,2,3}
    axes: np.ndarray  # (E,3) int64, looked-up axes of p̂ (unused slots 0)
    res: np.ndarray  # (E,3) int64, vertices per entry axis R_k ≥ 2 (unused slots 1)
    scale: np.ndarray  # (E,3) float64, u = p̂·scale + offset
    offset: np.ndarray  # (E,3) float64
    stride: np.ndarray  # (E,3) int64, direct-indexing strides (unused slots 0)
    hashed: np.ndarray  # (E,) bool, spatial hash instead of direct indexing
    rows: np.ndarray  # (E,) int64, table rows owned by the entry
    row_off: np.ndarray  # (E,) int64, first row of the entry
    lo: np.ndarray  # (E,3) float64, u's clamp range [lo, hi] = [0, R−1] ∩ [offset, scale + offset] (p̂ ∈ [0,1])
    hi: np.ndarray  # (E,3) float64
    #: every entry is 3-D over axes (x, y, z): the specialised trilinear kernels apply (derived)
    trilinear: bool = field(init=False)
    #: the kernels' scratch for this layout (``workspace.py``); never copied or pickled
    workspace: KernelWorkspace = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.trilinear = bool(np.all(self.ndim == 3) and np.all(self.axes == np.array([0, 1, 2])))
        self.workspace = KernelWorkspace()

    def __getstate__(self) -> dict:
        """Copies and pickles carry the layout only: a copy starts with an empty workspace."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "workspace"}

    def __setstate__(self, state: dict) -> None:
        for k, v in state.items():
            setattr(self, k, v)
        self.workspace = KernelWorkspace()

    @property
    def n_entries(self) -> int:
        return int(self.ndim.shape[0])

    @property
    def total_rows(self) -> int:
        return int(self.row_off[-1] + self.rows[-1]) if self.n_entries else 0

    @staticmethod
    def build(entries: list[dict]) -> "TableLayout":
        """Pack entries given as dicts with keys axes (list), res (list), scale, offset (lists), rows (int|None),
        hashed (bool). ``rows=None`` means exactly prod(res) rows (direct indexing)."""
        E = len(entries)
        ndim = np.zeros(E, np.int64)
        axes = np.zeros((E, 3), np.int64)
        res = np.ones((E, 3), np.int64)
        scale = np.zeros((E, 3), np.float64)
        offset = np.zeros((E, 3), np.float64)
        stride = np.zeros((E, 3), np.int64)
        hashed = np.zeros(E, np.bool_)
        rows = np.zeros(E, np.int64)
        row_off = np.zeros(E, np.int64)
        off = 0
        for e, ent in enumerate(entries):
            d = len(ent["axes"])
            if not 1 <= d <= 3:
                raise ValueError(f"entry {e}: {d} axes, expected 1..3")
            r = [int(v) for v in ent["res"]]
            if min(r) < 2:
                raise ValueError(f"entry {e}: resolution {r} needs >= 2 vertices per axis")
            if min(float(v) for v in ent["scale"]) <= 0.0:
                raise ValueError(f"entry {e}: scale {list(ent['scale'])} must be positive")
            ndim[e] = d
            axes[e, :d] = ent["axes"]
            res[e, :d] = r
            scale[e, :d] = ent["scale"]
            offset[e, :d] = ent["offset"]
            s = 1
            for k in range(d):
                stride[e, k] = s
                s *= r[k]
            n_rows = ent.get("rows") or s
            hashed[e] = bool(ent.get("hashed", False))
            if hashed[e] and (n_rows & (n_rows - 1)):
                raise ValueError(f"entry {e}: hashed table size {n_rows} must be a power of two")
            if not hashed[e] and n_rows < s:
                raise ValueError(f"entry {e}: {n_rows} rows cannot index {s} vertices directly")
            rows[e] = n_rows
            row_off[e] = off
            off += n_rows
        # both clamps of u in one: p̂ ↦ p̂·scale + offset is increasing (scale > 0), so clamping p̂ to [0,1] first is
        # the same as clamping u to [offset, scale + offset] (0·scale and 1·scale are exact)
        lo = np.maximum(offset, 0.0)
        hi = np.minimum(scale + offset, res - 1.0)
        return TableLayout(ndim, axes, res, scale, offset, stride, hashed, rows, row_off, lo, hi)

    def torch_arrays(self, device: torch.device) -> dict[str, torch.Tensor]:
        """The metadata as tensors on ``device`` (cached), for the reference path."""
        cache = self.workspace.torch_arrays
        key = str(device)
        if key not in cache:
            cache[key] = {
                k: torch.as_tensor(getattr(self, k), device=device)
                for k in ("axes", "res", "scale", "offset", "stride", "rows", "row_off")
            }
        return cache[key]
