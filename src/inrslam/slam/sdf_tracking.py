"""Point-to-surface tracking: align a frame's back-projected depth points to the zero level set of the map's SDF.

For points p_i (camera frame, metres) and a pose T = [R | t] (camera-to-world), the residual is the map's SDF at the
world point, in metres:

    r_i(T) = T_trunc * s(R p_i + t)          (s: the field's SDF in truncation units)

A left increment T <- exp(xi) T, xi = (rho, omega), moves x_i = R p_i + t to x_i + rho + omega x x_i, so

    dr_i / drho = g_i,   dr_i / domega = x_i x g_i,   g_i = T_trunc * grad s(x_i)   (one field query + backward).

Each Gauss-Newton (Levenberg-Marquardt) step solves (J^T W J + mu D) xi = -J^T W r with Huber weights
w_i = min(1, delta / |r_i|), using only points inside the band |s| < band where the field was trained as a distance.
This is the SDF tracking of Bylow et al. (RSS 2013) / KinectFusion-style frame-to-model alignment, on the neural map.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from inrslam.geometry.se3 import se3_exp


@dataclass
class SdfAlignResult:
    c2w: Tensor  # (4, 4) refined camera-to-world
    iters: int  # Gauss-Newton steps taken
    converged: bool  # stopped on a small step (not the iteration cap)
    n_used: int  # points inside the band at the last iteration
    rms: float  # robust-weighted RMS residual at the last iteration, metres (nan if no point)
    fallback: str | None  # "sdf_few_points" / "sdf_jump" / "sdf_nan" (input pose kept), or None


def sdf_residuals(field, c2w: Tensor, pts_cam: Tensor, truncation: float) -> tuple[Tensor, Tensor, Tensor]:
    """SDF of camera points placed by `c2w`.

    Args:
        field: a `Field` (``sdf(x (N,3) m) -> (N,)`` in truncation units).
        c2w: (4, 4); pts_cam: (N, 3) metres; truncation: metres per SDF unit.
    Returns:
        x (N, 3) world points, r (N,) metric SDF, g (N, 3) its spatial gradient.
    """
    x = (pts_cam @ c2w[:3, :3].T + c2w[:3, 3]).detach()
    x.requires_grad_(True)
    with torch.enable_grad():
        r = field.sdf(x) * truncation
        (g,) = torch.autograd.grad(r.sum(), x)
    return x.detach(), r.detach(), g


def gauss_newton_step(x: Tensor, r: Tensor, g: Tensor, huber: float, damping: float) -> tuple[Tensor, Tensor]:
    """One robust LM step for residuals r (N,) with spatial gradients g (N, 3) at world points x (N, 3).

    Returns: xi (6,) float64 twist (rho, omega) minimising sum_i w_i (r_i + J_i xi)^2 + mu |D xi|^2, and the weights
    w (N,). Example: points on the plane z = 0.01 with s = z (g = e_z) give xi = (0, 0, -0.01, 0, 0, 0).
    """
    r64, g64, x64 = r.double(), g.double(), x.double()
    J = torch.cat([g64, torch.linalg.cross(x64, g64)], dim=1)  # (N, 6)
    a = r64.abs()
    w = torch.where(a <= huber, torch.ones_like(a), huber / a.clamp_min(1e-12))
    H = (J * w[:, None]).T @ J
    b = (J * w[:, None]).T @ r64
    diag = torch.diagonal(H)
    mu = damping * diag.mean().clamp_min(1e-12)
    xi = -torch.linalg.solve(H + torch.diag(diag * damping + mu), b)
    return xi, w


def align_to_sdf(field, c2w: Tensor, pts_cam: Tensor, truncation: float, cfg) -> SdfAlignResult:
    """Gauss-Newton point-to-surface alignment from `c2w`; see the module docstring.

    Args:
        field: the map (its parameters are not changed); c2w: (4, 4) starting pose.
        pts_cam: (N, 3) camera-frame points of valid depth, metres.
        cfg: `SdfTrackConfig` (iters, huber, band, min_points, tol_trans, tol_rot, damping, max_step).
    """
    start = c2w.detach().clone()
    T = start.clone()
    band = cfg.band * truncation
    it, converged, n_used, rms = 0, False, 0, float("nan")
    for it in range(1, cfg.iters + 1):
        x, r, g = sdf_residuals(field, T, pts_cam, truncation)
        keep = (r.abs() < band) & torch.isfinite(r) & torch.isfinite(g).all(dim=1) & (g.norm(dim=1) > 0.1)
        n_used = int(keep.sum())
        if n_used < cfg.min_points:
            return SdfAlignResult(start, it - 1, False, n_used, rms, "sdf_few_points")
        xi, w = gauss_newton_step(x[keep], r[keep], g[keep], cfg.huber, cfg.damping)
        rms = float(torch.sqrt((w * r[keep].double() ** 2).sum() / w.sum()))
        if not bool(torch.isfinite(xi).all()):
            return SdfAlignResult(start, it, False, n_used, rms, "sdf_nan")
        T = (se3_exp(xi.to(T.dtype)) @ T).detach()
        if float(xi[:3].norm()) < cfg.tol_trans and float(xi[3:].norm()) < cfg.tol_rot:
            converged = True
            break
    if float(torch.linalg.norm(T[:3, 3] - start[:3, 3])) > cfg.max_step:
        return SdfAlignResult(start, it, converged, n_used, rms, "sdf_jump")
    return SdfAlignResult(T, it, converged, n_used, rms, None)
