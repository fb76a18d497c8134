"""Evaluate run directories and plain files: the thin I/O layer over `trajectory`, `mesh` and `image`.

`evaluate_run(run_dir)` recomputes every "from results" metric of a run directory (layout: docs/design.md) and
merges it into the run's `metrics.json` (process metrics written by the SLAM run are kept). The stable keys and
their units are documented in docs/metrics.md; `RESULT_KEYS` lists the keys this module owns.
"""

from __future__ import annotations

import json
import math
import os
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import numpy as np
import trimesh
from rich.table import Table

from inrslam.errors import ConfigError, DataError
from inrslam.eval.config import Alignment, EvalConfig
from inrslam.eval.mesh import GT_CULL_MAX_EDGE, cull_mesh, mesh_metrics, subdivide_to_edge
from inrslam.eval.trajectory import associate, ate, drift_per_100, rpe
from inrslam.geometry.intrinsics import Intrinsics
from inrslam.io.atomic import atomic_path
from inrslam.io.rundir import RunDir
from inrslam.io.trajectory import read_tum
from inrslam.io.yamlfile import load_yaml
from inrslam.status import logger, stage

log = logger(__name__)

PathLike = Union[str, os.PathLike]

#: keys `evaluate_run` (re)computes; always present in its output (None when not computable).
RESULT_KEYS = (
    "ate_rmse_m",
    "ate_mean_m",
    "ate_median_m",
    "ate_max_m",
    "rpe_trans_m",
    "rpe_rot_deg",
    "ate_keyframes_rmse_m",
    "ate_relative_rmse_m",
    "drift_m_per_100",
    "acc_m",
    "comp_m",
    "comp_ratio",
    "frames",
)

#: every key of the trajectory family (`trajectory_metrics` + the relative trajectory): all of them are rewritten on
#: each evaluation, null when the trajectory or its ground truth is missing, so no stale value survives.
TRAJECTORY_KEYS = (
    "ate_rmse_m", "ate_mean_m", "ate_median_m", "ate_std_m", "ate_min_m", "ate_max_m", "ate_n_used",
    "ate_n_excluded", "ate_scale", "rpe_trans_m", "rpe_rot_deg", "rpe_n_pairs", "drift_m_per_100",
    "unaligned_final_m", "ate_keyframes_rmse_m", "ate_keyframes_n_used", "ate_relative_rmse_m",
)

#: keys of the mesh family (Acc / Comp / Comp%), likewise rewritten together.
MESH_KEYS = ("acc_m", "comp_m", "comp_ratio")

#: `run_info.json` statuses after which a run directory holds its final trajectory and mesh.
FINISHED_STATUSES = ("slam_done", "complete")


# ----------------------------------------------------------------------------------------------------------------
# small readers (thin wrappers: formats live in inrslam.io; these only add run-directory conventions)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: invalid JSON ({e})") from None


def load_mesh(path: PathLike) -> trimesh.Trimesh:
    """Read a triangle mesh (PLY/OBJ/...) with trimesh, without merging or reordering vertices."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for unreadable files
        raise DataError(f"{path}: cannot read mesh ({e})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise DataError(f"{path}: expected a triangle mesh, got {type(mesh).__name__}")
    return mesh


def intrinsics_from_dict(d: Intrinsics | Mapping[str, Any], source: str = "intrinsics") -> Intrinsics:
    """`Intrinsics` from a mapping with keys fx, fy, cx, cy (pixels), width, height."""
    if isinstance(d, Intrinsics):
        return d
    keys = ("fx", "fy", "cx", "cy", "width", "height")
    missing = [k for k in keys if k not in d]
    if missing:
        raise DataError(f"{source}: missing intrinsics keys {missing} (expected {list(keys)})")
    return Intrinsics(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]), int(d["width"]), int(d["height"]))


def _f(x: Any) -> Optional[float]:
    """float or None for NaN / None (JSON-friendly)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


# ----------------------------------------------------------------------------------------------------------------
# pure assembly of the stable keys


