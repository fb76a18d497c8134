"""Photometric refinement of a pose: direct image alignment of the current frame onto a reference keyframe (torch,
float64, CPU; no I/O).

Each reference pixel p with depth z and an intensity gradient above a threshold is back-projected, X_k = z K^-1 p,
moved into the current camera by the relative pose T_ik (reference camera -> current camera), X_i = T_ik X_k, and
projected; its residual is the intensity difference

    r_p(T_ik) = I_i(pi(X_i)) - I_k(p)                       (I: grey level in [0, 1], bilinear)

Under a left increment T_ik <- exp(xi) T_ik, xi = (rho, omega), dX_i/dxi = [I | -[X_i]_x], so

    dr_p/dxi = grad I_i(pi(X_i)) . dpi/dX (X_i) . [I | -[X_i]_x],
    dpi/dX = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]

Gauss-Newton with Huber weights solves (J^T W J) xi = -J^T W r, coarse to fine over an image pyramid (each level
halves the image), and stops on a small step. This is dense visual odometry (Steinbruecker et al. 2011, Kerl et al.
2013). A textured wall constrains the sliding that leaves depth-only registration degenerate, and the depth only
enters through the parallax, so noisy depth hurts it far less than it hurts registration (docs/accurate.md).
Optionally (`depth_weight`) each point also has a depth residual, D_i(pi(X_i)) - z_i (`depth_residuals`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from inrslam.geometry.se3 import se3_exp

LUMA = (0.299, 0.587, 0.114)


@dataclass
class PhotoLevel:
    """One pyramid level: grey image, its central-difference gradients and depth, all (H, W) float64; pinhole
    (fx, fy, cx, cy) in this level's pixels; for the depth residual (`depth_residuals`) the depth's stack (4, H, W)
    of `depth_stack`, made on first use."""

    gray: Tensor
    grad_u: Tensor
    grad_v: Tensor
    depth: Tensor
    K: tuple[float, float, float, float]
    depth_stack: Tensor | None = None


@dataclass
class PhotoResult:
    """Result of `align_photometric`."""

    T_ik: Tensor  # (4, 4) float64 refined reference camera -> current camera
    iters: int  # Gauss-Newton steps over all levels
    n_points: int  # reference pixels used at the finest level
    rms: float  # Huber-weighted RMS intensity residual at the finest level (nan if none)
    fallback: str | None  # "photo_few_points" / "photo_nan" (input pose kept), or None
    light: tuple[float, float] | None = None  # affine brightness (alpha, beta) (slam.photo.affine_light)
    n_depth: int | None = None  # valid depth residuals of the first reference, finest level (slam.photo.depth_weight)


def grey(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) colour in [0, 1] -> (H, W) float64 grey level (ITU-R 601 luma weights `LUMA`)."""
    return np.asarray(rgb, dtype=np.float64) @ np.asarray(LUMA)


def _gradients(img: Tensor) -> tuple[Tensor, Tensor]:
    """Central differences (H, W) along u and v; 0 on the border."""
    gu, gv = torch.zeros_like(img), torch.zeros_like(img)
    gu[:, 1:-1] = 0.5 * (img[:, 2:] - img[:, :-2])
    gv[1:-1] = 0.5 * (img[2:] - img[:-2])
    return gu, gv


def _half(img: Tensor) -> Tensor:
    """2x2 box average (odd sizes drop the last row / column)."""
    H, W = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
    i = img[:H, :W]
    return 0.25 * (i[0::2, 0::2] + i[1::2, 0::2] + i[0::2, 1::2] + i[1::2, 1::2])


def _half_depth(d: Tensor) -> Tensor:
    """2x2 average of depth where all four are valid, else 0 (a block across an edge or a hole is invalid)."""
    H, W = d.shape[0] // 2 * 2, d.shape[1] // 2 * 2
    i = d[:H, :W]
    blocks = torch.stack([i[0::2, 0::2], i[1::2, 0::2], i[0::2, 1::2], i[1::2, 1::2]])
    return torch.where((blocks > 0).all(dim=0), blocks.mean(dim=0), torch.zeros_like(blocks[0]))


