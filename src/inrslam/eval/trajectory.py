"""Trajectory metrics: Umeyama/Horn alignment, timestamp association, ATE and RPE (pure numpy, no I/O).

Poses are camera-to-world (N, 4, 4) float64, metres, OpenCV axes (the axes do not matter for ATE/RPE as long as
both trajectories use the same ones). Frames whose pose is not finite (NaN/inf) are excluded and counted.

References:
    Sturm et al., "A Benchmark for the Evaluation of RGB-D SLAM Systems", IROS 2012 (ATE, RPE, association).
    Horn, "Closed-form solution of absolute orientation using unit quaternions", JOSA A 1987.
    Umeyama, "Least-squares estimation of transformation parameters between two point patterns", TPAMI 1991.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from inrslam.data.timestamps import associate  # noqa: F401 - re-exported: the evaluation's association
from inrslam.eval.config import Alignment
from inrslam.geometry.angles import rotation_angle_deg_np as rotation_angle_deg  # re-exported: benchmarks read it here

# ----------------------------------------------------------------------------------------------------------------
# alignment


def align_umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (or rigid) transform mapping `src` onto `dst`: dst_i ≈ s R src_i + t.

    Umeyama (1991), reflection-corrected:
        μx, μy = means;  Σ = (1/N) Σ_i (y_i − μy)(x_i − μx)ᵀ = U D Vᵀ (SVD)
        S = diag(1, 1, sign(det U · det V));   R = U S Vᵀ
        s = tr(D S) / σx²  with σx² = (1/N) Σ_i |x_i − μx|²   (s = 1 when `with_scale` is False)
        t = μy − s R μx
    Without scale this is Horn's (1987) closed-form absolute orientation.

    Args:
        src: (N, 3) points (e.g. estimated camera centres), metres.
        dst: (N, 3) corresponding points (e.g. ground-truth camera centres), metres.
        with_scale: also estimate the scale s (Sim(3)); otherwise s = 1 (SE(3)).
    Returns:
        R (3, 3) rotation (det +1), t (3,) metres, s scalar.
    Raises:
        ValueError for mismatched shapes, no points, or a zero-spread `src` with scale requested.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"align_umeyama: expected two (N, 3) arrays, got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n == 0:
        raise ValueError("align_umeyama: no points to align")
    mu_x, mu_y = src.mean(0), dst.mean(0)
    xc, yc = src - mu_x, dst - mu_y
    cov = yc.T @ xc / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    if with_scale:
        var_x = (xc * xc).sum() / n
        if var_x <= 0:
            raise ValueError("align_umeyama: source points have zero spread, scale is undefined")
        s = float(np.trace(np.diag(D) @ S) / var_x)
    else:
        s = 1.0
    t = mu_y - s * R @ mu_x
    return R, t, s


def sim3_matrix(R: np.ndarray, t: np.ndarray, s: float = 1.0) -> np.ndarray:
    """(4, 4) matrix [[s R, t], [0, 1]] acting on homogeneous points."""
    T = np.eye(4)
    T[:3, :3] = s * np.asarray(R)
    T[:3, 3] = t
    return T


# ----------------------------------------------------------------------------------------------------------------
# association


def associate_indices(idx_a: Sequence[int], idx_b: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Associate by frame index: positions (ia, ib) with idx_a[ia] == idx_b[ib], sorted by frame index.

    Duplicate frame indices keep their first occurrence.
    """
    a = np.asarray(idx_a, dtype=np.int64).ravel()
    b = np.asarray(idx_b, dtype=np.int64).ravel()
    _, ia, ib = np.intersect1d(a, b, assume_unique=False, return_indices=True)
    return ia.astype(np.int64), ib.astype(np.int64)