def trajectory_metrics(
    est_c2w: np.ndarray,
    gt_c2w: np.ndarray,
    keyframe_rows: Optional[np.ndarray] = None,
    align: Alignment | str = Alignment.SE3,
    rpe_delta: int = 1,
) -> dict:
    """Stable trajectory keys from associated (N, 4, 4) estimate / GT arrays (GT rows may be NaN = no GT).

    Keyframe ATE (`ate_keyframes_rmse_m`) restricts both arrays to `keyframe_rows` and aligns that subset on its
    own. Returns ate_rmse_m, ate_mean_m, ate_median_m, ate_std_m, ate_min_m, ate_max_m, ate_n_used, ate_n_excluded,
    rpe_trans_m, rpe_rot_deg, rpe_n_pairs, drift_m_per_100, unaligned_final_m (`drift_per_100`),
    ate_keyframes_rmse_m, ate_keyframes_n_used. Raises DataError for a Sim(3) alignment of an estimate whose
    positions never move (the scale is undefined; a keyframe subset that never moves leaves its keys empty).
    """
    if Alignment(align) is Alignment.SIM3 and not _moves(est_c2w, gt_c2w):
        raise DataError("Sim(3) alignment: the estimated camera positions never move, so the scale is undefined "
                        "(align with se3)")
    a = ate(est_c2w, gt_c2w, align=align)
    r = rpe(est_c2w, gt_c2w, delta=rpe_delta)
    d = drift_per_100(est_c2w, gt_c2w)
    out = {
        "ate_rmse_m": _f(a["rmse"]),
        "ate_mean_m": _f(a["mean"]),
        "ate_median_m": _f(a["median"]),
        "ate_std_m": _f(a["std"]),
        "ate_min_m": _f(a["min"]),
        "ate_max_m": _f(a["max"]),
        "ate_n_used": a["n_used"],
        "ate_n_excluded": a["n_excluded"],
        "ate_scale": _f(a["alignment"]["s"]),
        "rpe_trans_m": _f(r["trans_rmse"]),
        "rpe_rot_deg": _f(r["rot_rmse"]),
        "rpe_n_pairs": r["n_pairs"],
        "drift_m_per_100": _f(d["drift_m_per_100"]),
        "unaligned_final_m": _f(d["final_m"]),
        "ate_keyframes_rmse_m": None,
        "ate_keyframes_n_used": 0,
    }
    rows = np.asarray(keyframe_rows if keyframe_rows is not None else [], dtype=np.int64)
    if len(rows) > 0 and (Alignment(align) is not Alignment.SIM3
                          or _moves(np.asarray(est_c2w)[rows], np.asarray(gt_c2w)[rows])):
        k = ate(np.asarray(est_c2w)[rows], np.asarray(gt_c2w)[rows], align=align)
        out["ate_keyframes_rmse_m"] = _f(k["rmse"])
        out["ate_keyframes_n_used"] = k["n_used"]
    return out


def _moves(est_c2w: np.ndarray, gt_c2w: np.ndarray) -> bool:
    """Whether the estimated positions of the frames ATE uses (both poses finite) differ, or fewer than 2 are used
    (a Sim(3) alignment then falls back to SE(3) in `ate`)."""
    est, gt = np.asarray(est_c2w, dtype=np.float64), np.asarray(gt_c2w, dtype=np.float64)
    if est.ndim != 3 or est.shape != gt.shape:
        return True  # `ate` reports the shapes
    used = np.isfinite(est.reshape(len(est), -1)).all(1) & np.isfinite(gt.reshape(len(gt), -1)).all(1)
    p = est[used, :3, 3]
    return len(p) < 2 or bool((p != p[0]).any())


def associated_gt(ts_est: np.ndarray, ts_gt: np.ndarray, gt: np.ndarray, max_diff: float) -> np.ndarray:
    """(N, 4, 4) GT pose of each estimated frame (NaN where no GT timestamp is within max_diff)."""
    ia, ib = associate(ts_est, ts_gt, max_diff)
    full = np.full((len(ts_est), 4, 4), np.nan)
    full[ia] = gt[ib]
    return full


# ----------------------------------------------------------------------------------------------------------------
# run directories


