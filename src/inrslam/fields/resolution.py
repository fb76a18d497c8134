"""Grid / plane / line resolutions from block sizes (docs/spec.md §3.1) as ``TableLayout`` entries.

Default ("fixed") rule, per axis so cells are (nearly) cubic in metres: level l has cell size
h_l = h_coarse·(h_fine/h_coarse)^(l/(L−1)) (h_fine for L = 1) and R_a = ⌈L_a/h_l⌉ + 1 vertices along an axis of
extent L_a; the grid coordinate is u = p̂·(R_a − 1) (vertex-aligned: box faces lie on vertices).

Faithful rule (tiny-cuda-nn "Grid" of the original): one cubic resolution over the normalised box,
N₀ = max_a ⌊L_a/h_coarse⌋, b = (max_a ⌊L_a/h_fine⌋ / N₀)^(1/(L−1)), S_l = N₀·b^l − 1, R_l = ⌈S_l⌉ + 1,
u = p̂·S_l + 0.5, storage R_l³ rounded up to a multiple of 8 (hash levels capped at 2^log2_hashmap_size and
hashed when R_l³ exceeds it). Faithful planes/lines: level 0 ⌊L_a/h_coarse⌋, level l+1 ⌊n_l·(n_fine/n_coarse)^(1/(L−1))⌋
per axis, sampled with [0,1] coordinates in a [−1,1] sampler: u = (p̂ + 1)/2·(R − 1) (only the upper half is used).
"""

from __future__ import annotations

import math

import numpy as np

from inrslam.errors import ConfigError

PLANE_AXES = ((0, 1), (0, 2), (1, 2))  # xy, xz, yz
LINE_AXES = (2, 1, 0)  # the axis each plane leaves out: z, y, x (VM pairing P_xy⊙ℓ_z, P_xz⊙ℓ_y, P_yz⊙ℓ_x)


def level_cells(coarse: float, fine: float, levels: int) -> list[float]:
    """Cell sizes h_l (m), geometric from coarse to fine."""
    if levels == 1:
        return [fine]
    return [coarse * (fine / coarse) ** (l / (levels - 1)) for l in range(levels)]


def vertex_count(extent: float, cell: float) -> int:
    """R = ⌈L/h⌉ + 1 (≥ 2) vertices covering an extent L with cells of at most h metres."""
    return max(2, math.ceil(extent / cell - 1e-6) + 1)


def _next8(n: int) -> int:
    return (n + 7) // 8 * 8


def grid_entries(extent: np.ndarray, coarse: float, fine: float, levels: int, hashed: bool,
                 log2_hashmap_size: int, faithful: bool) -> list[dict]:
    """Entries of a multi-resolution dense (hashed=False) or hash grid over a box of ``extent`` (3,) metres."""
    cap = 1 << log2_hashmap_size
    out = []
    if faithful:
        n0 = max(1, max(math.floor(e / coarse) for e in extent))
        nf = max(1, max(math.floor(e / fine) for e in extent))
        if nf < 2 or (levels > 1 and n0 < 2):  # resolution 1: the original's level has scale 0 (one cell read)
            cell = fine if nf < 2 else coarse  # one level is the fine one alone
            raise ConfigError(f"field.faithful=true: the scene box's longest side ({max(extent):.3f} m) is under twice "
                              f"the cell size ({cell} m), so the original's grid rule gives a "
                              "level without cells; use a smaller field.block_coarse / block_fine or faithful=false")
        scales = [nf - 1.0] if levels == 1 else [n0 * (nf / n0) ** (l / (levels - 1)) - 1.0 for l in range(levels)]
        for s in scales:
            r = max(2, math.ceil(s) + 1)
            n = r ** 3
            use_hash = hashed and n > cap
            rows = cap if use_hash else (min(_next8(n), cap) if hashed else _next8(n))
            out.append(dict(axes=[0, 1, 2], res=[r] * 3, scale=[s] * 3, offset=[0.5] * 3, rows=rows,
                            hashed=use_hash))
        return out
    for h in level_cells(coarse, fine, levels):
        res = [vertex_count(e, h) for e in extent]
        n = res[0] * res[1] * res[2]
        use_hash = hashed and n > cap
        out.append(dict(axes=[0, 1, 2], res=res, scale=[r - 1.0 for r in res], offset=[0.0] * 3,
                        rows=cap if use_hash else n, hashed=use_hash))
    return out


def plane_sizes(extent: np.ndarray, coarse: float, fine: float, levels: int, faithful: bool) -> list[list[int]]:
    """Per-level per-axis vertex counts (n_x, n_y, n_z) of planes and lines."""
    if not faithful:
        return [[vertex_count(e, h) for e in extent] for h in level_cells(coarse, fine, levels)]
    n = [max(1, math.floor(e / coarse)) for e in extent]
    nf = [max(1, math.floor(e / fine)) for e in extent]
    if levels == 1:
        return [[max(2, v) for v in nf]]
    sizes = [n]
    for _ in range(levels - 1):
        n = [math.floor(a * (f / c) ** (1.0 / (levels - 1))) for a, f, c in zip(n, nf, sizes[0])]
        sizes.append(n)
    return [[max(2, v) for v in s] for s in sizes]


def _coord(r: int, faithful: bool) -> tuple[float, float]:
    """(scale, offset) of u = p̂·scale + offset on an axis of r vertices."""
    if faithful:  # [0,1] fed to an align-corners [−1,1] sampler
        return (r - 1) / 2.0, (r - 1) / 2.0
    return r - 1.0, 0.0


def plane_entries(sizes: list[list[int]], faithful: bool) -> list[dict]:
    """Three planes (xy, xz, yz) per level, level-major."""
    out = []
    for s in sizes:
        for a, b in PLANE_AXES:
            (sa, oa), (sb, ob) = _coord(s[a], faithful), _coord(s[b], faithful)
            out.append(dict(axes=[a, b], res=[s[a], s[b]], scale=[sa, sb], offset=[oa, ob], rows=None, hashed=False))
    return out


def line_entries(sizes: list[list[int]], faithful: bool) -> list[dict]:
    """Three lines (z, y, x) per level, level-major (line k pairs with plane k)."""
    out = []
    for s in sizes:
        for a in LINE_AXES:
            sc, of = _coord(s[a], faithful)
            out.append(dict(axes=[a], res=[s[a]], scale=[sc], offset=[of], rows=None, hashed=False))
    return out
