"""SE(3) helpers and pose parameterisations (torch, differentiable, device-agnostic; `_np` functions: numpy).

Quaternions are (w, x, y, z), scalar first, and need not be unit length: the rotation matrix uses the
factor 2/|q|^2 so the norm drops out (as the paper's code; the default pose parameterisation). The tangent-space
alternative (`se3_exp`, `slam.pose_param=se3`) is well-defined at zero rotation, unlike the original axis-angle
option (docs/spec.md §13.15).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def quat_to_matrix(q: Tensor) -> Tensor:
    """(..., 4) quaternion (w, x, y, z), any non-zero norm -> (..., 3, 3) rotation.

    R = I + 2/|q|^2 [[-(y²+z²), xy - wz, xz + wy], [xy + wz, -(x²+z²), yz - wx], [xz - wy, yz + wx, -(x²+y²)]]
    """
    w, x, y, z = q.unbind(-1)
    s = 2.0 / (q * q).sum(-1)
    R = torch.stack(
        [
            1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y),
            s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x),
            s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: Tensor) -> Tensor:
    """(..., 3, 3) rotation -> (..., 4) unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method)."""
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack(
        [
            torch.stack([1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                         m[..., 1, 0] - m[..., 0, 1]], -1),
            torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + 2 * m[..., 0, 0] - tr, m[..., 0, 1] + m[..., 1, 0],
                         m[..., 0, 2] + m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 + 2 * m[..., 1, 1] - tr,
                         m[..., 1, 2] + m[..., 2, 1]], -1),
            torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                         1 + 2 * m[..., 2, 2] - tr], -1),
        ],
        dim=-2,
    )  # (..., 4, 4): row k is 4 * q_k * q
    diag = torch.stack([1 + tr, 1 + 2 * m[..., 0, 0] - tr, 1 + 2 * m[..., 1, 1] - tr, 1 + 2 * m[..., 2, 2] - tr], -1)
    k = diag.argmax(-1, keepdim=True)
    q = torch.gather(cands, -2, k[..., None].expand(k.shape[:-1] + (1, 4))).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def skew(v: Tensor) -> Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrix [v]x."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(v.shape[:-1] + (3, 3))


def _one_minus_cos_over_theta2(theta2: Tensor, theta: Tensor) -> Tensor:
    """(1 - cos θ) / θ², smooth at 0. float64: a Taylor series below θ = 1e-4, the formula above. Other dtypes: the
    cancellation-free 0.5 (sin(θ/2) / (θ/2))² (in float32, 1 - cos θ loses every digit near θ = 1e-4: the formula
    gave 0 instead of 0.5 at θ = 1.5e-4)."""
    if theta2.dtype == torch.float64:
        return torch.where(theta2 < 1e-8, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    half = 0.5 * theta
    sinc_half = torch.where(theta2 < 1e-8, 1 - theta2 / 24, torch.sin(half) / half)
    return 0.5 * sinc_half * sinc_half


def _theta_minus_sin_over_theta3(theta2: Tensor, theta: Tensor) -> Tensor:
    """(θ - sin θ) / θ³, smooth at 0. float64: a Taylor series below θ = 1e-4. Other dtypes: the series to θ⁴ below
    θ = 0.5 (its truncation error, θ⁶ / 362880, is below float32's resolution there), the formula above."""
    if theta2.dtype == torch.float64:
        return torch.where(theta2 < 1e-8, 1.0 / 6 - theta2 / 120,
                           (theta - torch.sin(theta)) / (theta2 * theta).clamp_min(1e-36))
    series = 1.0 / 6 - theta2 / 120 + theta2 * theta2 / 5040
    return torch.where(theta2 < 0.25, series, (theta - torch.sin(theta)) / (theta2 * theta).clamp_min(1e-36))


def so3_exp(omega: Tensor) -> Tensor:
    """(..., 3) axis-angle -> (..., 3, 3) rotation (Rodrigues), smooth at 0 via Taylor series."""
    theta2 = (omega * omega).sum(-1, keepdim=True)[..., None]
    theta = theta2.clamp_min(1e-24).sqrt()
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = _one_minus_cos_over_theta2(theta2, theta)
    K = skew(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def se3_exp(xi: Tensor) -> Tensor:
    """(..., 6) twist (rho, omega) -> (..., 4, 4) SE(3) matrix; smooth at 0.

    T = [[R, V rho], [0, 1]], R = exp([omega]x), V = I + (1-cos θ)/θ² K + (θ - sin θ)/θ³ K².
    """
    rho, omega = xi[..., :3], xi[..., 3:]
    theta2 = (omega * omega).sum(-1, keepdim=True)[..., None]
    theta = theta2.clamp_min(1e-24).sqrt()
    b = _one_minus_cos_over_theta2(theta2, theta)
    c = _theta_minus_sin_over_theta3(theta2, theta)
    K = skew(omega)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(K.shape)
    R = so3_exp(omega)
    V = eye + b * K + c * (K @ K)
    t = (V @ rho[..., None])[..., 0]
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros(xi.shape[:-1] + (1, 4), dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def compose_qt(q: Tensor, t: Tensor) -> Tensor:
    """(..., 4) quaternion + (..., 3) translation -> (..., 4, 4) matrix."""
    R = quat_to_matrix(q)
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros(q.shape[:-1] + (1, 4), dtype=q.dtype, device=q.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def rotation_angle_deg(R: Tensor) -> Tensor:
    """(..., 3, 3) rotation -> (...,) angle in degrees, atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2): accurate near 0,
    where acos of the trace loses half the digits and reads a slightly non-orthonormal R as 0 or too large (the
    numpy twin is `inrslam.geometry.angles.rotation_angle_deg_np`)."""
    w = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    return torch.rad2deg(torch.atan2(0.5 * torch.linalg.vector_norm(w, dim=-1), 0.5 * (tr - 1)))


def mean_pose(poses: Tensor) -> Tensor:
    """(N, 4, 4) rigid poses -> (4, 4) their mean: the mean translation, and the rotation nearest (Frobenius) to the
    mean rotation matrix (the chordal L2 mean, by SVD; for nearby rotations the same as averaging their angles).

    Example: rotations of +a and -a about one axis with translations t and -t -> the identity.
    """
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] == 0:
        raise ValueError(f"mean_pose: expected (N >= 1, 4, 4) poses, got {tuple(poses.shape)}")
    U, _, Vh = torch.linalg.svd(poses[:, :3, :3].mean(dim=0))
    fix = torch.ones(3, dtype=poses.dtype, device=poses.device)
    fix[2] = torch.sign(torch.linalg.det(U @ Vh))
    out = torch.eye(4, dtype=poses.dtype, device=poses.device)
    out[:3, :3] = U @ torch.diag(fix) @ Vh
    out[:3, 3] = poses[:, :3, 3].mean(dim=0)
    return out


def nearest_rigid_np(T: np.ndarray) -> np.ndarray:
    """(4, 4) pose -> float64 copy whose rotation is the rotation nearest (Frobenius) to T's 3x3 block, by SVD
    (R = U diag(1, 1, det(U Vt)) Vt); translation and bottom row kept. Undoes the scale / shear a rotation gathers
    from products of rounded or extrapolated poses. Example: 1.001 x a rotation -> that rotation."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"nearest_rigid_np: expected a (4, 4) pose, got {T.shape}")
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))]) @ Vt
    return out