def _keyframe_rows(run_dir: Path, run_info: dict, ts_est: np.ndarray, max_diff: float,
                   notes: list) -> Optional[np.ndarray]:
    """Rows of trajectory.txt that are keyframes (frame indices -> rows via run_info timestamps)."""
    kf = run_info.get("keyframes")
    if kf is None and RunDir(run_dir).keyframes.is_file():
        kf = _read_json(RunDir(run_dir).keyframes)
        if isinstance(kf, dict):
            kf = kf.get("keyframes")
    if kf is None:
        notes.append("ate_keyframes_rmse_m: no keyframe list (run_info.json 'keyframes' or keyframes.json)")
        return None
    kf = np.asarray(kf, dtype=np.int64).ravel()
    stamps = run_info.get("timestamps")
    if stamps is not None:
        stamps = np.asarray(stamps, dtype=np.float64)
        kf = kf[(kf >= 0) & (kf < len(stamps))]
        ia, ib = associate(stamps[kf], ts_est, max_diff)
        return ib
    notes.append("keyframes: run_info.json has no 'timestamps'; assumed trajectory row == frame index")
    return kf[(kf >= 0) & (kf < len(ts_est))]


def _config_data_path(run_dir: Path) -> Optional[str]:
    """`data.path` of the run's config.yaml, or None (missing / unreadable file, built-in scene)."""
    try:
        cfg = load_yaml(RunDir(run_dir).config) or {}
        path = (cfg.get("data") or {}).get("path")
    except (ConfigError, AttributeError):
        return None
    return str(path) if path and not str(path).startswith("builtin:") else None


def resolve_gt_mesh(run_dir: PathLike, run_info: Mapping[str, Any]) -> Optional[Path]:
    """The GT mesh file of a run: `run_info["gt_mesh"]` when absolute (runs record absolute paths), else found for
    an older run that recorded the path relative to the directory it was started from (like its `data.path`).

    A relative path P is looked up (first existing file wins) as: the data root (config.yaml `data.path` when
    absolute, else the relative root found from the places below) joined with P taken relative to the recorded root
    (`run_info["dataset"]["root"]`); then P itself from the run directory, the current directory and each parent
    of the run directory. None when the run names no GT mesh; the first candidate when none exists (for the message).
    """
    p = run_info.get("gt_mesh")
    if not p:
        return None
    path = Path(str(p)).expanduser()
    if path.is_absolute():
        return path
    run_dir = Path(run_dir)
    bases = [run_dir.absolute(), Path.cwd(), *run_dir.absolute().parents]
    cands: list[Path] = []
    recorded_root = str((run_info.get("dataset") or {}).get("root") or "")
    cfg_root = _config_data_path(run_dir)
    if recorded_root and not Path(recorded_root).is_absolute():
        rel = Path(os.path.relpath(path, recorded_root))
        roots = [Path(cfg_root)] if cfg_root and Path(cfg_root).is_absolute() else []
        roots += [b / (cfg_root or recorded_root) for b in bases]
        cands += [r / rel for r in roots if r.is_dir()]
    cands += [b / path for b in bases]
    return next((c for c in cands if c.is_file()), cands[0])


