"""Alpha compositing of per-sample colours and depths with weights from a rendering function G."""

from __future__ import annotations

from torch import Tensor


def composite(weights: Tensor, rgb: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Weighted sums along each ray, no background colour and no normalisation by Σw (docs/spec.md §4).

    Ĉ = Σ_i w_i c_i,  D̂ = Σ_i w_i z_i,  O = Σ_i w_i,  Var = Σ_i w_i (z_i - D̂)².

    Args:
        weights: (R, S) weights >= 0.
        rgb: (R, S, 3) per-sample colour in [0, 1].
        z: (R, S) sample z-depths, metres.
    Returns:
        rgb (R, 3), depth (R,) metres (z-depth), opacity (R,), depth_var (R,) m².

    Example: w = [[0.25, 0.75]], z = [[1, 2]] -> depth 1.75, opacity 1, depth_var 0.1875.
    """
    out_rgb = (weights[..., None] * rgb).sum(dim=-2)
    depth = (weights * z).sum(dim=-1)
    opacity = weights.sum(dim=-1)
    depth_var = (weights * (z - depth[..., None]) ** 2).sum(dim=-1)
    return out_rgb, depth, opacity, depth_var
