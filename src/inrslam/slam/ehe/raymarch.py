"""Ray / sparse-voxel intersection and sampling inside the hit voxels (docs/ehe.md §3).

A 3-D DDA (Amanatides & Woo, Eurographics 1987) walks each ray through the voxel lattice and records the first
`max_hits` allocated voxels as intervals [t_in, t_out] of the ray parameter (z-depth: camera directions have z = 1).
Samples then lie on one ray-aligned lattice t_k = (k + u)·Δt, Δt = step / |d| (metric spacing `step`), kept where
they fall inside a hit interval: the spacing is uniform across voxel faces and no sample lies in free voxels.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from numba import njit
from torch import Tensor

from inrslam.slam.ehe.voxels import VoxelGrid


class PackedSamples(NamedTuple):
    """The valid samples of R rays only, in ray order: z (N,) ray parameter (metres of z-depth), ray (N,) int64 its
    ray, start (R + 1,) int64 offsets of each ray's samples, points (N, 3) world o + z d (float32)."""

    z: Tensor
    ray: Tensor
    start: Tensor
    points: Tensor


class RaySamples(NamedTuple):
    """Samples of R rays, padded to S per ray: z (R, S) ray parameter (z-depth, metres, sorted; padding repeats the
    last valid value), valid (R, S) bool, n_hits (R,) int64 merged hit intervals (0 = the ray misses every voxel)."""

    z: Tensor
    valid: Tensor
    n_hits: Tensor


