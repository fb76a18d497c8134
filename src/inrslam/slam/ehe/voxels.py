"""The sparse coarse level of EHE (docs/ehe.md §2): voxels of edge `voxel_size` over the scene box, allocated where
back-projected depth falls, each voxel vertex holding one learnable SDF prior (T-units).

Storage: voxel keys (i, j, k) are linearised over the box, key = i + nx·(j + ny·k), and an allocation mask over all
keys serves as a perfect hash map (O(1) lookups, 1 byte per possible voxel); vertex priors are one (V, 1) table over
the (nx+1)(ny+1)(nz+1) vertex lattice (vertex id i + vx·(j + vy·k)), read with the fused trilinear kernels of
`inrslam.fields.kernels` and updated row-wise; only the vertices of allocated voxels are ever initialised or
touched (docs/differences.md: the CPU-natural replacement of the original's octree).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import njit
from torch import Tensor, nn

from inrslam.fields.config import KernelChoice
from inrslam.fields.encoders import TableEncoder
from inrslam.geometry.intrinsics import Intrinsics

# the 8 corner offsets of a voxel, (8, 3), in the order (dx, dy, dz) = binary of 0..7 (dz fastest)
CORNERS = torch.tensor([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], dtype=torch.long)


@dataclass
class Allocation:
    """What one frame's depth did to the voxel structure.

    observed: (K,) int64 keys of the voxels the frame's points allocate (occupied + margin neighbours), sorted;
    new: (K',) keys among them that were not allocated before; capped: True when the vertex cap refused them.
    """

    observed: Tensor
    new: Tensor
    capped: bool = False


class VoxelGrid(nn.Module):
    """Sparse voxels over `bounds` ((3, 2) metres) with a learnable SDF prior per vertex.

    Buffers: allocated (nx·ny·nz,) bool; vertex_used, vertex_init (V,) bool, V = (nx+1)(ny+1)(nz+1).
    Parameter: priors.table (V, 1) SDF prior in T-units (0 until initialised); `prior` is its (V,) view.
    """

    origin: Tensor  # (3,) metres, the box minimum (vertex (0, 0, 0))
    allocated: Tensor  # (nx·ny·nz,) bool
    vertex_used: Tensor  # (V,) bool, vertex of an allocated voxel
    vertex_init: Tensor  # (V,) bool, prior initialised
    priors: TableEncoder

    def __init__(self, bounds: np.ndarray, voxel_size: float, kernel: KernelChoice = KernelChoice.AUTO):
        super().__init__()
        b = np.asarray(bounds, dtype=np.float64)
        self.voxel_size = float(voxel_size)
        self.dims = tuple(max(1, int(math.ceil((b[a, 1] - b[a, 0]) / voxel_size - 1e-9))) for a in range(3))
        self.vdims = tuple(n + 1 for n in self.dims)
        self.register_buffer("origin", torch.tensor(b[:, 0], dtype=torch.float32))
        self.register_buffer("allocated", torch.zeros(int(np.prod(self.dims)), dtype=torch.bool))
        n_vert = int(np.prod(self.vdims))
        self.register_buffer("vertex_used", torch.zeros(n_vert, dtype=torch.bool))
        self.register_buffer("vertex_init", torch.zeros(n_vert, dtype=torch.bool))
        entry = dict(axes=[0, 1, 2], res=list(self.vdims), scale=[float(n) for n in self.dims], offset=[0.0] * 3,
                     rows=n_vert, hashed=False)
        self.priors = TableEncoder([entry], 1, kernel)
        nn.init.zeros_(self.priors.table)

    @property
    def prior(self) -> Tensor:
        """(V,) vertex priors, T-units (a view of the table)."""
        return self.priors.table[:, 0]

    # -- keys ------------------------------------------------------------------------------------------------------
    def coords(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """(N, 3) metres -> voxel coordinates (N, 3) int64 and (N,) bool inside the box."""
        ijk = torch.floor((points - self.origin) / self.voxel_size).long()
        dims = torch.tensor(self.dims, device=points.device)
        inside = ((ijk >= 0) & (ijk < dims)).all(dim=1)
        return ijk, inside

    def key(self, ijk: Tensor) -> Tensor:
        """(..., 3) voxel coordinates -> (...,) linear keys i + nx·(j + ny·k)."""
        nx, ny, _ = self.dims
        return ijk[..., 0] + nx * (ijk[..., 1] + ny * ijk[..., 2])

    def unkey(self, key: Tensor) -> Tensor:
        """(K,) keys -> (K, 3) voxel coordinates."""
        nx, ny, _ = self.dims
        return torch.stack([key % nx, (key // nx) % ny, key // (nx * ny)], dim=-1)

    def vertex_ids(self, key: Tensor) -> Tensor:
        """(K,) voxel keys -> (K, 8) flat ids of their corner vertices (CORNERS order)."""
        c = self.unkey(key)[:, None, :] + CORNERS.to(key.device)
        vx, vy, _ = self.vdims
        return c[..., 0] + vx * (c[..., 1] + vy * c[..., 2])

    def lookup(self, points: Tensor) -> Tensor:
        """(N, 3) metres -> (N,) key of the allocated voxel holding each point, -1 where none."""
        ijk, inside = self.coords(points)
        k = self.key(ijk.clamp_min(0)).clamp_max(self.allocated.numel() - 1)
        return torch.where(inside & self.allocated[k], k, torch.full_like(k, -1))

    @property
    def n_allocated(self) -> int:
        return int(self.allocated.sum())

    @property
    def n_vertices(self) -> int:
        return int(self.vertex_used.sum())

    def point_stats(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Per voxel key: the number of points (N, 3) metres inside it, (n_keys,) int64, and the sum of their
        positions inside the voxel ((x − origin)/voxel_size − ijk, in [0, 1)³), (n_keys, 3). One numba pass on
        CPU float32 points; `point_stats_torch` (the reference) otherwise."""
        if points.device.type != "cpu" or points.dtype != torch.float32:
            return self.point_stats_torch(points)
        n_keys = self.allocated.numel()
        counts = np.zeros(n_keys, np.int64)
        sums = np.zeros((n_keys, 3), np.float32)
        nx, ny, nz = self.dims
        _point_stats(points.contiguous().numpy(), self.origin.numpy(), np.float32(self.voxel_size), nx, ny, nz,
                     counts, sums)
        return torch.from_numpy(counts), torch.from_numpy(sums)

    def point_stats_torch(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """`point_stats` in torch (any device)."""
        ijk, inside = self.coords(points)
        ijk, pts = ijk[inside], points[inside]
        n_keys = self.allocated.numel()
        key = self.key(ijk)
        counts = torch.bincount(key, minlength=n_keys)
        local = (pts - self.origin) / self.voxel_size - ijk.to(pts.dtype)  # (N, 3) in [0, 1)
        return counts, torch.zeros(n_keys, 3, dtype=pts.dtype, device=pts.device).index_add_(0, key, local)

    # -- allocation ------------------------------------------------------------------------------------------------
    @torch.no_grad()
    def allocate(self, points: Tensor, min_points: int, margin: float, max_vertices: int) -> Allocation:
        """Allocate the voxels of one frame's world points (N, 3) metres.

        Rule (docs/ehe.md §2): a voxel holding more than `min_points` points is allocated; for each axis, when the
        mean of its points lies within `margin`·voxel_size of a face, the face neighbour is allocated too.
        """
        counts, sums = self.point_stats(points)
        occ = torch.nonzero(counts > min_points).squeeze(1)
        if occ.numel() == 0:
            empty = occ.new_zeros(0)
            return Allocation(empty, empty)
        mean = sums[occ] / counts[occ, None].to(sums.dtype)  # (K, 3)
        base = self.unkey(occ)
        cand = [base]
        dims = torch.tensor(self.dims, device=points.device)
        for a in range(3):
            for side, near in ((-1, mean[:, a] < margin), (1, mean[:, a] > 1.0 - margin)):
                nb = base[near].clone()
                nb[:, a] += side
                cand.append(nb[((nb >= 0) & (nb < dims)).all(dim=1)])
        observed = torch.unique(self.key(torch.cat(cand)))
        new = observed[~self.allocated[observed]]
        if new.numel():
            verts = self.vertex_ids(new).reshape(-1)
            added = int((~self.vertex_used[torch.unique(verts)]).sum())
            if self.n_vertices + added > max_vertices:
                return Allocation(observed[self.allocated[observed]], new[:0], capped=True)
            self.allocated[new] = True
            self.vertex_used[verts] = True
        return Allocation(observed, new)

    # -- SDF priors --------------------------------------------------------------------------------------------------
    @torch.no_grad()
    def init_priors(self, keys: Tensor, depth: Tensor, intr: Intrinsics, c2w: Tensor, truncation: float) -> int:
        """Projective-TSDF priors for the not yet initialised vertices of voxels `keys` (K,) from one depth map.

        prior(v) = (D(π(v)) − z_v) / T for each corner v (z_v its camera z-depth, D the depth at its nearest
        pixel). A voxel is accepted only if all 8 corners project inside the image with z > 0 onto valid depth
        and every |D − z_v| <= √6 · voxel_size; each vertex is initialised once. Returns the voxels accepted.

        Args: depth (H, W) metres (0 = none); c2w (4, 4) camera-to-world; truncation T metres.
        """
        if keys.numel() == 0:
            return 0
        vid = self.vertex_ids(keys)  # (K, 8)
        todo = ~self.vertex_init[vid].all(dim=1)
        keys, vid = keys[todo], vid[todo]
        if keys.numel() == 0:
            return 0
        corners = (self.unkey(keys)[:, None, :] + CORNERS.to(keys.device)).to(c2w.dtype) * self.voxel_size
        world = corners + self.origin.to(c2w.dtype)
        w2c = torch.linalg.inv(c2w)
        cam = world @ w2c[:3, :3].T + w2c[:3, 3]  # (K, 8, 3)
        z = cam[..., 2]
        zs = torch.where(z > 0, z, torch.ones_like(z))
        u = torch.round(intr.fx * cam[..., 0] / zs + intr.cx)
        v = torch.round(intr.fy * cam[..., 1] / zs + intr.cy)
        H, W = depth.shape
        ok = (z > 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        d = depth[v.clamp(0, H - 1).long(), u.clamp(0, W - 1).long()]
        dist = d - z
        ok &= (d > 0) & (dist.abs() <= math.sqrt(6.0) * self.voxel_size)
        accept = ok.all(dim=1)
        vid, prior = vid[accept].reshape(-1), (dist[accept] / truncation).reshape(-1)
        fresh = ~self.vertex_init[vid]
        self.priors.table.data[vid[fresh], 0] = prior[fresh].to(self.priors.table.dtype)
        self.vertex_init[vid[fresh]] = True
        return int(accept.sum())

    def prior_at(self, points: Tensor) -> Tensor:
        """Trilinear interpolation of the 8 vertex priors of the voxel cell holding each point, (N,) T-units.

        s_p(x) = Σ_c w_c prior(v_c), w_c = Π_a (t_a if c_a = 1 else 1 − t_a), t = (x − origin)/voxel − ijk; points
        outside the box use the nearest cell (t clamped to [0, 1]). Differentiable in the priors (fused kernels).
        """
        extent = self.origin.new_tensor(self.dims) * self.voxel_size
        return self.priors.lookup((points - self.origin) / extent)[:, 0, 0]


@njit(cache=True)
def _point_stats(points, origin, voxel, nx, ny, nz, counts, sums):  # pragma: no cover - numba
    """`VoxelGrid.point_stats` for float32 points: voxel coordinates floor((x − origin)/voxel) in float32 as
    `VoxelGrid.coords`; points outside the box are skipped."""
    for n in range(points.shape[0]):
        u0 = (points[n, 0] - origin[0]) / voxel
        u1 = (points[n, 1] - origin[1]) / voxel
        u2 = (points[n, 2] - origin[2]) / voxel
        if not (0.0 <= u0 < nx and 0.0 <= u1 < ny and 0.0 <= u2 < nz):  # outside the box, or NaN
            continue
        i, j, k = math.floor(u0), math.floor(u1), math.floor(u2)
        key = i + nx * (j + ny * k)
        counts[key] += 1
        sums[key, 0] += u0 - i
        sums[key, 1] += u1 - j
        sums[key, 2] += u2 - k
