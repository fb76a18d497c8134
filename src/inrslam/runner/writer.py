"""`RunWriter`: everything a SLAM run writes into its run directory (layout: `inrslam.io.rundir.RunDir`).

The loop (`inrslam.slam.system.SlamSystem`) computes; the writer logs its records (`log.jsonl`, TensorBoard),
keeps `run_info.json` current, saves and restores checkpoints, and writes the trajectories, keyframes, meshes and
process metrics at the end. It also owns what only the process knows: wall time and peak memory over the resumed
segments of a run.
"""

from __future__ import annotations

import math
import platform
import resource
import time
import traceback
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
import trimesh
from trimesh.visual.color import ColorVisuals

import inrslam
from inrslam.datasets import absolute_path
from inrslam.errors import InrslamWarning, RunError
from inrslam.io.atomic import append_jsonl, atomic_path, write_json
from inrslam.io.rundir import RunDir
from inrslam.io.trajectory import write_tum
from inrslam.machine import machine
from inrslam.malloc_env import malloc_state
from inrslam.omp_env import wait_policy
from inrslam.runner.checkpoint import IDENTITY, load_checkpoint, save_checkpoint
from inrslam.slam.system import SlamSystem
from inrslam.status import logger, stage

log = logger(__name__)


class RunWriter:
    """Writes the run directory `rd` of `system`.

    Args:
        threads: the torch / numba thread count the run holds (recorded: results are bit-identical only at one
            count); None = whatever the process has set.
    """

    def __init__(self, system: SlamSystem, rd: RunDir, threads: int | None = None):
        self.system = system
        self.rd = rd
        self.cfg = system.cfg
        self.threads = threads
        self.tb: Any = None  # TensorBoard SummaryWriter when enabled
        self.wall_s_before = 0.0  # wall time of earlier (interrupted) segments of this run
        self.peak_mb_before = 0.0  # peak memory of earlier segments
        self._t_start = time.perf_counter()
        self.failures: list[str] = []  # post-SLAM steps that failed (see `step`)

    # -- start ---------------------------------------------------------------------------------------------------
    def start(self, resume: bool) -> None:
        """Open the run: a fresh log, or the checkpointed state and the log cut back to it (so a resumed run's log
        equals an uninterrupted one); remove temporary files a killed write left; mark the run as running."""
        self.rd.root.mkdir(parents=True, exist_ok=True)
        self.rd.remove_stale_temporaries()
        if resume:
            self._restore()
        else:
            self.rd.log.write_text("")
        self.write_run_info("running")
        self._open_tensorboard(resume)
        self._t_start = time.perf_counter()

    def _identity(self) -> dict:
        """What a checkpoint must agree on to belong to this run."""
        ident = {"frames": self.system.n_frames, "encoding": self.cfg.field.encoding, "render": self.cfg.render.name,
                 "seed": self.cfg.seed}
        if self.system.given is not None:  # a changed pose file must not continue a map built on the old one
            ident["poses"] = self.system.given.source.get("sha256", "gt")
        return ident

    def _restore(self) -> None:
        st = load_checkpoint(self.rd.checkpoint, self._identity())
        try:
            self.system.state.load_state_dict(st)
        except (KeyError, RuntimeError, ValueError) as e:  # e.g. parameter shapes of another field configuration
            reason = str(e).splitlines()[0][:160]
            raise RunError(f"{self.rd.checkpoint}: the checkpoint does not fit this run's config.yaml ({reason}): "
                           f"start the run again with --overwrite") from None
        self.wall_s_before, self.peak_mb_before = st["wall_s"], st["peak_mb"]
        log = self.rd.log
        if log.exists():
            with open(log, "rb+") as f:
                f.truncate(st["log_bytes"])

    def _open_tensorboard(self, resume: bool) -> None:
        """TensorBoard writer (optional). On resume, events from the checkpointed frame on are purged, so that
        the records logged again after the checkpoint do not show twice."""
        if not self.cfg.output.tensorboard:
            return
        try:
            from torch.utils.tensorboard import SummaryWriter
        except Exception:  # tensorboard not installed: optional, but it was asked for
            msg = ("output.tensorboard=true but tensorboard is not installed (pip install tensorboard); this run "
                   "writes no TensorBoard scalars (set output.tensorboard=false to silence this)")
            warnings.warn(msg, InrslamWarning, stacklevel=2)
            return
        self.tb = SummaryWriter(str(self.rd.tensorboard),
                                purge_step=self.system.state.next_frame if resume else None)

    # -- during the run ------------------------------------------------------------------------------------------
    def log(self, records: list[dict]) -> None:
        """Append records to log.jsonl (flushed each) and their finite numbers to TensorBoard."""
        for record in records:
            append_jsonl(self.rd.log, record)
            if self.tb is not None:
                step = record.get("frame", 0)
                for k, v in record.items():
                    if isinstance(v, (int, float)) and k != "frame" and math.isfinite(v):
                        self.tb.add_scalar(f"{record.get('type', 'log')}/{k}", v, step)

    def after_frame(self, i: int) -> bool:
        """Intermediate mesh (slam.mesh_every) and checkpoint (slam.checkpoint_every) after frame i; whether it
        saved a checkpoint."""
        s = self.cfg.slam
        n = self.system.n_frames
        if s.mesh_every and (i + 1) % s.mesh_every == 0:
            self.write_mesh(self.system.mesh(), self.rd.mesh_at(i))
        if s.checkpoint_every and (i + 1) % s.checkpoint_every == 0 and i + 1 < n:
            self.checkpoint()
            return True
        return False

    def checkpoint(self) -> None:
        """Save the loop's state with this process's bookkeeping (atomic; verified when loaded)."""
        log = self.rd.log
        save_checkpoint(self.rd.checkpoint, {
            **self.system.state.state_dict(),
            "log_bytes": log.stat().st_size if log.exists() else 0,
            "wall_s": self.wall_s(),
            "peak_mb": self.peak_memory_mb(),
            IDENTITY: self._identity(),
        })

    def wall_s(self) -> float:
        """Wall time of the run over all its segments, seconds."""
        return self.wall_s_before + time.perf_counter() - self._t_start

    def peak_memory_mb(self) -> float:
        """Peak memory of this run (max over resumed segments): CUDA allocator peak, or the process's max RSS."""
        dev = self.system.device
        if dev.type == "cuda":
            now = torch.cuda.max_memory_allocated(dev) / 2**20
        else:
            now = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB
        return max(now, self.peak_mb_before)

    def write_mesh(self, mesh: trimesh.Trimesh | None, path: Path) -> None:
        if mesh is not None:
            with atomic_path(path) as tmp:
                mesh.export(tmp)

    def write_mesh_thumbnail(self, mesh: trimesh.Trimesh, poses: np.ndarray) -> None:
        """mesh.png (atomic): `eval.mesh_thumbnail` of the final mesh, the up axis taken from the (N, 4, 4) c2w
        `poses` (NaN rows ignored)."""
        from PIL import Image

        from inrslam.eval.mesh_thumbnail import mesh_thumbnail, up_direction

        visual = mesh.visual
        colors = visual.vertex_colors if isinstance(visual, ColorVisuals) and visual.kind == "vertex" else None
        picture = mesh_thumbnail(mesh.vertices, mesh.faces, colors, up_direction(poses))
        with atomic_path(self.rd.mesh_thumbnail) as tmp:
            Image.fromarray(picture).save(tmp, format="PNG")

    def write_render(self, frame: int, picture: np.ndarray) -> None:
        """renders/frame_NNNNNN.png (atomic): a held-out frame's (H, 4W, 3) uint8 panel (eval.heldout.heldout_panel)."""
        from PIL import Image

        path = self.rd.render_at(frame)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            Image.fromarray(picture).save(tmp, format="PNG")
        self._tensorboard_image(f"heldout/frame_{frame:06d}", picture)

    def _tensorboard_image(self, tag: str, picture: np.ndarray) -> None:
        """Also log an (H, W, 3) uint8 picture to TensorBoard (when its writer is open: output.tensorboard and
        tensorboard installed), at the run's last frame as step, in the same event file as the run's scalars."""
        if self.tb is not None:
            self.tb.add_image(tag, picture, global_step=self.system.n_frames - 1, dataformats="HWC")
            self.tb.flush()

    def close_tensorboard(self) -> None:
        """Close the TensorBoard writer if one is open (after the held-out pictures: `finish` leaves it open)."""
        if self.tb is not None:
            self.tb.close()
            self.tb = None

    def write_run_info(self, status: str) -> None:
        """run_info.json: status, dataset (absolute paths), intrinsics, bounds, keyframes, versions, device, the
        machine (CPU model, cores, cache, memory: `inrslam.machine`), threads and their OpenMP wait policy."""
        sysm, ds = self.system, self.system.dataset
        st = sysm.state
        intr = ds.intrinsics
        root = getattr(ds, "root", None)
        gt_mesh = getattr(ds, "gt_mesh", None)
        info = {
            "status": status,
            "dataset": {"kind": getattr(ds, "name", "?"), "root": str(absolute_path(root)) if root else "",
                        "frames": sysm.n_frames},
            "intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
                           "width": intr.width, "height": intr.height},
            "bounds": sysm.bounds.tolist(),
            "bounds_source": ("estimated from the depth of the first frames with their ground-truth poses"
                              if getattr(ds, "bounds_estimated", False) else "dataset / config"),
            "gt_mesh": str(absolute_path(gt_mesh)) if gt_mesh else None,
            "keyframes": list(st.store.frame_ids),
            "timestamps": st.timestamps[: st.next_frame].tolist(),
            "frames_processed": st.next_frame,
            "versions": {"inrslam": inrslam.__version__, "torch": torch.__version__, "numpy": np.__version__,
                         "python": platform.python_version()},
            "device": str(sysm.device),
            "machine": machine(),
            "threads": self.threads if self.threads is not None else torch.get_num_threads(),
            "omp_wait_policy": wait_policy(),
            "malloc": malloc_state(),
            "poses": sysm.given.source if sysm.given is not None else {"source": "tracked"},
            "encoding": self.cfg.field.encoding,
            "render": self.cfg.render.name,
        }
        write_json(self.rd.run_info, info)

    @contextmanager
    def step(self, name: str) -> Iterator[None]:
        """Run a post-SLAM step; if it raises, log the error with its traceback and carry on with the next one."""
        try:
            yield
        except Exception as e:  # any failure: the remaining steps still write what they can
            self.failures.append(f"{name} failed ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})")
            self.log([{"type": "error", "step": name, "error": f"{type(e).__name__}: {e}",
                       "traceback": traceback.format_exc()}])

    # -- end -------------------------------------------------------------------------------------------------------
    def finish(self) -> dict:
        """Final checkpoint, trajectories (and trajectory.png), keyframes.json, mesh.ply (and mesh.png); returns the
        process metrics (the caller adds what it evaluates and writes metrics.json once)."""
        self.checkpoint()
        wall_s = self.wall_s()
        rd = self.rd
        res = self.system.result()
        write_tum(rd.trajectory, res.timestamps, res.est, header="inrslam estimated c2w (OpenCV axes)")
        write_tum(rd.trajectory_relative, res.timestamps, res.relative,
                  header="inrslam estimated c2w, non-keyframes relative to their refined keyframe (spec 7.6)")
        if np.isfinite(res.gt).all(axis=(1, 2)).any():
            write_tum(rd.trajectory_gt, res.timestamps, res.gt, header="ground-truth c2w (OpenCV axes)")
            if self.cfg.output.renders:
                from inrslam.eval.trajectory_plot import plot_trajectory

                with self.step("trajectory plot"):
                    plot_trajectory(res.est, res.gt, rd.trajectory_plot)
        write_json(rd.keyframes, {"keyframes": res.keyframes})
        if self.cfg.mesh.enabled:
            mesh = None
            stage(log, f"extracting the mesh (marching cubes, {self.cfg.mesh.resolution * 100:g} cm grid)")
            with self.step("mesh extraction"):
                mesh = self.system.mesh()
                self.write_mesh(mesh, rd.mesh)
            if mesh is not None and self.cfg.output.renders:
                stage(log, f"drawing mesh.png ({len(mesh.faces)} triangles)")
                with self.step("mesh thumbnail"):
                    self.write_mesh_thumbnail(mesh, res.est)
        process = {"wall_time_s": wall_s, "peak_memory_mb": self.peak_memory_mb()}
        # metrics after the mesh: an empty mesh is an event they count; dict order: METRIC_ORDER first
        return {**dict.fromkeys(METRIC_ORDER), **self.system.process_metrics(), **process}


# key order of the process metrics in metrics.json (docs/metrics.md)
METRIC_ORDER = ("frames", "track_ms_per_frame", "map_ms_per_call", "map_ms_per_frame", "init_ms", "wall_time_s",
                "model_size_mb", "model_size_with_optimizer_mb", "peak_memory_mb", "psnr_process_db",
                "depth_l1_process_m", "fallbacks", "lost_frames", "encoding", "render", "poses")