def voxel_hits(grid: VoxelGrid, origins: Tensor, dirs: Tensor, max_hits: int, t_max: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merged intervals of the first `max_hits` allocated voxels along each ray.

    Args: origins, dirs (R, 3) world, metres (t = z-depth); t_max: furthest t.
    Returns: t_in, t_out (R, max_hits) float64 (valid up to n_hits), n_hits (R,) int64 intervals.

    Adjacent allocated voxels along a ray merge into one interval; `max_hits` counts voxels, so a ray ends after
    its max_hits-th allocated voxel.
    """
    vs = grid.voxel_size
    o = ((origins.detach().double() - grid.origin.double()) / vs).cpu().numpy()
    d = (dirs.detach().double() / vs).cpu().numpy()
    R = o.shape[0]
    t_in = np.zeros((R, max_hits))
    t_out = np.zeros((R, max_hits))
    n = np.zeros(R, np.int64)
    nx, ny, nz = grid.dims
    _dda(o, d, grid.allocated.cpu().numpy(), nx, ny, nz, float(t_max), int(max_hits), t_in, t_out, n)
    return t_in, t_out, n


@njit(inline="always", cache=True)
def _axis_start(o, d, t0, dim):
    """DDA state of one axis at the entry point o + t0·d: cell c, step s (±1, 0), the t of the next face tn and the
    t between faces td (inf when the ray is parallel to the axis)."""
    c = min(max(int(math.floor(o + t0 * d)), 0), dim - 1)
    if d > 0.0:
        return c, 1, (c + 1 - o) / d, 1.0 / d
    if d < 0.0:
        return c, -1, (c - o) / d, -1.0 / d
    return c, 0, np.inf, np.inf


@njit(cache=True)
def _dda(o, d, alloc, nx, ny, nz, t_max, max_hits, t_in, t_out, n_hits):
    """For each ray r (origin o, direction d in voxel units): merged intervals t_in[r, :h], t_out[r, :h] (h =
    n_hits[r]) of the first max_hits allocated voxels it crosses within t in [0, t_max]. The walk's state lives in
    scalars (no per-ray arrays)."""
    dims = (nx, ny, nz)
    for r in range(o.shape[0]):
        n_hits[r] = 0
        t0, t1 = 0.0, t_max
        for a in range(3):
            if d[r, a] != 0.0:
                ta = (0.0 - o[r, a]) / d[r, a]
                tb = (dims[a] - o[r, a]) / d[r, a]
                if ta > tb:
                    ta, tb = tb, ta
                t0, t1 = max(t0, ta), min(t1, tb)
            elif o[r, a] < 0.0 or o[r, a] >= dims[a]:
                t1 = -1.0
        if t0 >= t1:
            continue
        c0, s0, tn0, td0 = _axis_start(o[r, 0], d[r, 0], t0, nx)
        c1, s1, tn1, td1 = _axis_start(o[r, 1], d[r, 1], t0, ny)
        c2, s2, tn2, td2 = _axis_start(o[r, 2], d[r, 2], t0, nz)
        voxels = 0
        t = t0
        while t < t1:
            # the axis whose face comes first (ties: the lower axis)
            if tn1 < tn0:
                a = 2 if tn2 < tn1 else 1
            else:
                a = 2 if tn2 < tn0 else 0
            tn = tn0 if a == 0 else (tn1 if a == 1 else tn2)
            t_end = min(tn, t1)
            if t_end > t and alloc[c0 + nx * (c1 + ny * c2)]:
                h = n_hits[r]
                if h > 0 and t_out[r, h - 1] >= t:
                    t_out[r, h - 1] = t_end
                else:
                    t_in[r, h], t_out[r, h] = t, t_end
                    n_hits[r] = h + 1
                voxels += 1
                if voxels >= max_hits:
                    break
            if a == 0:
                c0 += s0
                if c0 < 0 or c0 >= nx:
                    break
                tn0 += td0
            elif a == 1:
                c1 += s1
                if c1 < 0 or c1 >= ny:
                    break
                tn1 += td1
            else:
                c2 += s2
                if c2 < 0 or c2 >= nz:
                    break
                tn2 += td2
            t = t_end


@njit(cache=True)
def _lattice_count(t_in, t_out, n_hits, dt, jitter, counts):
    """counts[r]: the lattice samples t_k = (k + jitter[r])·dt[r] inside the intervals of ray r."""
    for r in range(t_in.shape[0]):
        m = 0
        for h in range(n_hits[r]):
            k = int(math.ceil(t_in[r, h] / dt[r] - jitter[r]))
            while (k + jitter[r]) * dt[r] < t_out[r, h]:
                if (k + jitter[r]) * dt[r] >= t_in[r, h]:
                    m += 1
                k += 1
        counts[r] = m


@njit(cache=True)
def _lattice_fill(t_in, t_out, n_hits, dt, jitter, start, o, d, z, ray, pts):
    """The samples `_lattice_count` counts, packed from start[r], with their ray and world point o + z d."""
    for r in range(t_in.shape[0]):
        m = start[r]
        for h in range(n_hits[r]):
            k = int(math.ceil(t_in[r, h] / dt[r] - jitter[r]))
            while (k + jitter[r]) * dt[r] < t_out[r, h]:
                t = (k + jitter[r]) * dt[r]
                if t >= t_in[r, h]:
                    z[m] = t
                    ray[m] = r
                    for a in range(3):
                        pts[m, a] = o[r, a] + t * d[r, a]
                    m += 1
                k += 1


def _lattice(grid: VoxelGrid, origins: Tensor, dirs: Tensor, step: float, max_hits: int, t_max: float,
             generator: torch.Generator | None) -> tuple[np.ndarray, ...]:
    """The lattice samples of each ray inside its hit voxels, packed: z (N,) float64, ray (N,), start (R + 1,),
    points (N, 3) float32 and the rays' merged hit intervals n_hits (R,); the lattice offset u ~ U(0, 1) per ray from
    `generator` (None: u = 0.5)."""
    t_in, t_out, n = voxel_hits(grid, origins, dirs, max_hits, t_max)
    R = origins.shape[0]
    dt = (step / dirs.detach().double().norm(dim=1)).cpu().numpy()
    u = (torch.rand(R, generator=generator, dtype=torch.float64).numpy() if generator is not None
         else np.full(R, 0.5))
    counts = np.zeros(R, np.int64)
    _lattice_count(t_in, t_out, n, dt, u, counts)
    start = np.zeros(R + 1, np.int64)
    np.cumsum(counts, out=start[1:])
    N = int(start[-1])
    z, ray, pts = np.zeros(N), np.zeros(N, np.int64), np.zeros((N, 3), np.float32)
    _lattice_fill(t_in, t_out, n, dt, u, start, origins.detach().double().cpu().numpy(),
                  dirs.detach().double().cpu().numpy(), z, ray, pts)
    return z, ray, start, pts, n


def sample_in_voxels(grid: VoxelGrid, origins: Tensor, dirs: Tensor, step: float, max_hits: int, t_max: float,
                     generator: torch.Generator | None = None) -> RaySamples:
    """Samples every `step` metres along each ray, inside its first `max_hits` allocated voxels only.

    Args: origins, dirs (R, 3) world (t = z-depth); step metres; generator: per-ray lattice offset u ~ U(0, 1)
        (None: u = 0.5, deterministic).
    Returns: RaySamples with S = the most samples any ray has (at least 1): `packed_samples_in_voxels`' samples,
    padded.

    Example: a ray along +z from z = 0 through allocated voxels [0.3, 0.4) m, step 0.01, u = 0.5 ->
    z = 0.305, 0.315, ..., 0.395 (10 samples).
    """
    z, ray, start, _, n = _lattice(grid, origins, dirs, step, max_hits, t_max, generator)
    R = origins.shape[0]
    counts = start[1:] - start[:-1]
    S = max(1, int(counts.max(initial=0)))
    col = np.arange(z.shape[0]) - start[ray]
    valid = np.zeros((R, S), dtype=np.bool_)
    valid[ray, col] = True
    last = np.where(counts > 0, z[np.maximum(start[1:] - 1, 0)] if z.shape[0] else 0.0, 0.0)
    zp = np.repeat(last[:, None], S, axis=1)  # padding repeats the ray's last sample (0 without any)
    zp[ray, col] = z
    dev = origins.device
    return RaySamples(torch.from_numpy(zp).to(dev, torch.float32), torch.from_numpy(valid).to(dev),
                      torch.from_numpy(n).to(dev))


def packed_samples_in_voxels(grid: VoxelGrid, origins: Tensor, dirs: Tensor, step: float, max_hits: int,
                             t_max: float, generator: torch.Generator | None = None) -> PackedSamples:
    """`sample_in_voxels`' valid samples, packed in ray order (the same samples for the same generator state),
    with their world points: what mapping needs, without the (R, S) padding."""
    z, ray, start, pts, _ = _lattice(grid, origins, dirs, step, max_hits, t_max, generator)
    dev = origins.device
    return PackedSamples(torch.from_numpy(z).to(dev, torch.float32), torch.from_numpy(ray).to(dev),
                         torch.from_numpy(start).to(dev), torch.from_numpy(pts).to(dev))
