"""Rendering of EHE ray samples (docs/ehe.md §3): the field only at valid samples (inside hit voxels), SDF(direct)
weights restricted to them, then compositing."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from inrslam.rendering.functional import bell_weights, first_surface_mask
from inrslam.slam.ehe.raymarch import RaySamples


class EheRender(NamedTuple):
    """rgb (R, 3), depth (R,) metres (z-depth), hit (R,) bool (the ray has samples), sdf (R, S) T-units
    (padding repeats the last valid value), z (R, S) metres, valid (R, S) bool, weights (R, S)."""

    rgb: Tensor
    depth: Tensor
    hit: Tensor
    sdf: Tensor
    z: Tensor
    valid: Tensor
    weights: Tensor


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


# samples whose normalised weight is below this get no colour query: their share of Ĉ is < 1e-6 each
COLOR_MIN_WEIGHT = 1e-6


def render_samples(field, origins: Tensor, dirs: Tensor, samples: RaySamples, truncation: float) -> EheRender:
    """Query `field` (an `EheField`) at the valid samples o + z d and composite Ĉ = Σ w c, D̂ = Σ w z.

    The SDF is evaluated at every valid sample; the colour decoder only where w > COLOR_MIN_WEIGHT (the bell
    weights σ(s/T)σ(−s/T) vanish a few centimetres from the surface, so most samples cannot change Ĉ; the
    skipped ones change it by less than 1e-6 each). Args: origins, dirs (R, 3) world; samples from
    `sample_in_voxels`.
    """
    z, valid = samples.z, samples.valid
    R, S = z.shape
    pts = (origins[:, None, :] + z[..., None] * dirs[:, None, :])[valid]
    p, f = field.encode(pts)
    sdf = torch.zeros(R, S, dtype=z.dtype, device=z.device).masked_scatter(valid, field.sdf_from(pts, p, f))
    sdf = fill_padding(sdf, valid)
    w = masked_direct_weights(sdf, z, valid, truncation)
    use = w[valid].detach() > COLOR_MIN_WEIGHT
    where = torch.nonzero(valid)[use]
    rgb_s = torch.sigmoid(field.rgb_from(p[use], f[use]))
    rgb = torch.zeros(R, 3, dtype=z.dtype, device=z.device).index_add(0, where[:, 0],
                                                                       w[where[:, 0], where[:, 1], None] * rgb_s)
    depth = (w * z).sum(dim=-1)
    return EheRender(rgb, depth, valid.any(dim=1), sdf, z, valid, w)
