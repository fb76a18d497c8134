"""The EHE mapping objective (docs/ehe.md §4; H₂-Mapping's ScanNet weights)."""

from __future__ import annotations

import torch
from torch import Tensor

from inrslam.slam.ehe.config import EheConfig
from inrslam.slam.ehe.rendering import EheRender


def _mean(x: Tensor) -> Tensor:
    return x.mean() if x.numel() else x.new_zeros(())


def packed_sdf_terms(sdf: Tensor, z: Tensor, ray: Tensor, depth: Tensor, has_depth: Tensor,
                     truncation: float) -> tuple[Tensor, Tensor]:
    """Balanced free-space and SDF losses over the samples of rays with depth.

    front: z < D − T; band: |z − D| <= T (behind: unsupervised). With n_f, n_b the counts and N all samples of rays
    with depth, L_fs = (1 − n_f/(n_f+n_b)) · Σ_front (s − 1)² / N,   L_sdf = (1 − n_b/(n_f+n_b)) · Σ_band
    (z + s·T − D)² / N.

    Args: packed samples sdf (N,) T-units, z (N,) metres, ray (N,) int64 the ray of each; depth (R,) metres and
        has_depth (R,) bool per ray (samples of rays without depth are not counted); truncation T metres.
    Returns: (L_fs, L_sdf) 0-d tensors (0 when there are no samples).
    """
    D = depth[ray]
    sup = has_depth[ray]
    # compared as the fused kernel does (`fused_loss`): D - T in float64, |z - D| in z's dtype against T in float64,
    # and a sample in front is not also in the band (float32 thresholds alone leave a 1-ulp gap at z = D - T)
    front = sup & (z.double() < D.double() - truncation)
    band = sup & ~front & ((z - D).abs().double() <= truncation)
    n_f, n_b, n = front.sum(), band.sum(), sup.sum()
    if int(n) == 0 or int(n_f + n_b) == 0:
        zero = sdf.new_zeros(()) * sdf.sum()
        return zero, zero
    tot = (n_f + n_b).to(sdf.dtype)
    fs = torch.where(front, (sdf - 1.0) ** 2, 0.0).sum() / n
    sd = torch.where(band, (z + sdf * truncation - D) ** 2, 0.0).sum() / n
    return (1.0 - n_f / tot) * fs, (1.0 - n_b / tot) * sd


def sdf_terms(sdf: Tensor, z: Tensor, valid: Tensor, depth: Tensor, truncation: float) -> tuple[Tensor, Tensor]:
    """`packed_sdf_terms` of padded samples: sdf, z (R, S), valid (R, S) bool (False for rays without depth);
    depth (R,) metres."""
    R, S = sdf.shape
    slot = torch.nonzero(valid.reshape(-1)).reshape(-1)
    return packed_sdf_terms(sdf.reshape(-1)[slot], z.reshape(-1)[slot], torch.div(slot, S, rounding_mode="floor"),
                            depth, torch.ones(R, dtype=torch.bool, device=sdf.device), truncation)


def ehe_losses(out: EheRender, rgb: Tensor, depth: Tensor, cfg: EheConfig) -> dict[str, Tensor]:
    """Loss terms and 'total' = 5 L_rgb + 1 L_depth + 10 L_fs + 50000 L_sdf (weights from `cfg`).

    L_rgb = mean |Ĉ − C| over rays that hit a voxel; L_depth = mean |D̂ − D| over those with
    depth_min < D < depth_max; L_fs, L_sdf: `packed_sdf_terms` on the samples of the rays with depth.
    Also 'mse' (colour MSE, for PSNR) and 'depth_l1' (metres), both without gradient.
    Args: rgb (R, 3) in [0, 1]; depth (R,) metres (0 = none).
    """
    hit = out.hit
    has_d = hit & (depth > cfg.depth_min) & (depth < cfg.depth_max)
    l_rgb = _mean((out.rgb[hit] - rgb[hit]).abs())
    l_depth = _mean((out.depth[has_d] - depth[has_d]).abs())
    fs, sd = packed_sdf_terms(out.sdf, out.z, out.ray, depth, has_d, cfg.truncation)
    total = cfg.color_weight * l_rgb + cfg.depth_weight * l_depth + cfg.free_space_weight * fs + cfg.sdf_weight * sd
    with torch.no_grad():
        mse = _mean((out.rgb[hit] - rgb[hit]) ** 2)
    return {"total": total, "rgb": l_rgb, "depth": l_depth, "free_space": fs, "sdf": sd, "mse": mse,
            "depth_l1": l_depth.detach()}