def select_frames(indices: Sequence[int], *trajectories: np.ndarray) -> tuple[np.ndarray, ...]:
    """Restrict trajectories (each (N, 4, 4) or (N, ...)) to the rows `indices` (e.g. keyframe indices).

    Raises ValueError for an index outside [0, N).
    """
    idx = np.asarray(indices, dtype=np.int64).ravel()
    out = []
    for traj in trajectories:
        traj = np.asarray(traj)
        if idx.size and (idx.min() < 0 or idx.max() >= traj.shape[0]):
            raise ValueError(f"select_frames: index out of range [0, {traj.shape[0]}): min {idx.min()}, "
                             f"max {idx.max()}")
        out.append(traj[idx])
    return tuple(out)


# ----------------------------------------------------------------------------------------------------------------
# metrics


def _stats(e: np.ndarray) -> dict:
    if e.size == 0:
        nan = float("nan")
        return {"rmse": nan, "mean": nan, "median": nan, "std": nan, "min": nan, "max": nan}
    return {
        "rmse": float(np.sqrt(np.mean(e * e))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
    }


def _check_poses(name: str, T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected (N, 4, 4) poses, got {T.shape}")
    return T


def _finite_rows(T: np.ndarray) -> np.ndarray:
    return np.isfinite(T.reshape(T.shape[0], -1)).all(1)


def ate(est_c2w: np.ndarray, gt_c2w: np.ndarray, align: Alignment | str = "se3") -> dict:
    """Absolute trajectory error (translational), after aligning the estimate to ground truth.

    With p_i, q_i the estimated / ground-truth camera centres of the used frames and (s, R, t) from
    `align_umeyama(p, q)` (SE(3): s = 1; Sim(3): s free; none: identity):
        e_i = | s R p_i + t − q_i |,      ATE_RMSE = sqrt( (1/N) Σ_i e_i² )     (Sturm et al. 2012)
    Only translations enter the error (as the TUM benchmark and the paper).

    Args:
        est_c2w: (N, 4, 4) estimated camera-to-world, metres.
        gt_c2w: (N, 4, 4) ground-truth camera-to-world of the same frames, metres; rows with any non-finite
            entry (missing GT) are excluded and counted, as are non-finite estimates.
        align: "se3" | "sim3" | "none" (or `Alignment`).
    Returns:
        dict with
            rmse, mean, median, std, min, max: metres (NaN when no frame is usable);
            n_used, n_excluded: frame counts (n_used + n_excluded = N);
            errors: (n_used,) per-frame errors, metres;  used: (N,) bool mask of the used frames;
            alignment: {"type", "R" (3,3), "t" (3,), "s", "T" (4,4) = [[sR, t], [0, 1]]}.
    """
    align = Alignment(align)
    est = _check_poses("ate est_c2w", est_c2w)
    gt = _check_poses("ate gt_c2w", gt_c2w)
    if est.shape[0] != gt.shape[0]:
        raise ValueError(f"ate: {est.shape[0]} estimated poses vs {gt.shape[0]} ground-truth poses (associate first)")
    used = _finite_rows(est) & _finite_rows(gt)
    p, q = est[used, :3, 3], gt[used, :3, 3]
    R, t, s = np.eye(3), np.zeros(3), 1.0
    if align is not Alignment.NONE and p.shape[0] > 0:
        with_scale = align is Alignment.SIM3 and p.shape[0] > 1
        R, t, s = align_umeyama(p, q, with_scale=with_scale)
    errors = np.linalg.norm((s * (R @ p.T)).T + t - q, axis=1)
    out = _stats(errors)
    out.update(
        n_used=int(used.sum()),
        n_excluded=int((~used).sum()),
        errors=errors,
        used=used,
        alignment={"type": align.value, "R": R, "t": t, "s": float(s), "T": sim3_matrix(R, t, s)},
    )
    return out


def drift_per_100(est_c2w: np.ndarray, gt_c2w: np.ndarray) -> dict:
    """Growth of the *unaligned* position error: both trajectories expressed relative to their first usable frame,

        e_i = | p_i - q_i |  with  p = (est_0^-1 est_i).t,  q = (gt_0^-1 gt_i).t,
        drift = 100 * (sum_i k_i e_i) / (sum_i k_i^2)   metres per 100 frames (k_i = frame offset from the first),

    the least-squares slope through the origin (e_0 = 0 by construction). Example: e_k = 0.001 k gives 0.1 m per
    100 frames. Returns {"drift_m_per_100": float (NaN with < 2 frames), "final_m": e of the last usable frame}.
    """
    est = _check_poses("drift est_c2w", est_c2w)
    gt = _check_poses("drift gt_c2w", gt_c2w)
    used = np.nonzero(_finite_rows(est) & _finite_rows(gt))[0]
    if used.size < 2:
        return {"drift_m_per_100": float("nan"), "final_m": float("nan")}
    i0 = used[0]
    p = (np.linalg.inv(est[i0]) @ est[used])[:, :3, 3]
    q = (np.linalg.inv(gt[i0]) @ gt[used])[:, :3, 3]
    e = np.linalg.norm(p - q, axis=1)
    k = (used - i0).astype(np.float64)
    return {"drift_m_per_100": float(100.0 * (k @ e) / (k @ k)), "final_m": float(e[-1])}


def _inv(T: np.ndarray) -> np.ndarray:
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -(Rt @ T[..., :3, 3:])[..., 0]
    Ti[..., 3, 3] = 1.0
    return Ti


def rpe(est_c2w: np.ndarray, gt_c2w: np.ndarray, delta: int = 1) -> dict:
    """Relative pose error over a fixed frame step (Sturm et al. 2012; same convention as evo).

    For every pair (i, j = i + delta) whose four poses are finite:
        E_ij = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)       (Q ground truth, P estimate, camera-to-world)
        e_trans = |trans(E_ij)| (m),   e_rot = angle(rot(E_ij)) (deg)
    RMSE over pairs. Every pair (i, i + delta) is used (overlapping, as the TUM tool `evaluate_rpe.py` and evo with
    `all_pairs=True`; evo's default strides by delta, which is identical for delta = 1). RPE is invariant to any
    rigid transform of either trajectory, so no alignment is used.

    Args:
        est_c2w, gt_c2w: (N, 4, 4) camera-to-world of the same frames, metres.
        delta: frame step (>= 1), in rows of the arrays.
    Returns:
        dict with trans_rmse, trans_mean, trans_median, trans_max (m); rot_rmse, rot_mean, rot_median, rot_max (deg);
        n_pairs, n_excluded (pairs with a non-finite pose); trans_errors, rot_errors (n_pairs,); pairs (n_pairs, 2).
    """
    if int(delta) < 1:
        raise ValueError(f"rpe: delta must be >= 1, got {delta}")
    delta = int(delta)
    est = _check_poses("rpe est_c2w", est_c2w)
    gt = _check_poses("rpe gt_c2w", gt_c2w)
    if est.shape[0] != gt.shape[0]:
        raise ValueError(f"rpe: {est.shape[0]} estimated poses vs {gt.shape[0]} ground-truth poses (associate first)")
    n = est.shape[0]
    i = np.arange(max(n - delta, 0))
    j = i + delta
    ok = _finite_rows(est) & _finite_rows(gt)
    valid = ok[i] & ok[j]
    i, j = i[valid], j[valid]
    rel_gt = _inv(gt[i]) @ gt[j]
    rel_est = _inv(est[i]) @ est[j]
    E = _inv(rel_gt) @ rel_est
    et = np.linalg.norm(E[:, :3, 3], axis=1)
    er = rotation_angle_deg(E[:, :3, :3])
    st, sr = _stats(et), _stats(er)
    out = {f"trans_{k}": st[k] for k in ("rmse", "mean", "median", "max")}
    out.update({f"rot_{k}": sr[k] for k in ("rmse", "mean", "median", "max")})
    out.update(
        n_pairs=int(i.size),
        n_excluded=int((~valid).sum()),
        trans_errors=et,
        rot_errors=er,
        pairs=np.stack([i, j], 1),
        delta=delta,
    )
    return out
