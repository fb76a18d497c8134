"""The SLAM run: initialise on frame 0, track every frame, map + bundle-adjust every `map_every`-th frame, write
a self-describing run directory, checkpoint and resume (docs/spec.md §1, §7)."""

from __future__ import annotations

import math
import os
import platform
import resource
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

import inrslam
from inrslam.data.frame import Frame
from inrslam.errors import ConfigError
from inrslam.geometry.camera import pixel_directions
from inrslam.io.atomic import append_jsonl, atomic_path, write_json
from inrslam.io.rundir import RunDir
from inrslam.io.trajectory import write_tum
from inrslam.rendering.sampling import sample_pixels
from inrslam.slam.config import GicpTarget, PoseInit
from inrslam.slam.keyframes import KeyframeStore
from inrslam.slam.mapping import initialise, map_frame
from inrslam.slam.mesh_extraction import extract_mesh
from inrslam.slam.model import SceneModel
from inrslam.slam.poses import constant_velocity, relative_trajectory
from inrslam.slam.registration import PreparedCloud, depth_points, moved_beyond, prepare_depth, register
from inrslam.slam.sdf_tracking import align_to_sdf
from inrslam.slam.tracking import track_frame


def resolve_device(name: str) -> torch.device:
    """'auto' -> cuda if available else cpu."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"config key 'device': {name!r} requested but CUDA is not available")
    return dev


class FrameTensors:
    """One frame on the device, with uniform ray sampling helpers."""

    def __init__(self, frame: Frame, device: torch.device):
        self.frame = frame
        self.intr = frame.intrinsics
        self.rgb = torch.from_numpy(np.ascontiguousarray(frame.rgb, dtype=np.float32)).to(device).reshape(-1, 3)
        self.depth = torch.from_numpy(np.ascontiguousarray(frame.depth, dtype=np.float32)).to(device).reshape(-1)
        self.device = device

    def rays(self, idx: torch.Tensor):
        """(n,) flat pixel indices -> dirs_cam (n,3), rgb (n,3), depth (n,)."""
        W = self.intr.width
        u, v = (idx % W).float(), torch.div(idx, W, rounding_mode="floor").float()
        return pixel_directions(self.intr, u, v), self.rgb[idx], self.depth[idx]

    def sample(self, n: int, generator: torch.Generator, edge: int = 0):
        """n distinct pixels uniformly inside an `edge`-pixel border (no border if it would leave none)."""
        H, W = self.intr.height, self.intr.width
        if H - 2 * edge <= 0 or W - 2 * edge <= 0:
            edge = 0
        n = min(n, (H - 2 * edge) * (W - 2 * edge))
        u, v = sample_pixels(H, W, n, edge, generator, self.device)
        return self.rays(v * W + u)


class SlamSystem:
    """Runs SLAM on a dataset and writes the run directory `out_dir` (layout in docs/design.md)."""

    def __init__(self, cfg, dataset, out_dir: str | os.PathLike, progress=None, threads: int | None = None):
        self.cfg = cfg
        # the torch / numba thread count the caller holds for this run (recorded: results are bit-identical only
        # at one count); None = whatever the process has set
        self.threads = threads
        self.dataset = dataset
        self.out = Path(out_dir)
        self.rd = RunDir(self.out)
        self.progress = progress  # callable(frame_idx, n_frames, info: dict) or None
        self.device = resolve_device(cfg.device)
        torch.manual_seed(cfg.seed)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.n_frames = len(dataset)
        if self.n_frames == 0:
            raise ConfigError(f"dataset {getattr(dataset, 'root', '?')} has no frames")
        self.bounds = np.asarray(dataset.bounds, dtype=np.float64)
        self.model = SceneModel(cfg, self.bounds).to(self.device)
        self.optimizers = self.model.make_optimizers(cfg.slam.map_lr)
        self.store = KeyframeStore(device=self.device)
        self.est = torch.full((self.n_frames, 4, 4), float("nan"), dtype=torch.float32, device=self.device)
        # relative bookkeeping (docs/spec.md §7.6): tracked pose of frame i in the frame of its latest keyframe
        self.rel = torch.full((self.n_frames, 4, 4), float("nan"), dtype=torch.float32, device=self.device)
        self.rel_kf = np.full(self.n_frames, -1, dtype=np.int64)
        self.gt = np.full((self.n_frames, 4, 4), np.nan)
        self.timestamps = np.zeros(self.n_frames)
        self.next_frame = 0
        self.track_ms: list[float] = []
        self.map_ms: list[float] = []
        self.init_ms = 0.0
        self.wall_s_before = 0.0  # wall time of earlier (interrupted) segments of this run
        self.peak_mb_before = 0.0  # peak memory of earlier segments
        self._t_start = time.perf_counter()
        self.proc_psnr: list[float] = []
        self.proc_depth_l1: list[float] = []
        self.events: list[dict] = []
        self.tb: Any = None  # TensorBoard SummaryWriter when enabled
        # (frame index, cloud) of the GICP target; not checkpointed: rebuilt from the dataset after a resume
        self._target_cloud: tuple[int, PreparedCloud] | None = None
        self._local_target: tuple[tuple[int, ...], PreparedCloud] | None = None  # slam.gicp.target = local_map
        self._kf_points: dict[int, np.ndarray] = {}  # camera-frame points of the local map's keyframes
        self.gicp_kfs = [0]  # GICP keyframes (slam.gicp.target = keyframe / local_map), the last is the current

    # -- bookkeeping --------------------------------------------------------------------------------------
    def _log(self, record: dict) -> None:
        append_jsonl(self.rd.log, record)
        if self.tb is not None:
            step = record.get("frame", 0)
            for k, v in record.items():
                if isinstance(v, (int, float)) and k != "frame" and math.isfinite(v):
                    self.tb.add_scalar(f"{record.get('type', 'log')}/{k}", v, step)

    def _open_tensorboard(self, resume: bool = False) -> None:
        """TensorBoard writer (optional). On resume, events from the checkpointed frame on are purged, so that
        the records logged again after the checkpoint do not show twice."""
        if not self.cfg.output.tensorboard:
            return
        try:
            from torch.utils.tensorboard import SummaryWriter
        except Exception:  # tensorboard not installed: optional
            return
        self.tb = SummaryWriter(str(self.rd.tensorboard), purge_step=self.next_frame if resume else None)

    def _keyframe_fraction(self) -> float:
        return 0.005 if self.cfg.slam.keyframe_variant else self.cfg.slam.keyframe_fraction

    def write_run_info(self, status: str) -> None:
        intr = self.dataset.intrinsics
        info = {
            "status": status,
            "dataset": {"kind": getattr(self.dataset, "name", "?"), "root": str(getattr(self.dataset, "root", "")),
                        "frames": self.n_frames},
            "intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
                           "width": intr.width, "height": intr.height},
            "bounds": self.bounds.tolist(),
            "bounds_source": ("estimated from the depth of the first frames with their ground-truth poses"
                              if getattr(self.dataset, "bounds_estimated", False) else "dataset / config"),
            "gt_mesh": str(self.dataset.gt_mesh) if getattr(self.dataset, "gt_mesh", None) else None,
            "keyframes": list(self.store.frame_ids),
            "timestamps": self.timestamps[: self.next_frame].tolist(),
            "frames_processed": self.next_frame,
            "versions": {"inrslam": inrslam.__version__, "torch": torch.__version__, "numpy": np.__version__,
                         "python": platform.python_version()},
            "device": str(self.device),
            "threads": self.threads if self.threads is not None else torch.get_num_threads(),
            "encoding": self.cfg.field.encoding,
            "render": self.cfg.render.name,
        }
        write_json(self.rd.run_info, info)

    # -- checkpoint -----------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        log = self.rd.log
        return {
            "next_frame": self.next_frame,
            "model": self.model.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "store": self.store.state_dict(),
            "est": self.est.cpu(),
            "rel": self.rel.cpu(), "rel_kf": self.rel_kf,
            "gt": self.gt,
            "timestamps": self.timestamps,
            "generator": self.generator.get_state(),
            "track_ms": self.track_ms, "map_ms": self.map_ms, "init_ms": self.init_ms,
            "proc_psnr": self.proc_psnr, "proc_depth_l1": self.proc_depth_l1, "events": self.events,
            "gicp_kfs": list(self.gicp_kfs),
            "log_bytes": log.stat().st_size if log.exists() else 0,
            "wall_s": self.wall_s_before + time.perf_counter() - self._t_start,
            "peak_mb": self._peak_memory_mb(),
        }

    def save_checkpoint(self) -> None:
        with atomic_path(self.rd.checkpoint) as tmp:
            torch.save(self.state_dict(), tmp)

    def load_checkpoint(self) -> None:
        path = self.rd.checkpoint
        if not path.is_file():
            raise ConfigError(f"{path}: no checkpoint to resume from")
        st = torch.load(path, map_location="cpu", weights_only=False)
        self.model.load_state_dict(st["model"])
        for k, o in self.optimizers.items():
            o.load_state_dict(st["optimizers"][k])
        self.store.load_state_dict(st["store"])
        self.est = st["est"].to(self.device)
        if "rel" in st:  # checkpoints from before the relative trajectory lack it (those frames stay absolute)
            self.rel, self.rel_kf = st["rel"].to(self.device), st["rel_kf"]
        self.gt, self.timestamps = st["gt"], st["timestamps"]
        self.generator.set_state(st["generator"])
        self.track_ms, self.map_ms, self.init_ms = st["track_ms"], st["map_ms"], st["init_ms"]
        self.proc_psnr, self.proc_depth_l1, self.events = st["proc_psnr"], st["proc_depth_l1"], st["events"]
        self.next_frame = st["next_frame"]
        self.gicp_kfs = list(st.get("gicp_kfs", [0]))
        self.wall_s_before = st["wall_s"]
        self.peak_mb_before = st["peak_mb"]
        log = self.rd.log
        if log.exists():  # drop records written after the checkpoint, so the resumed log equals an uninterrupted one
            with open(log, "rb+") as f:
                f.truncate(st["log_bytes"])

    # -- the loop ----------------------------------------------------------------------------------------------
    def run(self, resume: bool = False) -> Path:
        """Process every frame, then write the trajectory, mesh and process metrics. Returns the run directory."""
        self.out.mkdir(parents=True, exist_ok=True)
        if resume:
            self.load_checkpoint()
        else:
            self.rd.log.write_text("")
        self.write_run_info("running")
        self._open_tensorboard(resume)
        self._t_start = time.perf_counter()
        ck_every = self.cfg.slam.checkpoint_every
        for i in range(self.next_frame, self.n_frames):
            frame = self.dataset[i]
            self._process(i, frame)
            self.next_frame = i + 1
            if self.cfg.slam.mesh_every and (i + 1) % self.cfg.slam.mesh_every == 0:
                self._write_mesh(self.rd.mesh_at(i))
            if ck_every and (i + 1) % ck_every == 0 and i + 1 < self.n_frames:
                self.save_checkpoint()
            if self.progress:
                self.progress(i, self.n_frames, self._progress_info(i))
        self.save_checkpoint()
        wall_s = self.wall_s_before + time.perf_counter() - self._t_start
        self._finish(wall_s)
        if self.tb is not None:
            self.tb.close()
        return self.out

    def _progress_info(self, i: int) -> dict:
        """What a progress display may show: last tracking time, and the trajectory so far with its GT."""
        return {"track_ms": self.track_ms[-1] if self.track_ms else 0.0,
                "est": self.est[: i + 1], "gt": self.gt[: i + 1]}

    def _process(self, i: int, frame: Frame) -> None:
        cfg = self.cfg.slam
        ft = FrameTensors(frame, self.device)
        self.timestamps[i] = frame.timestamp
        self.model.renderer.set_progress(i / max(self.n_frames - 1, 1))  # NeuS cosine annealing, if enabled
        if frame.pose_valid and np.all(np.isfinite(frame.c2w)):
            self.gt[i] = frame.c2w
        n_valid_depth = int((ft.depth > 0).sum())
        if i == 0:
            c2w0 = torch.as_tensor(frame.c2w if frame.pose_valid else np.eye(4), dtype=torch.float32,
                                   device=self.device)
            self.est[0] = c2w0
            t0 = time.perf_counter()
            hist = initialise(self.model, self.optimizers,
                              lambda n: (c2w0,) + ft.sample(n, self.generator), cfg.init_iters, cfg.init_pixels,
                              self.generator)
            self.init_ms = (time.perf_counter() - t0) * 1e3
            self._log({"type": "init", "frame": 0, "iters": len(hist), "loss_first": hist[0] if hist else None,
                       "loss_last": hist[-1] if hist else None, "init_ms": self.init_ms})
            self._add_keyframe(0, ft)
            return
        prev = self.est[i - 1]
        pred = constant_velocity(prev, self.est[i - 2] if (i >= 2 and cfg.const_velocity) else None)
        t0 = time.perf_counter()
        extra: dict = {}
        fallback: str | None
        if cfg.init is PoseInit.GICP:
            pred = self._gicp_init(i, frame, pred, extra)
        if n_valid_depth == 0:
            # no depth: colour-only tracking is ill-posed at the paper's settings; keep the prediction
            c2w, loss, fallback, iters = pred, float("nan"), "no_valid_depth", 0
        else:
            if cfg.sdf_track.iters > 0 and (not cfg.sdf_track.only_on_init_failure or "init_fallback" in extra):
                pred = self._sdf_refine(ft, pred, extra)
            if cfg.track_iters > 0 and (not cfg.track_only_on_init_failure or "init_fallback" in extra):
                dirs, rgb, depth = ft.sample(cfg.track_pixels, self.generator, edge=cfg.track_edge)
                res = track_frame(self.model, pred, dirs, rgb, depth, cfg, self.generator, cfg.max_pose_jump)
                c2w, loss, fallback, iters = res.c2w, res.best_loss, res.fallback, res.iters
            else:  # geometric tracking only
                c2w, loss, fallback, iters = pred, float("nan"), None, 0
        track_ms = (time.perf_counter() - t0) * 1e3
        self.track_ms.append(track_ms)
        self.est[i] = c2w
        kf = self.store.frame_ids[-1]
        self.rel[i] = torch.linalg.inv(self.est[kf]) @ c2w
        self.rel_kf[i] = kf
        fallback = ",".join(f for f in (extra.pop("init_fallback", None), extra.pop("sdf_fallback", None), fallback)
                            if f)
        rec = {"type": "track", "frame": i, "loss": loss, "track_ms": track_ms, "iters": iters, **extra}
        if fallback:
            rec["fallback"] = fallback
            self.events.append({"frame": i, "event": fallback})
        self._log(rec)
        if i % cfg.map_every == 0:
            self._map(i, ft)

    def _gicp_init(self, i: int, frame: Frame, pred: torch.Tensor, rec: dict) -> torch.Tensor:
        """GICP of frame i's depth onto its target (`slam.gicp.target`: frame i-1, the GICP keyframe, or a local map
        of the last GICP keyframes) from the prediction; the prediction when a check fails (the reason goes to `rec`
        as init_fallback). Targets are kept in memory and rebuilt from the dataset after a resume."""
        g = self.cfg.slam.gicp
        points = depth_points(frame.depth, frame.intrinsics, g)
        cur = PreparedCloud(points, g)
        if g.target is GicpTarget.LOCAL_MAP:
            t_idx, target, base = self.gicp_kfs[-1], self._local_map(g), np.eye(4)
        else:
            t_idx = i - 1 if g.target is GicpTarget.PREVIOUS else self.gicp_kfs[-1]
            if self._target_cloud is None or self._target_cloud[0] != t_idx:
                t_frame = self.dataset[t_idx]
                self._target_cloud = (t_idx, prepare_depth(t_frame.depth, t_frame.intrinsics, g))
            target, base = self._target_cloud[1], self.est[t_idx].double().cpu().numpy()
        reg = register(target, cur, np.linalg.inv(base) @ pred.double().cpu().numpy(), g)
        rec.update(gicp_fitness=round(reg.fitness, 4), gicp_degeneracy=round(reg.degeneracy, 4), gicp_target=t_idx)
        c2w = base @ reg.T_target_source
        if g.target is GicpTarget.PREVIOUS:
            self._target_cloud = (i, cur)
        else:
            from_kf = (reg.T_target_source if g.target is GicpTarget.KEYFRAME
                       else np.linalg.inv(self.est[self.gicp_kfs[-1]].double().cpu().numpy()) @ c2w)
            if not reg.ok or moved_beyond(from_kf, g.kf_dist, g.kf_angle) or reg.fitness < g.kf_fitness:
                self.gicp_kfs.append(i)  # the target of the next frames (placed at its tracked pose)
                self._target_cloud = (i, cur)
                if g.target is GicpTarget.LOCAL_MAP:
                    self._kf_points[i] = points  # no second read of this frame when the local map is rebuilt
        if not reg.ok:
            rec["init_fallback"] = f"gicp_{reg.reason}"
            return pred
        return torch.as_tensor(c2w, dtype=pred.dtype, device=pred.device)

    def _local_map(self, g) -> PreparedCloud:
        """World-frame cloud of the last `g.local_map_keyframes` GICP keyframes at their current poses (cached)."""
        ids = tuple(self.gicp_kfs[-g.local_map_keyframes:])
        if self._local_target is None or self._local_target[0] != ids:
            pts = []
            for k in ids:
                if k not in self._kf_points:  # frame 0, or keyframes from before a resume
                    f = self.dataset[k]
                    self._kf_points[k] = depth_points(f.depth, f.intrinsics, g)
                T = self.est[k].double().cpu().numpy()
                pts.append(self._kf_points[k] @ T[:3, :3].T + T[:3, 3])
            for k in [k for k in self._kf_points if k not in ids]:
                del self._kf_points[k]
            self._local_target = (ids, PreparedCloud(np.concatenate(pts), g))
        return self._local_target[1]

    def _sdf_refine(self, ft: "FrameTensors", pred: torch.Tensor, rec: dict) -> torch.Tensor:
        """Point-to-surface Gauss-Newton against the map from `pred` (slam.sdf_track)."""
        sc = self.cfg.slam.sdf_track
        valid = torch.nonzero(ft.depth > 0).squeeze(1)
        if valid.numel() > sc.points:
            valid = valid[torch.randperm(valid.numel(), generator=self.generator)[: sc.points].to(valid.device)]
        dirs, _, depth = ft.rays(valid)
        res = align_to_sdf(self.model.field, pred, dirs * depth[:, None], self.model.truncation, sc)
        rec.update(sdf_iters=res.iters, sdf_points=res.n_used, sdf_rms_mm=round(res.rms * 1e3, 3)
                   if math.isfinite(res.rms) else None)
        if res.fallback:
            rec["sdf_fallback"] = res.fallback
        return res.c2w

    def _map(self, i: int, ft: FrameTensors) -> None:
        cfg = self.cfg.slam
        kf_ids = list(self.store.frame_ids)
        t0 = time.perf_counter()
        res = map_frame(self.model, self.optimizers, self.store, self.est[kf_ids], self.est[i],
                        lambda n: ft.sample(n, self.generator), cfg, self.generator)
        map_ms = (time.perf_counter() - t0) * 1e3
        self.map_ms.append(map_ms)
        fallback = None
        if bool(torch.isfinite(res.kf_c2w).all()) and bool(torch.isfinite(res.cur_c2w).all()):
            self.est[kf_ids] = res.kf_c2w
            self.est[i] = res.cur_c2w
        else:  # keep the poses from before bundle adjustment
            fallback = "ba_nan"
        if res.skipped:
            fallback = (fallback + "," if fallback else "") + f"nan_loss_x{res.skipped}"
        if fallback:
            self.events.append({"frame": i, "event": fallback})
        self.proc_psnr += res.psnr
        self.proc_depth_l1 += [d for d in res.depth_l1 if math.isfinite(d)]
        self._log({"type": "map", "frame": i, "map_ms": map_ms, "keyframes": len(kf_ids),
                   "loss": res.losses[-1] if res.losses else None,
                   "psnr": float(np.mean(res.psnr)) if res.psnr else None,
                   "depth_l1": float(np.nanmean(res.depth_l1)) if res.depth_l1 else None,
                   **({"fallback": fallback} if fallback else {})})
        self._add_keyframe(i, ft)

    def _add_keyframe(self, i: int, ft: FrameTensors) -> None:
        H, W = ft.intr.height, ft.intr.width
        n = max(1, int(round(self._keyframe_fraction() * H * W)))
        idx = torch.randperm(H * W, generator=self.generator)[:n].to(self.device)
        dirs, rgb, depth = ft.rays(idx)
        self.store.add(i, dirs, rgb, depth)

    # -- outputs -------------------------------------------------------------------------------------------------
    def _write_mesh(self, path: Path) -> bool:
        m = self.cfg.mesh
        mesh = extract_mesh(self.model.field, self.bounds, m.resolution, m.chunk, m.color)
        if mesh is None:
            self.events.append({"frame": self.next_frame - 1, "event": "empty_mesh"})
            return False
        with atomic_path(path) as tmp:
            mesh.export(tmp)
        return True

    def _peak_memory_mb(self) -> float:
        """Peak memory of this run (max over resumed segments): CUDA allocator peak, or the process's max RSS."""
        if self.device.type == "cuda":
            now = torch.cuda.max_memory_allocated(self.device) / 2**20
        else:
            now = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB
        return max(now, self.peak_mb_before)

    def _finish(self, wall_s: float) -> None:
        from inrslam.fields import model_size_mb

        est = self.est.double().cpu().numpy()
        write_tum(self.rd.trajectory, self.timestamps, est, header="inrslam estimated c2w (OpenCV axes)")
        write_tum(self.rd.trajectory_relative, self.timestamps,
                  relative_trajectory(est, self.rel.double().cpu().numpy(), self.rel_kf, self.store.frame_ids),
                  header="inrslam estimated c2w, non-keyframes relative to their refined keyframe (spec 7.6)")
        if np.isfinite(self.gt).all(axis=(1, 2)).any():
            write_tum(self.rd.trajectory_gt, self.timestamps, self.gt, header="ground-truth c2w (OpenCV axes)")
        write_json(self.rd.keyframes, {"keyframes": list(self.store.frame_ids)})
        if self.cfg.mesh.enabled:
            self._write_mesh(self.rd.mesh)
        metrics = {
            "frames": self.n_frames,
            "track_ms_per_frame": float(np.mean(self.track_ms)) if self.track_ms else None,
            "map_ms_per_call": float(np.mean(self.map_ms)) if self.map_ms else None,
            "init_ms": self.init_ms,
            "wall_time_s": wall_s,
            "model_size_mb": model_size_mb(self.model.field),
            "model_size_with_optimizer_mb": model_size_mb(self.model.field, with_optimizer=True),
            "peak_memory_mb": self._peak_memory_mb(),
            "psnr_process_db": float(np.mean(self.proc_psnr)) if self.proc_psnr else None,
            "depth_l1_process_m": float(np.mean(self.proc_depth_l1)) if self.proc_depth_l1 else None,
            "fallbacks": len(self.events),
            "encoding": self.cfg.field.encoding,
            "render": self.cfg.render.name,
        }
        self.rd.write_metrics(metrics)
        self.write_run_info("slam_done")
