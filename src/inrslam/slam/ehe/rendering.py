"""Rendering of EHE ray samples (docs/ehe.md §3): the field only at valid samples (inside hit voxels), SDF(direct)
weights restricted to them, then compositing."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from inrslam.rendering.functional import bell_weights, first_surface_mask
from inrslam.slam.ehe.raymarch import PackedSamples


class EheRender(NamedTuple):
    """rgb (R, 3), depth (R,) metres (z-depth), hit (R,) bool (the ray has samples); then the N samples, packed in
    ray order: sdf (N,) T-units, z (N,) metres, ray (N,) int64 (the ray of each sample), weights (N,); start (R + 1,)
    int64 the offset of each ray's samples."""

    rgb: Tensor
    depth: Tensor
    hit: Tensor
    sdf: Tensor
    z: Tensor
    ray: Tensor
    weights: Tensor
    start: Tensor

    def padded(self, values: Tensor) -> Tensor:
        """Packed per-sample values (N,) -> (R, S) with S the most samples of a ray (at least 1), each row's padding
        repeating its last value (0 if none): the layout `first_crossing` and `masked_direct_weights` read."""
        R = self.hit.shape[0]
        counts = self.start[1:] - self.start[:-1]
        S = max(1, int(counts.max())) if R else 1
        col = torch.arange(values.shape[0], device=values.device) - self.start[self.ray]
        out = values.new_zeros(R, S).index_put((self.ray, col), values)
        return fill_padding(out, torch.arange(S, device=values.device) < counts[:, None])  # samples lead each row


def fill_padding(values: Tensor, valid: Tensor) -> Tensor:
    """(R, S) values whose valid samples lead each row -> padding replaced by the row's last valid value (0 if
    none). Example: [[1, 2, 9]] with valid [[T, T, F]] -> [[1, 2, 2]]."""
    last = (valid.sum(dim=1, keepdim=True) - 1).clamp_min(0)
    return torch.where(valid, values, values.gather(1, last))


def masked_direct_weights(sdf: Tensor, z: Tensor, valid: Tensor, truncation: float) -> Tensor:
    """SDF(direct) weights over the valid samples only (docs/spec.md §4.1 restricted to `valid`):

    w_i = ŵ_i m_i v_i / (Σ_j ŵ_j m_j v_j + 1e-8),  ŵ_i = σ(s_i/T) σ(−s_i/T),  m_i = 1[z_i < z_k + T]
    with k the first sign change of s over the valid samples (all samples kept when there is none).

    Args: sdf (R, S) T-units, padding = last valid value (`fill_padding`); z (R, S) metres; valid (R, S) bool.
    Returns: (R, S) weights; rows with a valid sample sum to 1, others are 0.
    """
    m = first_surface_mask(sdf.detach(), z, truncation, no_crossing_keeps_all=True)
    w = bell_weights(sdf, truncation) * m * valid
    return w / (w.sum(dim=-1, keepdim=True) + 1e-8)


def packed_direct_weights(sdf: Tensor, z: Tensor, ray: Tensor, n_rays: int, truncation: float) -> Tensor:
    """`masked_direct_weights` on packed samples (sdf, z (N,) in ray order, ray (N,) sorted), (N,) weights.

    Same rule: the first sign change k of each ray's samples (between two consecutive samples of that ray),
    m_i = 1[z_i < z_k + T] (every sample when the ray has none), w_i = ŵ_i m_i / (Σ_j ŵ_j m_j + 1e-8) per ray.
    """
    N = sdf.numel()
    pos = sdf.detach() > 0
    change = (pos[1:] != pos[:-1]) & (ray[1:] == ray[:-1])  # (N-1,): a crossing between samples j and j+1
    j = torch.nonzero(change).reshape(-1)
    first = torch.full((n_rays,), N, dtype=torch.int64, device=sdf.device)
    first = first.scatter_reduce(0, ray[j], j, "amin")  # N: no crossing
    z_k = torch.cat([z, z.new_full((1,), float("inf"))])[first]  # inf: keep every sample
    w = bell_weights(sdf, truncation) * (z.double() < z_k[ray].double() + truncation)  # z_k + T in float64 (kernel)
    total = torch.zeros(n_rays, dtype=w.dtype, device=w.device).index_add(0, ray, w)
    return w / (total[ray] + 1e-8)


# samples whose normalised weight is below this get no colour query: their share of Ĉ is < 1e-6 each
COLOR_MIN_WEIGHT = 1e-6


def render_samples(field, origins: Tensor, dirs: Tensor, samples: PackedSamples, truncation: float) -> EheRender:
    """Query `field` (an `EheField`) at the samples o + z d and composite Ĉ = Σ w c, D̂ = Σ w z.

    The SDF is evaluated at every sample; the colour decoder only where w > COLOR_MIN_WEIGHT (the bell weights
    σ(s/T)σ(−s/T) vanish a few centimetres from the surface, so most samples cannot change Ĉ; the skipped ones
    change it by less than 1e-6 each). Args: origins, dirs (R, 3) world; samples from `packed_samples_in_voxels`.
    """
    z, ray, start, pts = samples
    R = origins.shape[0]
    p, f = field.encode(pts)
    sdf = field.sdf_from(pts, p, f)
    w = packed_direct_weights(sdf, z, ray, R, truncation)
    use = torch.nonzero(w.detach() > COLOR_MIN_WEIGHT).reshape(-1)
    rgb_s = torch.sigmoid(field.rgb_from(p[use], f[use]))
    rgb = torch.zeros(R, 3, dtype=z.dtype, device=z.device).index_add(0, ray[use], w[use, None] * rgb_s)
    depth = torch.zeros(R, dtype=z.dtype, device=z.device).index_add(0, ray, w * z)
    return EheRender(rgb, depth, start[1:] > start[:-1], sdf, z, ray, w, start)
