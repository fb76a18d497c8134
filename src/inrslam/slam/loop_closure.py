"""Loop closure for the keyframes of the SLAM loop (docs/loop_closure.md): detection by geometric overlap,
verification by coarse-to-fine GICP with a drift bound, a significance test, a colour check and an ambiguity check,
and the pose-graph correction.

Pure numpy (depth images and poses in, decisions and poses out); the loop (`slam.system`) reads the frames and
applies the result. Poses are float64 c2w (4, 4), OpenCV axes, metres.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from inrslam.errors import ConfigError
from inrslam.geometry.angles import rotation_angle_deg_np
from inrslam.geometry.pinhole import project_np
from inrslam.slam import pose_graph
from inrslam.slam.config import GicpConfig, LoopConfig
from inrslam.slam.registration import PreparedCloud, register


def view_angle_deg(Ta: np.ndarray, Tb: np.ndarray) -> float:
    """Angle between the viewing directions (camera +z) of two c2w poses, degrees."""
    c = float(np.clip(Ta[:3, 2] @ Tb[:3, 2], -1.0, 1.0))
    return float(np.degrees(np.arccos(c)))


def overlap(points_cam: np.ndarray, T_w_src: np.ndarray, T_w_dst: np.ndarray, depth_dst: np.ndarray, intr,
            tol: float) -> float:
    """Fraction of a frame's camera-frame points (N, 3) that, moved to the world by `T_w_src` and seen from
    `T_w_dst`, land inside the destination image on a pixel whose depth (H, W, metres; 0 = none) is within `tol`
    metres of theirs. 1 = the destination sees everything the source sees; 0 = nothing (or no points)."""
    if points_cam.shape[0] == 0:
        return 0.0
    T = np.linalg.solve(T_w_dst, T_w_src)
    p = points_cam @ T[:3, :3].T + T[:3, 3]
    u, v, z = project_np(p, intr.fx, intr.fy, intr.cx, intr.cy)
    H, W = depth_dst.shape
    ok = (z > 0) & np.isfinite(u) & np.isfinite(v)
    ui, vi = np.floor(u[ok] + 0.5).astype(np.int64), np.floor(v[ok] + 0.5).astype(np.int64)
    inside = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    d = depth_dst[vi[inside], ui[inside]]
    hit = (d > 0) & (np.abs(d - z[ok][inside]) < tol)
    return float(hit.sum()) / points_cam.shape[0]


def color_disagreement(depth_src: np.ndarray, grey_src: np.ndarray, grey_dst: np.ndarray, T_dst_src: np.ndarray,
                        intr, stride: int = 4) -> float:
    """Mean |grey_dst(pi(T X)) - grey_src(p)| over the source's valid depth pixels p (every `stride`-th row and
    column) back-projected to X and moved into the destination camera by `T_dst_src` (4, 4), of those landing
    inside its image (bilinear); grey in [0, 1], images (H, W). NaN when none lands. How well a relative pose
    explains two views' colour: 0 for a view warped onto itself by the identity."""
    from scipy.ndimage import map_coordinates

    from inrslam.geometry.pinhole import backproject_np

    d = np.asarray(depth_src, dtype=np.float64)
    vv, uu = np.mgrid[0:d.shape[0]:stride, 0:d.shape[1]:stride]
    sub = d[::stride, ::stride]
    ok = np.isfinite(sub) & (sub > 0)
    X = backproject_np(d, intr.fx, intr.fy, intr.cx, intr.cy, stride=stride)  # the same pixels, row-major
    q = X @ T_dst_src[:3, :3].T + T_dst_src[:3, 3]
    u, v, z = project_np(q, intr.fx, intr.fy, intr.cx, intr.cy)
    H, W = grey_dst.shape
    inside = (z > 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    if not inside.any():
        return float("nan")
    g_src = np.asarray(grey_src, dtype=np.float64)[vv[ok], uu[ok]][inside]
    g_dst = map_coordinates(np.asarray(grey_dst, dtype=np.float64), [v[inside], u[inside]], order=1)
    return float(np.abs(g_dst - g_src).mean())


@dataclass
class Candidate:
    """An older keyframe that may close a loop with the current one."""

    frame: int  # its frame index
    distance: float  # metres between the camera centres (current estimates)
    angle: float  # degrees between the viewing directions
    overlap: float = 0.0  # `overlap` of the current keyframe's points on its depth


def nearby_keyframes(frame: int, keyframes: list[int], est: np.ndarray, cfg: LoopConfig,
                     before: int | None = None) -> list[Candidate]:
    """Keyframes at least `cfg.min_gap` frames older than `frame` whose estimated camera is within `cfg.max_dist`
    metres and `cfg.max_angle` degrees of it (est: (N, 4, 4) c2w by frame index), nearest first. With `before`,
    only keyframes older than that frame: the first frame of the tracker's local map, whose keyframes every frame is
    registered onto already (a loop onto one would move the whole window rigidly, the run's first keyframe too)."""
    Tc = est[frame]
    out = []
    for k in keyframes:
        if frame - k < cfg.min_gap or (before is not None and k >= before):
            continue
        dist = float(np.linalg.norm(est[k][:3, 3] - Tc[:3, 3]))
        ang = view_angle_deg(est[k], Tc)
        if dist <= cfg.max_dist and ang <= cfg.max_angle:
            out.append(Candidate(k, dist, ang))
    return sorted(out, key=lambda c: c.distance)


def path_length(est: np.ndarray, a: int, b: int) -> float:
    """Metres travelled by the estimated camera from frame a to frame b (sum of position steps)."""
    p = est[a: b + 1, :3, 3]
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if b > a else 0.0


@dataclass
class Verification:
    """GICP check of one candidate: the keyframe's pose in the candidate's camera and why it may be rejected."""

    frame: int  # the candidate's frame
    ok: bool
    reason: str | None  # "coarse_<gicp reason>" / "<gicp reason>" / "correction" / "ambiguous", or None
    T_cand_cur: np.ndarray  # (4, 4) current keyframe's camera in the candidate's camera (GICP)
    fitness: float  # fine-stage inlier fraction
    correction: float  # metres the loop would move the current keyframe
    correction_angle: float  # degrees it would turn it
    bound: float  # metres of correction allowed (max_correction + per metre travelled)

    def record(self) -> dict:
        """Its `loop_verify` log fields."""
        return {"candidate": self.frame, "ok": self.ok, "reason": self.reason, "fitness": round(self.fitness, 4),
                "correction_m": round(self.correction, 5), "correction_deg": round(self.correction_angle, 3),
                "bound_m": round(self.bound, 4)}


def stage_clouds(points: np.ndarray, gicp: GicpConfig, cfg: LoopConfig) -> list[PreparedCloud]:
    """A keyframe's camera-frame points (N, 3) prepared for each verification stage (`cfg.corr_stages`): the coarse
    stages (all but the last) share one cloud on a `cfg.coarse_downsample`-metre voxel grid (0: the tracker's
    `gicp.downsample`), the last stage uses `gicp.downsample`. A coarse stage only has to bring a drift of centimetres
    within reach of the next; on the built-in scenes the 5 cm cloud keeps ~30 % of the 2 cm cloud's points."""
    fine = PreparedCloud(points, gicp)
    if len(cfg.corr_stages) <= 1:
        return [fine] * len(cfg.corr_stages)
    coarse = (PreparedCloud(points, dataclasses.replace(gicp, downsample=cfg.coarse_downsample))
              if cfg.coarse_downsample > 0 else fine)
    return [coarse] * (len(cfg.corr_stages) - 1) + [fine]


def verify(cand: list[PreparedCloud], cur: list[PreparedCloud], T_w_cand: np.ndarray, T_w_cur: np.ndarray,
           travelled: float, frame: int, gicp: GicpConfig, cfg: LoopConfig) -> Verification:
    """Register the current keyframe's cloud onto a candidate's (camera frames; `stage_clouds` of each) from their
    estimated relative pose, coarse to fine (`cfg.corr_stages`; a wide first stage reaches a drift of tens of
    centimetres, the last one is precise; each stage converged at `cfg.epsilon`), every stage with the fitness and
    degeneracy checks. The loop is rejected if it would move the keyframe more than the drift bound
    `max_correction + max_correction_per_m * travelled` or turn it more than `max_correction_angle`."""
    T = np.linalg.solve(T_w_cand, T_w_cur)
    bound = cfg.max_correction + cfg.max_correction_per_m * travelled
    stages = list(cfg.corr_stages)
    if not stages:
        raise ConfigError("config key 'slam.loop.corr_stages': expected at least one correspondence distance, got []")
    if len(cand) != len(stages) or len(cur) != len(stages):
        raise ValueError(f"{len(cand)} / {len(cur)} clouds for {len(stages)} verification stages (use stage_clouds)")
    for k, corr in enumerate(stages):
        last = k == len(stages) - 1
        reg = register(cand[k], cur[k], T, dataclasses.replace(
            gicp, max_corr=corr, max_step=np.inf, min_fitness=cfg.min_fitness if last else 0.3,
            eps_trans=cfg.epsilon, eps_rot=cfg.epsilon))
        if not reg.ok:
            return Verification(frame, False, reg.reason if last else f"coarse_{reg.reason}", reg.T_target_source,
                                reg.fitness, np.nan, np.nan, bound)
        T = reg.T_target_source
    moved = T_w_cand @ T
    corr_m = float(np.linalg.norm(moved[:3, 3] - T_w_cur[:3, 3]))
    ang = float(rotation_angle_deg_np(moved[:3, :3] @ T_w_cur[:3, :3].T))
    ok = corr_m <= bound and ang <= cfg.max_correction_angle
    return Verification(frame, ok, None if ok else "correction", T, reg.fitness, corr_m, ang, bound)


def new_place(candidate: int, loops: list[dict], cfg: LoopConfig) -> bool:
    """Whether no loop edge exists yet onto a candidate within `cfg.min_gap` frames of `candidate` (a loop there
    would be the first onto that place; otherwise that loop is closed and further edges keep it closed). Example:
    min_gap 100, an edge onto frame 0 -> candidate 5 is not a new place, candidate 150 is."""
    return not any(abs(int(lp["candidate"]) - candidate) < cfg.min_gap for lp in loops)


def significant(v: Verification, first: bool, cfg: LoopConfig) -> bool:
    """Whether a verified loop is worth an edge: it moves the keyframe at least `cfg.min_correction` metres, or it is
    not the `first` loop onto its place (`new_place`: that loop is closed, further edges keep it closed). A first loop
    onto a place that corrects less than the verification's own error would only add that error to a trajectory that
    had not drifted there. Example: min_correction 5 mm, a first loop correcting 3 mm -> False; the same onto a place
    with an edge already -> True."""
    return v.correction >= cfg.min_correction or not first


def color_confirms(loop_e: float, estimate_e: float, first: bool, margin: float) -> bool:
    """Whether the colour confirms a loop: its registered relative pose explains the two views' colour
    (`color_disagreement` `loop_e`) better than the current estimate's (`estimate_e`), by at least `margin` x
    `estimate_e` for the `first` loop onto a place, which moves the trajectory (a registration the colour cannot
    tell from the estimate is not evidence that the estimate drifted). False with NaN (no overlap to judge by).
    Example: margin 0.05, estimate 0.100 -> a first loop needs < 0.095, a further edge < 0.100."""
    return loop_e < estimate_e * (1.0 - margin if first else 1.0)


def consistent(verified: list[Verification], est: np.ndarray, tol: float) -> bool:
    """Whether the accepted verifications place the current keyframe within `tol` metres of each other (more than
    one place that fits equally: an ambiguous, repeated-structure match)."""
    pos = np.array([(est[v.frame] @ v.T_cand_cur)[:3, 3] for v in verified]).reshape(-1, 3)
    return bool((np.linalg.norm(pos[:, None] - pos[None], axis=-1) <= tol).all())  # every pair


def corrected_keyframes(kf_poses: np.ndarray, kf_ids: list[int], loops: list[dict], cfg: LoopConfig,
                        odometry: np.ndarray | None = None) -> np.ndarray:
    """Pose-graph optimisation of the keyframes (K, 4, 4) c2w: odometry edges between consecutive keyframes and
    every loop `{"candidate": frame, "frame": frame, "T": (4, 4) candidate <- current}`; keyframe 0 fixed. The
    odometry edges are `odometry` (K - 1, 4, 4), each keyframe's pose relative to the one before as tracked, or,
    without it, measured from the current poses (then a correction that moved a run of keyframes rigidly is taken
    for odometry by every later optimisation). Starts from `kf_poses`; returns the corrected (K, 4, 4) poses."""
    slot = {f: k for k, f in enumerate(kf_ids)}
    if odometry is None:
        edges = pose_graph.odometry_edges(kf_poses, cfg.odom_sigma_t, cfg.odom_sigma_r)
    else:
        if len(odometry) != len(kf_poses) - 1:
            raise ValueError(f"{len(odometry)} odometry edges for {len(kf_poses)} keyframes")
        edges = [pose_graph.Edge(k, k + 1, np.asarray(T, dtype=np.float64), cfg.odom_sigma_t, cfg.odom_sigma_r)
                 for k, T in enumerate(odometry)]
    edges += [pose_graph.Edge(slot[lp["candidate"]], slot[lp["frame"]], np.asarray(lp["T"], dtype=np.float64),
                              cfg.loop_sigma_t, cfg.loop_sigma_r, cfg.huber) for lp in loops]
    return pose_graph.optimise(kf_poses, edges, fixed=0)


def follow_keyframes(est: np.ndarray, old_kf: np.ndarray, new_kf: np.ndarray, kf_ids: list[int],
                     rel_kf: np.ndarray, upto: int, rigid_from: int | None = None) -> np.ndarray:
    """Frames 0..upto (est (N, 4, 4) c2w) after their keyframes moved from `old_kf` to `new_kf` (K, 4, 4): a
    keyframe takes its new pose; any other frame moves rigidly with the keyframe it was tracked from
    (`rel_kf`, frame ids), keeping its pose relative to it. Frames from `rigid_from` on (the tracker's local map)
    all move with the newest keyframe instead, so that the window the next frames are registered onto keeps its
    shape. Frames after `upto` are left as they are."""
    out = est.copy()
    slot = {f: k for k, f in enumerate(kf_ids)}
    delta = new_kf @ np.linalg.inv(old_kf)  # (K, 4, 4) world-frame correction of each keyframe
    start = upto + 1 if rigid_from is None else min(rigid_from, upto + 1)
    for j in range(upto + 1):
        if not np.isfinite(est[j]).all():
            continue
        if j >= start:
            out[j] = delta[-1] @ est[j]
        elif j in slot:
            out[j] = new_kf[slot[j]]
        elif rel_kf[j] in slot:
            out[j] = delta[slot[int(rel_kf[j])]] @ est[j]
    return out