def evaluate_run(run_dir: PathLike, cfg: Any = None, write: bool = True) -> dict:
    """(Re)compute all result metrics of a run directory and merge them into its `metrics.json`.

    Reads `trajectory.txt`, `trajectory_gt.txt` (TUM; associated by timestamp within `cfg.max_time_diff`; estimated
    frames without GT are excluded from ATE and counted), `run_info.json` (`intrinsics`, `gt_mesh`, `keyframes`,
    `timestamps`), `keyframes.json` (fallback), `mesh.ply` and the GT mesh. The reconstructed mesh is culled with
    the ground-truth cameras (every `cfg.cull_every`-th row of `trajectory_gt.txt`, frustum + occlusion); the GT
    mesh is used as is, or with `cfg.cull_gt` culled the same way after splitting its triangles to edges of at most
    `GT_CULL_MAX_EDGE`. A relative `gt_mesh` of an older run is found by `resolve_gt_mesh`. Existing keys of
    `metrics.json` (process metrics: timings, model size, PSNR, ...) are kept; the keys in `RESULT_KEYS`,
    `TRAJECTORY_KEYS` and `MESH_KEYS` are always written (None when not computable, with the reason in
    `eval_notes`), together with `protocol` (this evaluation's settings) and `mesh_eval` (culling / ICP details).
    A run whose SLAM part did not finish (run_info.json status other than slam_done / complete, or no
    trajectory.txt) raises DataError and its metrics.json is left as it is.

    Args:
        run_dir: the run directory.
        cfg: protocol: an `EvalConfig`, or anything `EvalConfig.from_any` accepts (the run config's `eval` section,
            a dict); missing fields take the defaults (the benchmark protocol with ICP off).
        write: write the merged dict back to `metrics.json` (atomically).
    Returns:
        the merged metrics dict.

    While it writes, it holds the run folder's lock (`RunDir.lock`): RunError when another process runs there.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise DataError(f"{run_dir}: run directory not found")
    with RunDir(run_dir).lock() if write else nullcontext():
        return _evaluate_run(run_dir, EvalConfig.from_any(cfg), write)


def _evaluate_run(run_dir: Path, cfg: EvalConfig, write: bool) -> dict:
    """`evaluate_run` of an existing run folder, with its protocol resolved."""
    notes: list[str] = []
    rd = RunDir(run_dir)
    info_path = rd.run_info
    run_info = _read_json(info_path) if info_path.is_file() else {}
    if not isinstance(run_info, dict):
        raise DataError(f"{info_path}: expected a JSON object")
    if not info_path.is_file():
        notes.append("run_info.json missing: no keyframes, intrinsics or GT mesh")
    _check_finished(run_dir, run_info)
    metrics_path = rd.metrics
    existing = _read_json(metrics_path) if metrics_path.is_file() else {}
    if not isinstance(existing, dict):
        raise DataError(f"{metrics_path}: expected a JSON object")

    res: dict[str, Any] = {k: None for k in (*RESULT_KEYS, *TRAJECTORY_KEYS, *MESH_KEYS)}

    # --- trajectory
    est_path, gt_path = rd.trajectory, rd.trajectory_gt
    gt_cams = None
    if gt_path.is_file():
        ts_gt, gt = read_tum(gt_path)
        gt_cams = gt
    ts_est, est = read_tum(est_path)
    res["frames"] = int(len(est))
    if gt_cams is not None:
        stage(log, f"evaluation: ATE / RPE of {len(est)} poses ({Alignment(cfg.align).value} alignment)")
        gt_full = associated_gt(ts_est, ts_gt, gt, cfg.max_time_diff)
        rows = _keyframe_rows(run_dir, run_info, ts_est, cfg.max_time_diff, notes)
        try:
            res.update(trajectory_metrics(est, gt_full, rows, cfg.align, cfg.rpe_delta))
        except DataError as e:  # e.g. Sim(3) alignment of an estimate that never moved: the keys stay null
            notes.append(f"no ATE/RPE: {e}")
        if res["ate_n_used"] == 0:
            notes.append(f"ATE: no estimated timestamp within {cfg.max_time_diff} s of a GT timestamp")
        rel_path = rd.trajectory_relative
        if rel_path.is_file():  # docs/spec.md §7.6: non-keyframes carried along by their keyframe's refinement
            ts_rel, est_rel = read_tum(rel_path)
            rel_gt = associated_gt(ts_rel, ts_gt, gt, cfg.max_time_diff)
            try:
                res["ate_relative_rmse_m"] = trajectory_metrics(est_rel, rel_gt, None, cfg.align, cfg.rpe_delta)[
                    "ate_rmse_m"]
            except DataError as e:
                notes.append(f"no relative ATE: {e}")
    else:
        notes.append("trajectory_gt.txt missing: no ATE/RPE")

    # --- mesh
    rec_path = rd.mesh
    gt_mesh_path = resolve_gt_mesh(run_dir, run_info)
    mesh_eval: dict[str, Any] = {}
    if not cfg.mesh_metrics:
        notes.append("mesh metrics disabled (mesh_metrics: false)")
    elif not rec_path.is_file():
        notes.append("mesh.ply missing: no Acc/Comp")
    elif gt_mesh_path is None or not gt_mesh_path.is_file():
        notes.append(f"GT mesh {'not given' if gt_mesh_path is None else f'not found at {gt_mesh_path}'}: no Acc/Comp")
    elif gt_cams is None or "intrinsics" not in run_info:
        notes.append("no GT cameras (trajectory_gt.txt) or intrinsics (run_info.json): cannot cull, no Acc/Comp")
    else:
        mres = _mesh_eval(load_mesh(rec_path), load_mesh(gt_mesh_path), gt_cams,
                          intrinsics_from_dict(run_info["intrinsics"], f"{info_path}: intrinsics"), cfg)
        mesh_eval = mres.pop("mesh_eval")
        mesh_eval["gt_mesh"] = str(gt_mesh_path)
        if mres.get("error"):
            notes.append(mres.pop("error"))
        res.update(mres)

    out = dict(existing)
    out.update(res)
    out["protocol"] = cfg.protocol()
    out["mesh_eval"] = mesh_eval
    out["eval_notes"] = notes
    if write:
        rd.write_metrics(out)
    return out


def _check_finished(run_dir: Path, run_info: Mapping[str, Any]) -> None:
    """DataError unless the run finished SLAM: run_info.json status slam_done / complete (when it has a status) and
    trajectory.txt written. Evaluating a half-done run would replace its metrics with nulls."""
    rd = RunDir(run_dir)
    status = run_info.get("status")
    if status is None and rd.trajectory.is_file():
        return  # a run directory written by hand or another tool: evaluate what is there
    if status in FINISHED_STATUSES and rd.trajectory.is_file():
        return
    what = f"status {status}" if status is not None else "no run_info.json status"
    if not rd.trajectory.is_file():
        what += ", no trajectory.txt"
    if rd.has_checkpoint():
        raise DataError(f"{run_dir}: the run is incomplete ({what}): resume it with inrslam run --resume {run_dir}")
    if rd.holds_run():
        raise DataError(f"{run_dir}: the run is incomplete ({what}, no checkpoint yet): start it again with "
                        f"inrslam run --config {rd.config} --out {run_dir} --overwrite")
    raise DataError(f"{run_dir}: not a finished run ({what}) and no config.yaml to continue it from")


def _mesh_eval(rec: trimesh.Trimesh, gt: trimesh.Trimesh, cams: np.ndarray, intr: Intrinsics, cfg: EvalConfig,
               culled_out: Optional[PathLike] = None) -> dict:
    cams = culling_cameras(cams, cfg)
    stage(log, f"evaluation: culling the mesh ({len(rec.faces)} triangles) with {len(cams)} cameras (frustum"
               f"{' + occlusion' if cfg.cull_occlusion else ''})")
    culled = cull_mesh(rec, cams, intr, every=1, eps=cfg.cull_eps, occlusion=cfg.cull_occlusion)
    gt_split_faces = None
    if cfg.cull_gt:  # GT triangles split first: visibility is per vertex, GT walls are often two triangles
        stage(log, "evaluation: culling the ground-truth mesh the same way")
        gt = subdivide_to_edge(gt, GT_CULL_MAX_EDGE)
        gt_split_faces = int(len(gt.faces))
        gt = cull_mesh(gt, cams, intr, every=1, eps=cfg.cull_eps, occlusion=cfg.cull_occlusion)
    if culled_out is not None:
        with atomic_path(culled_out) as tmp:
            culled.export(tmp)
    empty_gt = _no_surface(gt)
    details = {
        "rec_faces": int(len(rec.faces)),
        "culled_faces": int(len(culled.faces)),
        "cameras_used": int(len(cams)),
        "gt_faces": int(len(gt.faces)),
        **({"gt_max_edge_m": GT_CULL_MAX_EDGE, "gt_split_faces": gt_split_faces} if cfg.cull_gt else {}),
        "icp_transform": None,
        "icp_info": None,
    }
    if _no_surface(culled) or empty_gt:
        what = ("culled reconstruction is empty" if _no_surface(culled) else
                "ground-truth mesh has no triangles" + (" seen by the cameras (cull_gt)" if cfg.cull_gt else ""))
        return {"acc_m": None, "comp_m": None, "comp_ratio": None, "mesh_eval": details,
                "error": f"{what}: no Acc/Comp"}
    stage(log, f"evaluation: accuracy / completion on {cfg.n_samples} surface samples{' after ICP' if cfg.icp else ''}")
    m = mesh_metrics(culled, gt, n_samples=cfg.n_samples, threshold=cfg.threshold, icp=cfg.icp, seed=cfg.seed)
    details["icp_transform"] = m["icp_transform"]
    details["icp_info"] = m["icp_info"]
    return {"acc_m": m["acc_m"], "comp_m": m["comp_m"], "comp_ratio": m["comp_ratio"], "mesh_eval": details}


def _no_surface(mesh: trimesh.Trimesh) -> bool:
    """True for a mesh with nothing to sample (no triangles, or only zero-area ones)."""
    return len(mesh.faces) == 0 or not mesh.area > 0


def culling_cameras(gt_cams: np.ndarray, cfg: EvalConfig) -> np.ndarray:
    """Every `cull_every`-th GT camera, plus all virtual cameras of `cfg.virtual_cameras` (TUM file) if given."""
    cams = np.asarray(gt_cams, dtype=np.float64).reshape(-1, 4, 4)[:: cfg.cull_every]
    if cfg.virtual_cameras:
        _, virt = read_tum(cfg.virtual_cameras)
        cams = np.concatenate([cams, virt])
    return cams


# ----------------------------------------------------------------------------------------------------------------
# anyone's files


def eval_trajectory_files(
    est_path: PathLike, gt_path: PathLike, align: Alignment | str = "se3", max_diff: float = 0.02, rpe_delta: int = 1
) -> dict:
    """ATE / RPE of two TUM trajectory files (camera-to-world), associated by timestamp (TUM rule, `max_diff` s).

    Only associated frames are evaluated (RPE pairs are consecutive associated frames, step `rpe_delta`).
    Returns the trajectory keys of `trajectory_metrics` plus n_est, n_gt, n_matched and `protocol`.
    """
    ts_e, est = read_tum(est_path)
    ts_g, gt = read_tum(gt_path)
    ia, ib = associate(ts_e, ts_g, max_diff)
    if ia.size == 0:
        raise DataError(f"{est_path} vs {gt_path}: no timestamps associated within {max_diff} s")
    out = trajectory_metrics(est[ia], gt[ib], None, align, rpe_delta)
    del out["ate_keyframes_rmse_m"], out["ate_keyframes_n_used"]
    out.update(n_est=int(len(est)), n_gt=int(len(gt)), n_matched=int(ia.size))
    out["protocol"] = {
        "alignment": Alignment(align).value,
        "association": {"method": "timestamp", "max_diff_s": max_diff},
        "rpe_delta": rpe_delta,
    }
    return out


def eval_mesh_files(
    rec_path: PathLike,
    gt_path: PathLike,
    cameras_path: Optional[PathLike] = None,
    intrinsics: Optional[Union[Intrinsics, Mapping[str, Any]]] = None,
    every: int = 2,
    eps: float = 0.03,
    occlusion: bool = True,
    n_samples: int = 200_000,
    threshold: float = 0.05,
    icp: bool = False,
    seed: int = 0,
    culled_out: Optional[PathLike] = None,
    virtual_cameras: Optional[PathLike] = None,
    cull_gt: bool = False,
) -> dict:
    """Acc / Comp / Comp% of a reconstructed mesh file against a GT mesh file.

    If `cameras_path` (TUM file of ground-truth camera-to-world poses, OpenCV axes) is given, the reconstruction is
    culled first (frustum + occlusion, `intrinsics` required) and optionally saved to `culled_out`; without it the
    reconstruction is evaluated unculled (say so when reporting). Returns acc_m, comp_m, comp_ratio, mesh_eval,
    protocol.
    """
    cfg = EvalConfig(cull_every=every, cull_eps=eps, cull_occlusion=occlusion, n_samples=n_samples,
                     threshold=threshold, icp=icp, seed=seed, virtual_cameras=str(virtual_cameras or ""),
                     cull_gt=cull_gt)
    rec, gt = load_mesh(rec_path), load_mesh(gt_path)
    protocol = cfg.protocol()
    del protocol["alignment"], protocol["association"], protocol["rpe_delta"]
    for path, mesh in ((rec_path, rec), (gt_path, gt)):
        if _no_surface(mesh):
            raise DataError(f"{path}: no triangles with area (a point cloud?): expected a triangle mesh with a surface")
    if cameras_path is None:
        m = mesh_metrics(rec, gt, n_samples=n_samples, threshold=threshold, icp=icp, seed=seed)
        protocol["culling"] = None
        details = {"rec_faces": int(len(rec.faces)), "culled_faces": None, "cameras_used": 0,
                   "icp_transform": m["icp_transform"], "icp_info": m["icp_info"]}
        out = {"acc_m": m["acc_m"], "comp_m": m["comp_m"], "comp_ratio": m["comp_ratio"], "mesh_eval": details}
    else:
        if intrinsics is None:
            raise DataError(f"{cameras_path}: culling with cameras needs intrinsics (fx, fy, cx, cy, width, height)")
        _, cams = read_tum(cameras_path)
        out = _mesh_eval(rec, gt, cams, intrinsics_from_dict(intrinsics), cfg, culled_out)
        if out.get("error"):
            raise DataError(f"{rec_path} vs {gt_path}: {out['error']} (cameras {cameras_path})")
    out["protocol"] = protocol
    return out


# ----------------------------------------------------------------------------------------------------------------
# display

# key -> (label, unit shown, factor applied to the stored value)
_DISPLAY = {
    "ate_rmse_m": ("ATE RMSE", "cm", 100.0),
    "ate_mean_m": ("ATE mean", "cm", 100.0),
    "ate_median_m": ("ATE median", "cm", 100.0),
    "ate_max_m": ("ATE max", "cm", 100.0),
    "ate_keyframes_rmse_m": ("ATE RMSE (keyframes)", "cm", 100.0),
    "ate_relative_rmse_m": ("ATE RMSE (relative traj.)", "cm", 100.0),
    "rpe_trans_m": ("RPE trans. RMSE", "cm", 100.0),
    "drift_m_per_100": ("Drift (unaligned error growth)", "cm/100 fr", 100.0),
    "unaligned_final_m": ("Unaligned error, last frame", "cm", 100.0),
    "rpe_rot_deg": ("RPE rot. RMSE", "deg", 1.0),
    "acc_m": ("Accuracy", "cm", 100.0),
    "comp_m": ("Completion", "cm", 100.0),
    "comp_ratio": ("Completion ratio", "%", 100.0),
    "psnr_db": ("PSNR (held-out)", "dB", 1.0),
    "ssim": ("SSIM (held-out)", "", 1.0),
    "depth_l1_m": ("Depth L1 (held-out)", "cm", 100.0),
    "psnr_process_db": ("PSNR (process)", "dB", 1.0),
    "depth_l1_process_m": ("Depth L1 (process)", "cm", 100.0),
    "track_ms_per_frame": ("Tracking", "ms/frame", 1.0),
    "map_ms_per_call": ("Mapping", "ms/call", 1.0),
    "model_size_mb": ("Model size", "MiB", 1.0),
    "peak_memory_mb": ("Peak memory", "MiB", 1.0),
    "frames": ("Frames", "", 1.0),
}


def _unit_for(key: str) -> tuple[str, str, float]:
    if key in _DISPLAY:
        return _DISPLAY[key]
    for suffix, unit, fac in (("_m", "cm", 100.0), ("_deg", "deg", 1.0), ("_db", "dB", 1.0), ("_mb", "MiB", 1.0),
                              ("_ms", "ms", 1.0), ("_s", "s", 1.0), ("_ratio", "%", 100.0)):
        if key.endswith(suffix):
            return key, unit, fac
    return key, "", 1.0


def format_table(metrics: Mapping[str, Any], title: Optional[str] = "Metrics") -> Table:
    """A rich table (metric, value, unit) of the scalar entries of a metrics dict; lengths shown in cm.

    Known keys come first in a fixed order, then other numeric keys; dicts / lists are skipped; None -> "—".
    """
    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_column("unit")
    keys = [k for k in _DISPLAY if k in metrics] + sorted(k for k in metrics if k not in _DISPLAY)
    for key in keys:
        val = metrics[key]
        if isinstance(val, (dict, list, tuple, str)):
            continue
        label, unit, fac = _unit_for(key)
        if val is None:
            txt = "—"
        elif isinstance(val, bool):
            txt = str(val)
        elif isinstance(val, (int, np.integer)) and fac == 1.0:
            txt = str(int(val))
        else:
            v = float(val) * fac
            txt = f"{v:.4f}" if abs(v) < 10 else f"{v:.2f}"
        table.add_row(label, txt, unit)
    return table