DEPTH_EDGE = 0.05  # a depth step above this fraction of the depth between neighbouring pixels is an edge


def depth_stack(d: Tensor, edge: float = DEPTH_EDGE) -> Tensor:
    """(H, W) depth in metres (0 = invalid) -> (4, H, W): depth, central differences along u and v, and a validity
    map, 1 where the pixel and its four neighbours have depth and no neighbour differs from it by more than `edge` x
    its depth (a bilinear sample of the map is 1 only between four such pixels); 0 on the border."""
    ok = torch.zeros_like(d, dtype=torch.bool)
    c = d[1:-1, 1:-1]
    inner = c > 0
    for n in (d[1:-1, 2:], d[1:-1, :-2], d[2:, 1:-1], d[:-2, 1:-1]):
        inner &= (n > 0) & ((n - c).abs() <= edge * c)
    ok[1:-1, 1:-1] = inner
    du, dv = _gradients(d)
    zero = torch.zeros_like(d)
    return torch.stack([torch.where(ok, d, zero), torch.where(ok, du, zero), torch.where(ok, dv, zero), ok.to(d.dtype)])


def build_pyramid(rgb: np.ndarray, depth: np.ndarray, K: tuple[float, float, float, float],
                  levels: int) -> list[PhotoLevel]:
    """(H, W, 3) colour in [0, 1] and (H, W) depth in metres (0 = invalid) -> `levels` levels, finest first.
    A level's intrinsics: f / 2 and (c + 0.5) / 2 - 0.5 (pixel centres at integers)."""
    g = torch.as_tensor(grey(rgb))
    d = torch.as_tensor(np.asarray(depth, dtype=np.float64))
    d = torch.where(torch.isfinite(d) & (d > 0), d, torch.zeros_like(d))
    fx, fy, cx, cy = (float(v) for v in K)
    out = []
    for lvl in range(levels):
        if lvl:
            g, d = _half(g), _half_depth(d)
            fx, fy, cx, cy = fx / 2, fy / 2, (cx + 0.5) / 2 - 0.5, (cy + 0.5) / 2 - 0.5
        out.append(PhotoLevel(g, *_gradients(g), d, (fx, fy, cx, cy)))
    return out


def _sample(stack: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Bilinear samples (C, N) of a (C, H, W) stack at pixel coordinates u, v (N,)."""
    H, W = stack.shape[-2:]
    grid = torch.stack([2 * u / (W - 1) - 1, 2 * v / (H - 1) - 1], dim=-1)[None, None]
    return F.grid_sample(stack[None], grid, mode="bilinear", align_corners=True)[0, :, 0]


def reference_points(level: PhotoLevel, grad_threshold: float, max_points: int,
                     generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """Informative reference pixels: valid depth and |grad I| > grad_threshold, at most `max_points` (a random
    subset). Returns X_k (N, 3) camera-frame points in metres and their intensities (N,)."""
    mag = torch.hypot(level.grad_u, level.grad_v)
    v, u = torch.nonzero((level.depth > 0) & (mag > grad_threshold), as_tuple=True)
    if v.numel() > max_points:
        keep = torch.randperm(v.numel(), generator=generator)[:max_points]
        v, u = v[keep], u[keep]
    fx, fy, cx, cy = level.K
    z = level.depth[v, u]
    X = torch.stack([(u.double() - cx) / fx * z, (v.double() - cy) / fy * z, z], dim=-1)
    return X, level.gray[v, u]


def _moved(cur: PhotoLevel, X_k: Tensor, T_ik: Tensor, border: int, stack: Tensor
           ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Points X_k (N, 3) moved by T_ik into the current camera: X (N, 3), their depth zs (N,) (1 where not in front),
    the bilinear samples (C, N) of a (C, H, W) `stack` of the current level where they project, and a validity mask
    (N,): in front of the camera and inside the image less `border` pixels."""
    H, W = stack.shape[-2:]
    fx, fy, cx, cy = cur.K
    X = X_k @ T_ik[:3, :3].T + T_ik[:3, 3]
    x, y, z = X.unbind(-1)
    zs = torch.where(z > 1e-6, z, torch.ones_like(z))
    u, v = fx * x / zs + cx, fy * y / zs + cy
    valid = (z > 1e-6) & (u >= border) & (u <= W - 1 - border) & (v >= border) & (v <= H - 1 - border)
    return X, zs, _sample(stack, u.clamp(0, W - 1), v.clamp(0, H - 1)), valid


def _jacobian(cur: PhotoLevel, X: Tensor, zs: Tensor, grad_u: Tensor, grad_v: Tensor, dz: float) -> Tensor:
    """J (N, 6) of a residual f(pi(X)) - dz * z under a left twist of the pose: with the sampled image gradient
    (grad_u, grad_v) (N,), g = grad f . dpi/dX - dz e_z (N, 3) and J = g [I | -[X]_x] = (g, X x g)."""
    fx, fy = cur.K[0], cur.K[1]
    x, y, _ = X.unbind(-1)
    gu, gv = grad_u * fx / zs, grad_v * fy / zs
    gz = -(gu * x + gv * y) / zs
    g = torch.stack([gu, gv, gz - dz], dim=-1)  # (x - 0.0 is x bit for bit: the intensity residual's J unchanged)
    return torch.cat([g, torch.linalg.cross(X, g)], dim=-1)


def photometric_residuals(cur: PhotoLevel, X_k: Tensor, I_k: Tensor, T_ik: Tensor,
                          border: int = 1) -> tuple[Tensor, Tensor, Tensor]:
    """Residuals r (N,), Jacobians J (N, 6) w.r.t. a left twist (rho, omega) of T_ik, and a validity mask (N,)
    (in front of the camera, projecting inside the image less `border` pixels); see the module docstring."""
    X, zs, s, valid = _moved(cur, X_k, T_ik, border, torch.stack([cur.gray, cur.grad_u, cur.grad_v]))
    r = s[0] - I_k
    J = _jacobian(cur, X, zs, s[1], s[2], 0.0)
    return torch.where(valid, r, torch.zeros_like(r)), J * valid[:, None], valid


def depth_residuals(cur: PhotoLevel, X_k: Tensor, T_ik: Tensor, border: int = 1) -> tuple[Tensor, Tensor, Tensor]:
    """Depth residuals r (N,) = D_i(pi(X_i)) - z_i in metres (the current frame's depth where the moved point lands,
    bilinear, against the point's own depth), their Jacobians J (N, 6) w.r.t. a left twist (rho, omega) of T_ik, and
    a validity mask (N,) (in front, inside the image, between four pixels with depth and no depth edge). With
    G = grad D . dpi/dX - e_z (N, 3), dr/dxi = (G, X_i x G), as for `photometric_residuals`. Example: a wall at
    z = 2 m facing the camera, a point at 1.99 m: r = +1 cm, dr/drho = (0, 0, -1)."""
    if cur.depth_stack is None:
        cur.depth_stack = depth_stack(cur.depth)
    X, zs, s, valid = _moved(cur, X_k, T_ik, border, cur.depth_stack)
    valid = valid & (s[3] > 1.0 - 1e-9)
    r = s[0] - X[:, 2]
    J = _jacobian(cur, X, zs, s[1], s[2], 1.0)
    return torch.where(valid, r, torch.zeros_like(r)), J * valid[:, None], valid


def depth_block(cur: PhotoLevel, X_k: Tensor, T_ik: Tensor, scale: float) -> tuple[Tensor, Tensor, int] | None:
    """The depth residuals' normal equations (H (6, 6), b (6,)) and their count for `align_photometric`, each
    residual weighted as an intensity residual of the same standard score: Huber at 1.345 sigma_d, sigma_d = 1.4826
    x the median |r| (a robust standard deviation, this step's), times `scale` / sigma_d^2 (`scale`: depth_weight x
    the intensity residuals' variance). None with fewer than 6 valid residuals."""
    r, J, valid = depth_residuals(cur, X_k, T_ik)
    n = int(valid.sum())
    if n < 6:
        return None
    sigma = max(1.4826 * float(r[valid].abs().median()), 1e-5)
    w = huber_weights(r, valid, 1.345 * sigma) * (scale / sigma ** 2)
    return (J * w[:, None]).T @ J, (J * w[:, None]).T @ r, n


def twist_small(D: Tensor) -> Tensor:
    """First-order twist (rho, omega) of a near-identity pose D (4, 4): rho = t, omega = vee((R - R^T) / 2); exact
    to first order in the angle (se3_exp(xi) -> xi + O(|xi|^2))."""
    R = D[:3, :3]
    omega = 0.5 * torch.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return torch.cat([D[:3, 3], omega])


def huber_weights(r: Tensor, valid: Tensor, huber: float) -> Tensor:
    """IRLS weights (N,) of residuals r (N,) under a Huber loss of threshold `huber`: 1 where |r| <= huber, else
    huber / |r|; 0 where not `valid`. Example: huber 0.05, r = 0.1 -> 0.5."""
    a = r.abs()
    return torch.where(a <= huber, torch.ones_like(a), huber / a.clamp_min(1e-12)) * valid


def align_photometric(ref: list[PhotoLevel], cur: list[PhotoLevel], T_ik: Tensor, cfg,
                      generator: torch.Generator | None = None,
                      prior: tuple[Tensor, Tensor, float] | None = None,
                      others: list[tuple[list[PhotoLevel], Tensor]] | None = None) -> PhotoResult:
    """Coarse-to-fine Gauss-Newton of T_ik (reference camera -> current camera, (4, 4)) on the photometric residuals.

    With a `prior` (T_p (4, 4), its information Lambda (6, 6) in the left twist of T_ik, weight lam) the cost gains
    lam/2 e^T Lambda e, e = twist of T T_p^-1 (`twist_small`): per step, with the photometric residuals scaled by
    their own variance (the current weighted RMS^2), (H + lam rms^2 Lambda) xi = -(b + lam rms^2 Lambda e). It pulls
    the pose towards T_p where that is well constrained and leaves it free where it is not (a degenerate view).
    With `cfg.affine_light` the reference's intensities are (1 + alpha) I_k + beta, alpha and beta solved with the
    twist (8 unknowns; dr/dalpha = -I_k, dr/dbeta = -1): an exposure change is not read as motion.
    `others`, pairs (pyramid, T_ij) of more references j (older keyframes; T_ij: camera j -> current camera), add
    their residuals to the same steps: a left twist of T_ik is a left twist of the current camera's world -> camera
    pose, so every T_ij takes the same update (slam.photo.track_refs). `rms` and the point count stay the first
    reference's. With `cfg.depth_weight` > 0 every reference point also has a depth residual (`depth_residuals`,
    `depth_block`), the current frame's depth where it lands against its own, as in dense RGB-D odometry (Kerl et
    al. 2013), weighted by its robust scale so that 1 weighs it as an intensity residual.

    Args:
        ref, cur: pyramids of the reference keyframe (with depth) and the current frame (`build_pyramid`).
        cfg: `PhotoConfig` (iters, grad_threshold, max_points, huber, min_points, tol); a level needs
            min_points / 4^level valid residuals (level 0 = finest).
    """
    start = T_ik.detach().to(torch.float64).clone()
    T = start.clone()
    light = torch.zeros(2, dtype=torch.float64)  # (alpha, beta): I_k is seen as (1 + alpha) I_k + beta
    n_par = 8 if getattr(cfg, "affine_light", False) else 6
    depth_weight = float(getattr(cfg, "depth_weight", 0.0))
    more = [(pyr, T_j.detach().to(torch.float64).clone()) for pyr, T_j in (others or [])]
    total, n_used, rms, n_depth = 0, 0, float("nan"), None
    for lvl in reversed(range(len(ref))):
        X_k, I_k = reference_points(ref[lvl], cfg.grad_threshold, cfg.max_points, generator)
        X_more = [reference_points(pyr[lvl], cfg.grad_threshold, cfg.max_points, generator) for pyr, _ in more]
        for _ in range(cfg.iters):
            r, J, valid = photometric_residuals(cur[lvl], X_k, I_k, T)
            n_used = int(valid.sum())
            if n_used < cfg.min_points / 4 ** lvl:
                return PhotoResult(start, total, n_used, rms, "photo_few_points")
            if n_par == 8:  # affine brightness: r = I_i(pi(X_i)) - (1 + alpha) I_k - beta
                r = (r - light[0] * I_k - light[1]) * valid
                J = torch.cat([J, -I_k[:, None] * valid[:, None], -valid[:, None].to(J.dtype)], dim=1)
            w = huber_weights(r, valid, cfg.huber)
            H = (J * w[:, None]).T @ J
            b = (J * w[:, None]).T @ r
            rms = float(torch.sqrt((w * r * r).sum() / w.sum().clamp_min(1e-12)))
            for (X_j, I_j), (_, T_j) in zip(X_more, more):  # older references: the twist's block only
                r_j, J_j, valid_j = photometric_residuals(cur[lvl], X_j, I_j, T_j)
                w_j = huber_weights(r_j, valid_j, cfg.huber)
                H[:6, :6] = H[:6, :6] + (J_j * w_j[:, None]).T @ J_j
                b[:6] = b[:6] + (J_j * w_j[:, None]).T @ r_j
            if depth_weight > 0:  # the same reference points' depth residuals (slam.photo.depth_weight)
                pairs = [(X_k, T), *((X_j, T_j) for (X_j, _), (_, T_j) in zip(X_more, more))]
                blocks = [depth_block(cur[lvl], X_j, T_j, depth_weight * rms * rms) for X_j, T_j in pairs]
                n_depth = 0 if blocks[0] is None else blocks[0][2]
                for blk in blocks:
                    if blk is not None:
                        H[:6, :6] = H[:6, :6] + blk[0]
                        b[:6] = b[:6] + blk[1]
            total += 1
            if prior is not None:
                T_p, info, lam = prior
                L = (lam * rms * rms) * info
                H[:6, :6] = H[:6, :6] + L
                b[:6] = b[:6] + L @ twist_small(T @ torch.linalg.inv(T_p))
            try:
                step = -torch.linalg.solve(H + 1e-9 * torch.diagonal(H).mean() * torch.eye(n_par, dtype=H.dtype), b)
            except torch.linalg.LinAlgError:  # no intensity gradient where the points land: nothing constrained
                step = torch.full((n_par,), float("nan"), dtype=H.dtype)
            if not bool(torch.isfinite(step).all()):
                return PhotoResult(start, total, n_used, rms, "photo_nan")
            xi = step[:6]
            T = se3_exp(xi) @ T
            more = [(pyr, se3_exp(xi) @ T_j) for pyr, T_j in more]
            if n_par == 8:
                light = light + step[6:]
            if float(xi.norm()) < cfg.tol:
                break
    return PhotoResult(T, total, n_used, rms, None, (float(light[0]), float(light[1])) if n_par == 8 else None,
                       n_depth)


def step_bound(recent: list[float], weak: bool, cfg) -> float:
    """How far (metres) a photometric refinement may move the pose it started from: `cfg.weak_max_step` when the
    geometric pose is weak (GICP failed or its view is near-degenerate), else max(`cfg.max_step`,
    `cfg.jump_factor` x median of `recent`, the moves of the last accepted refinements). Example: max_step 1 cm,
    factor 4, recent moves of 5 mm -> 2 cm."""
    if weak:
        return cfg.weak_max_step
    return max(cfg.max_step, cfg.jump_factor * float(np.median(recent)) if recent else 0.0)


def jump_kept(rms: float, level: float, cfg) -> bool:
    """Whether a refinement that moved its pose beyond `step_bound` stands anyway: `cfg.jump_rms_factor` > 0 and its
    residual RMS is at most that factor x `level`, the RMS of the first refinement onto the same keyframe (> 0):
    the image is explained as well as usual, so the geometric pose is the one that is off. Example: factor 1.5,
    level 0.02 -> kept up to RMS 0.03; never with level 0 (no refinement onto this keyframe yet)."""
    return cfg.jump_rms_factor > 0 and level > 0 and math.isfinite(rms) and rms <= cfg.jump_rms_factor * level
