"""The SLAM loop (docs/spec.md §1, §7): initialise on frame 0, track every frame, map + bundle-adjust every
`map_every`-th frame. It computes and returns; it writes no file. The run writer (`inrslam.runner`) drives it frame by
frame and writes the run directory, the log and the checkpoints."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import numpy as np
import torch
import trimesh

from inrslam.data.frame import Frame, RGBDDataset, checked_frame, repeated_streams
from inrslam.data.given_poses import GivenPoses, load_given_poses
from inrslam.errors import ConfigError, DataError, TrackingLost
from inrslam.geometry.se3 import mean_pose
from inrslam.slam.config import GicpConfig, GicpTarget, MeshConfig, PoseInit, SlamConfig
from inrslam.slam.frame_tensors import FrameTensors
from inrslam.slam.keyframes import KeyframeStore
from inrslam.slam.loop_closure import (
    color_confirms,
    color_disagreement,
    consistent,
    corrected_keyframes,
    follow_keyframes,
    nearby_keyframes,
    new_place,
    overlap,
    path_length,
    significant,
    stage_clouds,
    verify,
)
from inrslam.slam.mapping import initialise, map_frame, refit
from inrslam.slam.mesh_extraction import extract_mesh
from inrslam.slam.model import ModelConfig, SceneModel
from inrslam.slam.photometric import PhotoLevel, align_photometric, grey, jump_kept, step_bound
from inrslam.slam.poses import constant_velocity, relative_pose, relative_trajectory
from inrslam.slam.registration import (
    PreparedCloud,
    depth_noise,
    depth_points,
    filtered_depth,
    min_points,
    moved_beyond,
    prepare_depth,
    register,
)
from inrslam.slam.sdf_tracking import align_to_sdf
from inrslam.slam.state import SlamState
from inrslam.slam.tracking import TrackResult, track_frame
from inrslam.slam.trajectory_graph import frame_pyramid, photometric_links, refine_trajectory

Rays = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # dirs_cam (R, 3), rgb (R, 3), depth (R,) metres
MIN_IMAGE_SIZE = 16  # pixels per side (held-out SSIM uses an 11-px window; tracking keeps a border)

# (frame index, n_frames, info) -> None, called after every frame; info: see `SlamSystem.progress_info`
Progress = Callable[[int, int, dict], None]


class SlamRunConfig(ModelConfig, Protocol):
    """The sections of a run's config the loop reads (`inrslam.config.RunConfig` has them; it sits above slam)."""

    slam: SlamConfig
    mesh: MeshConfig
    seed: int
    device: str


def resolve_device(name: str) -> torch.device:
    """'auto' -> cuda if available else cpu."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"config key 'device': {name!r} requested but CUDA is not available")
    return dev


def _joined(*events: str | None) -> str:
    """The events that happened, comma-joined as a log record's `fallback` ("" when none)."""
    return ",".join(e for e in events if e)


@dataclass
class SlamResult:
    """What a finished loop hands to its writer (numpy, float64 c2w in OpenCV axes).

    est: (N, 4, 4) estimated poses; relative: (N, 4, 4) non-keyframes carried by their refined keyframe
    (docs/spec.md §7.6); gt: (N, 4, 4) ground truth (NaN = none); timestamps: (N,) seconds; keyframes: frame ids;
    metrics: the process metrics of docs/metrics.md (timings, model size, PSNR while mapping, fallbacks).
    """

    est: np.ndarray
    relative: np.ndarray
    gt: np.ndarray
    timestamps: np.ndarray
    keyframes: list[int]
    metrics: dict[str, Any]


class SlamSystem:
    """SLAM on `dataset` with the resolved config `cfg`; `state` holds all that a checkpoint saves.

    Use: `process(i)` for i = state.next_frame .. n_frames - 1 (each returns the frame's log records), then
    `mesh()` and `result()`. `run()` does all frames in memory (benchmarks, notebooks).
    """

    def __init__(self, cfg: SlamRunConfig, dataset: RGBDDataset):
        self.cfg = cfg
        self.dataset = dataset
        self.device = resolve_device(cfg.device)
        torch.manual_seed(cfg.seed)
        self.n_frames = len(dataset)
        if self.n_frames == 0:
            raise ConfigError(f"dataset {getattr(dataset, 'root', '?')} has no frames")
        intr = dataset.intrinsics
        if min(intr.width, intr.height) < MIN_IMAGE_SIZE:
            raise DataError(f"{getattr(dataset, 'root', 'dataset')}: frames are {intr.width}x{intr.height} px; the "
                            f"SLAM loop needs at least {MIN_IMAGE_SIZE}x{MIN_IMAGE_SIZE}")
        self.bounds = np.asarray(dataset.bounds, dtype=np.float64)
        sc = cfg.slam
        # mapping only (slam.poses): every frame's pose is given, nothing is tracked, poses stay fixed
        self.given: GivenPoses | None = (load_given_poses(sc.poses, dataset, sc.poses_tolerance, sc.poses_anchor)
                                         if sc.poses else None)
        self.model = self._make_model().to(self.device)
        self.state = SlamState.fresh(self.model, self.model.make_optimizers(cfg.slam.map_lr),
                                     KeyframeStore(device=self.device), torch.Generator().manual_seed(cfg.seed),
                                     self.n_frames, self.device)
        self._records: list[dict] = []
        # GICP targets, kept in memory only (rebuilt from the dataset after a resume): (frame index, cloud) of the
        # previous frame / keyframe, (keyframe ids, cloud) of the local map, camera-frame points of its keyframes
        self._target_cloud: tuple[int, PreparedCloud] | None = None
        self._local_target: tuple[tuple[int, ...], PreparedCloud] | None = None
        self._kf_points: dict[int, np.ndarray] = {}
        # pyramids of the last slam.photo.kf_refs photometric keyframes, in memory only (rebuilt from the dataset
        # after a resume)
        self._photo_pyrs: dict[int, list[PhotoLevel]] = {}
        self._gicp_information: np.ndarray | None = None  # the current frame's GICP information (`pose_information`)
        self._prev_frame: Frame | None = None  # the previous frame (slam.photo.skip_stale), in memory only

    def _make_model(self) -> SceneModel:
        """The map the loop trains (a subclass with another mapper may return its own `SceneModel` subclass)."""
        return SceneModel(self.cfg, self.bounds)

    # -- shorthands of the state --------------------------------------------------------------------------------
    @property
    def est(self) -> torch.Tensor:
        """(N, 4, 4) estimated c2w so far (NaN = not processed)."""
        return self.state.est

    @property
    def generator(self) -> torch.Generator:
        return self.state.generator

    @property
    def store(self) -> KeyframeStore:
        return self.state.store

    # -- driving -------------------------------------------------------------------------------------------------
    def process(self, i: int, frame: Frame | None = None) -> list[dict]:
        """Process frame i (must be `state.next_frame`); returns its log records (init / track / map)."""
        if i != self.state.next_frame:
            raise ValueError(f"frame {i} processed out of order (next is {self.state.next_frame})")
        self._records = []
        self._process(i, self._frame(i) if frame is None else checked_frame(frame, self.dataset.intrinsics))
        self.state.next_frame = i + 1
        return self._records

    def run(self, progress: Progress | None = None) -> "SlamSystem":
        """Process every remaining frame in memory (nothing is written)."""
        for i in range(self.state.next_frame, self.n_frames):
            self.process(i)
            if progress:
                progress(i, self.n_frames, self.progress_info(i))
        return self

    def progress_info(self, i: int) -> dict:
        """What a progress display or live viewer may show: last tracking time, the trajectory so far (N, 4, 4) with
        its GT, the keyframe ids, and `mesh(resolution)`: a marching-cubes mesh of the current map at `resolution`
        metres (None if empty; logs nothing, changes nothing the run saves)."""
        s = self.state
        m = self.cfg.mesh
        return {"track_ms": s.track_ms[-1] if s.track_ms else 0.0, "est": s.est[: i + 1], "gt": s.gt[: i + 1],
                "keyframes": list(s.store.frame_ids),
                "mesh": lambda resolution: extract_mesh(self.model.field, self.bounds, resolution, m.chunk, m.color)}

    def _log(self, record: dict) -> None:
        self._records.append(record)

    def _event(self, i: int, event: str) -> None:
        self.state.events.append({"frame": i, "event": event})

    def _frame(self, k: int) -> Frame:
        """Frame k of the dataset, checked (`checked_frame`: shapes, finite colour, NaN / inf depth read as 0)."""
        return checked_frame(self.dataset[k], self.dataset.intrinsics)

    def _process(self, i: int, frame: Frame) -> None:
        cfg = self.cfg.slam
        noise = depth_noise(frame.depth, cfg.gicp) if cfg.gicp.depth_filter > 0 or cfg.photo.enabled else None
        # the frame's depth after slam.gicp's filter (noisy depth only), once: the map and the photometric pyramid
        smooth = (filtered_depth(frame.depth, cfg.gicp, noise=noise)
                  if noise is not None and (cfg.map_filtered_depth or cfg.photo.enabled) else frame.depth)
        ft = FrameTensors(self._map_frame(frame, smooth), self.device)
        lc = self.cfg.loss
        if lc.silhouette_behind < 1.0:  # mapping rays at depth silhouettes: a shorter SDF band behind the depth
            ft.set_silhouettes(lc.silhouette_behind, lc.silhouette_jump, lc.silhouette_radius)
        self.state.timestamps[i] = frame.timestamp
        self.model.renderer.set_progress(i / max(self.n_frames - 1, 1))  # NeuS cosine annealing, if enabled
        if frame.pose_valid and np.all(np.isfinite(frame.c2w)):
            self.state.gt[i] = frame.c2w
        n_valid_depth = int((ft.depth > 0).sum())
        if i == 0 and n_valid_depth == 0 and self.given is None:
            raise DataError(f"{frame.source or 'frame 0'}: the first frame has no valid depth, so the map cannot be "
                            "initialised and every later frame would look lost; start at a frame with depth "
                            "(data.start=K) or give poses (--poses)")
        if i == 0:
            start = self.given.c2w[0] if self.given is not None else frame.c2w if frame.pose_valid else np.eye(4)
            c2w0 = torch.as_tensor(start, dtype=torch.float32, device=self.device)
            self.est[0] = c2w0
            t0 = time.perf_counter()
            hist = initialise(self.model, self.state.optimizers,
                              lambda n: (c2w0,) + ft.training_rays(ft.sample_index(n, self.generator)),
                              cfg.init_iters, cfg.init_pixels, self.generator, cfg.init_stop_window, cfg.init_stop_tol)
            self.state.init_ms = (time.perf_counter() - t0) * 1e3
            if hist and math.isfinite(hist[-1]):
                self.state.track_losses = [hist[-1]]  # seeds the running loss level of lost-tracking detection
            self._log({"type": "init", "frame": 0, "iters": len(hist), "loss_first": hist[0] if hist else None,
                       "loss_last": hist[-1] if hist else None, "init_ms": self.state.init_ms})
            self._add_keyframe(0, ft)
            return
        if self.given is not None:
            self._place_given(i, ft)
            return
        prev = self.est[i - 1]
        pred = constant_velocity(prev, self.est[i - 2] if (i >= 2 and cfg.const_velocity) else None)
        t0 = time.perf_counter()
        extra: dict = {}
        fallback: str | None
        if noise is not None:
            extra["depth_noise"] = round(noise, 6) if math.isfinite(noise) else None
        self._gicp_information = None
        if cfg.init is PoseInit.GICP:
            pred = self._gicp_init(i, frame, pred, extra, noise)
        cur_pyr = None
        if cfg.photo.enabled and n_valid_depth > 0 and noise is not None and noise >= cfg.photo.min_depth_noise:
            stale = None
            if cfg.photo.skip_stale:
                before, self._prev_frame = self._previous_frame(i), frame
                stale = repeated_streams(before, frame)
            if stale:  # colour and depth from different times: no photometric refinement; GICP onto frame i-1
                extra["stale"] = stale  # (identity where the depth repeats), not onto the local map, which sits
                onto_prev = self._gicp_onto_previous(i, before, frame, pred, cfg.gicp)  # ~1 cm off the image's pose
                pred = pred if onto_prev is None else onto_prev
            else:
                pred, cur_pyr = self._photo_refine(i, frame, pred, smooth, extra)
        if n_valid_depth == 0:
            # no depth: colour-only tracking is ill-posed at the paper's settings; keep the prediction
            c2w, loss, fallback, iters = pred, float("nan"), "no_valid_depth", 0
        else:
            # the neural map tracks a frame whose initialiser failed, unless the photometric refinement took it over;
            # without a geometric initialiser (slam.init=const_velocity) there is nothing to fail: it tracks every one
            init_failed = (cfg.init is not PoseInit.GICP
                           or ("init_fallback" in extra and not extra.get("photo_rescued")))
            if cfg.sdf_track.iters > 0 and (not cfg.sdf_track.only_on_init_failure or init_failed):
                pred = self._sdf_refine(ft, pred, extra)
            if cfg.track_iters > 0 and (not cfg.track_only_on_init_failure or init_failed):
                rays = ft.sample(cfg.track_pixels, self.generator, edge=cfg.track_edge)
                res = track_frame(self.model, pred, *rays, cfg, self.generator, cfg.max_pose_jump)
                if math.isfinite(res.best_loss):
                    res = self._check_lost(i, frame, pred, rays, res, extra)
                c2w, loss, fallback, iters = res.c2w, res.best_loss, res.fallback, res.iters
            else:  # geometric tracking only
                c2w, loss, fallback, iters = pred, float("nan"), None, 0
        self._set_pose(i, c2w)
        if cur_pyr is not None:
            self._renew_photo_keyframe(i, cur_pyr, "photo_fallback" in extra, extra)
        track_ms = (time.perf_counter() - t0) * 1e3
        self.state.track_ms.append(track_ms)
        fallback = _joined(extra.pop("init_fallback", None), extra.pop("photo_fallback", None),
                           extra.pop("sdf_fallback", None), fallback)
        rec = {"type": "track", "frame": i, "loss": loss, "track_ms": track_ms, "iters": iters, **extra}
        if fallback:
            rec["fallback"] = fallback
            self._event(i, fallback)
        self._log(rec)
        if i % cfg.map_every == 0:
            self._map(i, ft)
        if cfg.loop_closure and i == self.n_frames - 1 and self.state.loops:
            self._finish_loops(i)
        if cfg.refine.enabled and i == self.n_frames - 1:
            self._refine_trajectory(i)

    def _map_frame(self, frame: Frame, smooth: np.ndarray) -> Frame:
        """The frame the map learns from: `frame`, or with `smooth`, its depth after slam.gicp's filter
        (`filtered_depth`: noisy depth only), when `slam.map_filtered_depth` is set."""
        if not self.cfg.slam.map_filtered_depth or smooth is frame.depth:
            return frame
        return dataclasses.replace(frame, depth=smooth.astype(np.float32))

    def _set_pose(self, i: int, c2w: torch.Tensor) -> None:
        """Frame i's pose, and the same pose relative to the last keyframe (docs/spec.md §7.6)."""
        self.est[i] = c2w
        kf = self.store.frame_ids[-1]
        self.state.rel[i] = relative_pose(self.est[kf], c2w, self.cfg.slam.faithful_relative)
        self.state.rel_kf[i] = kf

    def _place_given(self, i: int, ft: FrameTensors) -> None:
        """Mapping only: frame i takes its given pose (no tracking), then maps every `map_every`-th frame."""
        assert self.given is not None
        self._set_pose(i, torch.as_tensor(self.given.c2w[i], dtype=torch.float32, device=self.device))
        self._log({"type": "pose", "frame": i, "source": self.given.source["source"]})
        if i % self.cfg.slam.map_every == 0:
            self._map(i, ft)

    def _check_lost(self, i: int, frame: Frame, pred: torch.Tensor, rays: Rays, res: TrackResult,
                    rec: dict) -> TrackResult:
        """Lost-tracking check of frame i's rendered tracking `res` (slam.lost): a loss above factor x the median of
        recent frames is lost. With `recover`, the frame is re-tracked from GICP onto the previous frame and from
        the previous pose, keeping the lowest loss; still lost -> a `tracking_lost` fallback, and after
        `stop_after` consecutive lost frames the run stops with TrackingLost."""
        lc, s = self.cfg.slam.lost, self.state
        level = float(np.median(s.track_losses[-lc.window:])) if s.track_losses else math.inf
        if res.best_loss <= lc.factor * level:
            s.track_losses = (s.track_losses + [res.best_loss])[-lc.window:]
            s.lost_run = 0
            return res
        rec["lost_ratio"] = round(res.best_loss / level, 1)
        if lc.recover:
            cfg = dataclasses.replace(self.cfg.slam, track_iters=2 * self.cfg.slam.track_iters)
            for start in self._recovery_starts(i, frame, pred):
                alt = track_frame(self.model, start, *rays, cfg, self.generator, cfg.max_pose_jump)
                if math.isfinite(alt.best_loss) and alt.best_loss < res.best_loss:
                    res = alt
            rec["recovered_ratio"] = round(res.best_loss / level, 1)
            if res.best_loss <= lc.factor * level:  # its loss stays out of the level: a lost view may not raise it
                s.lost_run = 0
                return dataclasses.replace(res, fallback=_joined(res.fallback, "tracking_recovered"))
        s.lost_run += 1
        if lc.stop_after and s.lost_run >= lc.stop_after:
            raise TrackingLost(
                f"tracking lost for {s.lost_run} consecutive frames up to frame {i} (loss {res.best_loss:.3g}, "
                f"{res.best_loss / level:.0f}x its running level {level:.3g}); the frames before are in the last "
                f"checkpoint. Lower data.stride, set slam.lost.recover=true, or slam.lost.stop_after=0 to go on")
        return dataclasses.replace(res, fallback=_joined(res.fallback, "tracking_lost"))

    def _recovery_starts(self, i: int, frame: Frame, pred: torch.Tensor) -> list[torch.Tensor]:
        """Starting poses to re-track a lost frame from: GICP of its depth onto the previous frame's with a wide
        correspondence distance (from the prediction), and the previous pose (no motion)."""
        g = dataclasses.replace(self.cfg.slam.gicp, max_corr=self.cfg.slam.lost.recover_max_corr, max_step=1.0,
                                min_fitness=0.3)
        wide = self._gicp_onto_previous(i, self._frame(i - 1), frame, pred, g)
        return ([] if wide is None else [wide]) + [self.est[i - 1].clone()]

    def _gicp_onto_previous(self, i: int, prev: Frame, frame: Frame, pred: torch.Tensor,
                            g: GicpConfig) -> torch.Tensor | None:
        """Frame i's pose by GICP (settings `g`) of its depth onto frame i-1's (`prev`, at its estimated pose), from
        `pred`; None when the registration fails a check."""
        base = self.est[i - 1].double().cpu().numpy()
        reg = register(prepare_depth(prev.depth, prev.intrinsics, g), prepare_depth(frame.depth, frame.intrinsics, g),
                       np.linalg.inv(base) @ pred.double().cpu().numpy(), g)
        return torch.as_tensor(base @ reg.T_target_source, dtype=pred.dtype, device=pred.device) if reg.ok else None

    def _gicp_init(self, i: int, frame: Frame, pred: torch.Tensor, rec: dict,
                   noise: float | None = None) -> torch.Tensor:
        """GICP of frame i's depth onto its target (`slam.gicp.target`: frame i-1, the GICP keyframe, or a local map
        of the last GICP keyframes) from the prediction; the prediction when a check fails (the reason goes to `rec`
        as init_fallback). Targets are kept in memory and rebuilt from the dataset after a resume. `noise`: the
        frame's depth noise at 1 m if already estimated."""
        g = self.cfg.slam.gicp
        points = depth_points(frame.depth, frame.intrinsics, g, noise)
        cur = PreparedCloud(points, g)
        if g.target is GicpTarget.LOCAL_MAP:
            t_idx, target, base = self.state.gicp_kfs[-1], self._local_map(g), np.eye(4)
        else:
            t_idx = i - 1 if g.target is GicpTarget.PREVIOUS else self.state.gicp_kfs[-1]
            if g.target is GicpTarget.PREVIOUS and self._target_cloud is not None and self._target_cloud[0] < t_idx:
                t_idx = self._target_cloud[0]  # the frames since had too little depth to be a target
            if self._target_cloud is None or self._target_cloud[0] != t_idx:
                self._target_cloud = self._rebuilt_target(t_idx, g)
                t_idx = self._target_cloud[0]
            target, base = self._target_cloud[1], self.est[t_idx].double().cpu().numpy()
        reg = register(target, cur, np.linalg.inv(base) @ pred.double().cpu().numpy(), g)
        rec.update(gicp_fitness=round(reg.fitness, 4), gicp_degeneracy=round(reg.degeneracy, 4), gicp_target=t_idx)
        self._gicp_information = reg.information  # of this frame's GICP pose (a photometric prior, slam.photo)
        c2w = base @ reg.T_target_source
        if g.target is GicpTarget.PREVIOUS:
            if cur.size >= min_points(g):  # (a frame with too little depth is never the target)
                self._target_cloud = (i, cur)
        else:
            from_kf = (reg.T_target_source if g.target is GicpTarget.KEYFRAME
                       else np.linalg.inv(self.est[self.state.gicp_kfs[-1]].double().cpu().numpy()) @ c2w)
            renew = not reg.ok or moved_beyond(from_kf, g.kf_dist, g.kf_angle) or reg.fitness < g.kf_fitness
            if renew and cur.size >= min_points(g):  # (a frame with too little depth never becomes the target)
                self.state.gicp_kfs.append(i)  # the target of the next frames (placed at its tracked pose)
                self._target_cloud = (i, cur)
                if g.target is GicpTarget.LOCAL_MAP:
                    self._kf_points[i] = points  # no second read of this frame when the local map is rebuilt
        if not reg.ok:
            rec["init_fallback"] = f"gicp_{reg.reason}"
            return pred
        return torch.as_tensor(c2w, dtype=pred.dtype, device=pred.device)

    def _rebuilt_target(self, t_idx: int, g: GicpConfig) -> tuple[int, PreparedCloud]:
        """The GICP target cloud of frame `t_idx`, read again (after a resume); for the previous-frame target, the
        latest frame up to `t_idx` with enough depth, as the uninterrupted run kept it."""
        while True:
            t_frame = self._frame(t_idx)
            cloud = prepare_depth(t_frame.depth, t_frame.intrinsics, g)
            if g.target is not GicpTarget.PREVIOUS or t_idx == 0 or cloud.size >= min_points(g):
                return t_idx, cloud
            t_idx -= 1

    def _pyramid(self, frame: Frame, smooth: np.ndarray | None = None) -> list[PhotoLevel]:
        """Photometric pyramid of a frame (`trajectory_graph.frame_pyramid`)."""
        return frame_pyramid(frame, self.cfg.slam, smooth)

    def _photo_refine(self, i: int, frame: Frame, pred: torch.Tensor, smooth: np.ndarray,
                      rec: dict) -> tuple[torch.Tensor, list[PhotoLevel]]:
        """Photometric alignment of frame i onto the photometric keyframe from `pred` (slam.photo); returns the pose
        (`pred` when it fails: the reason goes to `rec` as photo_fallback) and the frame's pyramid. It may move a
        well-conditioned GICP pose by max(`max_step`, `jump_factor` x the median move of recent accepted
        refinements), a near-degenerate or failed one by `weak_max_step`. Where the initialiser failed and this
        succeeds, `rec["photo_rescued"]` says the photometric pose stands."""
        pc = self.cfg.slam.photo
        k = self.state.photo_kfs[-1]
        cur = self._pyramid(frame, smooth)
        T_k = self.est[k].double().cpu()
        T_iw = torch.linalg.inv(pred.double().cpu())  # world -> current camera, from the starting pose
        T_ik = T_iw @ T_k
        prior = None
        if pc.gicp_prior > 0 and "init_fallback" not in rec and self._gicp_information is not None:
            prior = (T_ik.clone(), torch.as_tensor(self._gicp_information), pc.gicp_prior)  # T_ik is GICP's here
        others = [(self._photo_pyramid(j), T_iw @ self.est[j].double().cpu())
                  for j in self.state.photo_kfs[-pc.track_refs:-1]] if pc.track_refs > 1 else None
        res = align_photometric(self._photo_pyramid(k), cur, T_ik, pc, torch.Generator().manual_seed(self.cfg.seed + i),
                                prior, others)
        c2w = T_k @ torch.linalg.inv(res.T_ik)
        fallback = res.fallback
        shift = float(torch.linalg.norm(c2w[:3, 3] - pred[:3, 3].double().cpu()))
        weak = "init_fallback" in rec or rec.get("gicp_degeneracy", 0.0) < pc.weak_degeneracy
        within = not shift > step_bound(self.state.photo_shifts, weak, pc)  # (a NaN shift counts as within)
        if fallback is None and not within:
            if jump_kept(res.rms, self.state.photo_kf_rms, pc):
                rec["photo_jump_kept"] = True  # beyond the bound, but the image is explained as well as usual
            else:
                fallback = "photo_jump"
        if fallback is None and within:
            self.state.photo_shifts = (self.state.photo_shifts + [shift])[-pc.jump_window:]
        rec.update(photo_iters=res.iters, photo_points=res.n_points, photo_target=k,
                   photo_rms=round(res.rms, 5) if math.isfinite(res.rms) else None,
                   photo_shift_mm=round(shift * 1e3, 3) if math.isfinite(shift) else None)
        if others is not None:
            rec["photo_refs"] = 1 + len(others)  # keyframes aligned onto at once (slam.photo.track_refs)
        if res.light is not None:
            rec["photo_light"] = [round(res.light[0], 4), round(res.light[1], 4)]
        if res.n_depth is not None:
            rec["photo_depth_points"] = res.n_depth  # depth residuals beside the intensities (slam.photo.depth_weight)
        if fallback:
            rec["photo_fallback"] = fallback
            return pred, cur
        if "init_fallback" in rec and pc.rescue:
            rec["photo_rescued"] = True
        return c2w.to(dtype=pred.dtype, device=pred.device), cur

    def _previous_frame(self, i: int) -> Frame:
        """Frame i-1: kept from its processing (slam.photo.skip_stale), or read again (after a resume)."""
        if self._prev_frame is None or self._prev_frame.index != i - 1:
            return self._frame(i - 1)
        return self._prev_frame

    def _photo_pyramid(self, k: int) -> list[PhotoLevel]:
        """Photometric pyramid of keyframe k: kept from when it became one, or rebuilt (after a resume)."""
        if k not in self._photo_pyrs:
            self._photo_pyrs[k] = self._pyramid(self._frame(k))
        return self._photo_pyrs[k]

    def _renew_photo_keyframe(self, i: int, pyramid: list[PhotoLevel], failed: bool, rec: dict) -> None:
        """Frame i becomes the photometric reference once it has moved `kf_dist` / turned `kf_angle` from the
        current one, its residual RMS `rec["photo_rms"]` exceeds `kf_rms_factor` x the first one onto the current
        reference (the reference no longer explains the view), or when the alignment onto it failed. With
        `kf_refs` > 1 a new keyframe's pose is first averaged with its alignments onto older keyframes."""
        pc = self.cfg.slam.photo
        s = self.state
        k = s.photo_kfs[-1]
        rms = rec.get("photo_rms")
        if not failed and rms is not None and rms > 0 and s.photo_kf_rms <= 0:
            s.photo_kf_rms = float(rms)  # the first refinement onto this reference sets its level
        grown = pc.kf_rms_factor > 0 and not failed and rms is not None and s.photo_kf_rms > 0 \
            and rms > pc.kf_rms_factor * s.photo_kf_rms
        from_kf = (torch.linalg.inv(self.est[k].double()) @ self.est[i].double()).cpu().numpy()
        if failed or grown or moved_beyond(from_kf, pc.kf_dist, pc.kf_angle):
            if pc.kf_refs > 1 and not failed:
                self._average_keyframe_pose(i, pyramid, rec)
            s.photo_kfs.append(i)
            s.photo_kf_rms = 0.0
            self._photo_pyrs[i] = pyramid
            keep = set(s.photo_kfs[-max(pc.kf_refs, pc.track_refs):])
            self._photo_pyrs = {j: p for j, p in self._photo_pyrs.items() if j in keep}

    def _average_keyframe_pose(self, i: int, pyramid: list[PhotoLevel], rec: dict) -> None:
        """Frame i, about to become a photometric keyframe, is aligned onto the `kf_refs` - 1 keyframes before its
        reference too (from its pose); its pose becomes the mean (`mean_pose`) of the accepted ones (no fallback,
        a move within `step_bound`) and its own: each keyframe placed by several older ones, not by the last link of
        the chain only (meant to slow the chain's random walk; on 7-Scenes it did not, docs/accurate.md). Logs
        `photo_kf_refs` (poses averaged) and `photo_kf_move_mm`."""
        pc = self.cfg.slam.photo
        s = self.state
        T_i = self.est[i].double().cpu()
        poses = [T_i]
        for j, k in enumerate(s.photo_kfs[-pc.kf_refs:-1]):
            T_k = self.est[k].double().cpu()
            gen = torch.Generator().manual_seed(self.cfg.seed + i + 100_003 * (j + 1))
            res = align_photometric(self._photo_pyramid(k), pyramid, torch.linalg.inv(T_i) @ T_k, pc, gen)
            if res.fallback is not None:
                continue
            c2w = T_k @ torch.linalg.inv(res.T_ik)
            if float(torch.linalg.norm(c2w[:3, 3] - T_i[:3, 3])) <= step_bound(s.photo_shifts, False, pc):
                poses.append(c2w)
        rec["photo_kf_refs"] = len(poses)
        if len(poses) > 1:
            T = mean_pose(torch.stack(poses))
            rec["photo_kf_move_mm"] = round(float(torch.linalg.norm(T[:3, 3] - T_i[:3, 3])) * 1e3, 3)
            self._set_pose(i, T.to(dtype=self.est.dtype, device=self.est.device))

    def _local_map(self, g: GicpConfig) -> PreparedCloud:
        """World-frame cloud of the last `g.local_map_keyframes` GICP keyframes at their current poses (cached)."""
        ids = tuple(self.state.gicp_kfs[-g.local_map_keyframes:])
        if self._local_target is None or self._local_target[0] != ids:
            pts = []
            for k in ids:
                if k not in self._kf_points:  # frame 0, or keyframes from before a resume
                    f = self._frame(k)
                    self._kf_points[k] = depth_points(f.depth, f.intrinsics, g)
                T = self.est[k].double().cpu().numpy()
                pts.append(self._kf_points[k] @ T[:3, :3].T + T[:3, 3])
            for k in [k for k in self._kf_points if k not in ids]:
                del self._kf_points[k]
            self._local_target = (ids, PreparedCloud(np.concatenate(pts), g))
        return self._local_target[1]

    def _sdf_refine(self, ft: FrameTensors, pred: torch.Tensor, rec: dict) -> torch.Tensor:
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
        if self.given is not None:  # given poses stay as given: no bundle adjustment
            cfg = dataclasses.replace(cfg, bundle_adjust=False)
        kf_ids = list(self.store.frame_ids)
        t0 = time.perf_counter()
        res = map_frame(self.model, self.state.optimizers, self.store, self.est[kf_ids], self.est[i],
                        lambda n: ft.training_rays(ft.sample_index(n, self.generator)), cfg, self.generator)
        map_ms = (time.perf_counter() - t0) * 1e3
        self.state.map_ms.append(map_ms)
        fallback = None
        if bool(torch.isfinite(res.kf_c2w).all()) and bool(torch.isfinite(res.cur_c2w).all()):
            if not (torch.equal(self.est[kf_ids], res.kf_c2w) and torch.equal(self.est[i], res.cur_c2w)):
                self._local_target = None  # bundle adjustment moved poses: the GICP local map is rebuilt at them
            self.est[kf_ids] = res.kf_c2w
            self.est[i] = res.cur_c2w
        else:  # keep the poses from before bundle adjustment
            fallback = "ba_nan"
        if res.skipped:
            fallback = (fallback + "," if fallback else "") + f"nan_loss_x{res.skipped}"
        if fallback:
            self._event(i, fallback)
        self.state.proc_psnr += res.psnr
        self.state.proc_depth_l1 += [d for d in res.depth_l1 if math.isfinite(d)]
        self._log({"type": "map", "frame": i, "map_ms": map_ms, "keyframes": len(kf_ids),
                   "loss": res.losses[-1] if res.losses else None,
                   "psnr": float(np.mean(res.psnr)) if res.psnr else None,
                   "depth_l1": float(np.nanmean(res.depth_l1)) if res.depth_l1 else None,
                   **({"fallback": fallback} if fallback else {})})
        self._add_keyframe(i, ft)

    def _add_keyframe(self, i: int, ft: FrameTensors) -> None:
        cfg = self.cfg.slam
        n = max(1, int(round(cfg.keyframe_fraction * ft.intr.height * ft.intr.width)))
        idx = ft.random_index(n, self.generator)
        if cfg.keyframe_edge_fraction > 0:  # silhouettes: a few percent of the pixels, most of a render's depth error
            edges = ft.edge_pixels(cfg.keyframe_edge_jump, near_only=cfg.keyframe_edge_near_only)
            m = min(edges.numel(), int(round(cfg.keyframe_edge_fraction * ft.intr.height * ft.intr.width)))
            if m > 0:
                pick = torch.randperm(edges.numel(), generator=self.generator)[:m].to(edges.device)
                idx = torch.cat([idx, edges[pick]])
        self.store.add(i, *ft.rays(idx), behind=ft.behind_of(idx))
        if cfg.loop_closure and self.given is None:
            self._record_odometry(i)
            if i > 0:
                t0 = time.perf_counter()
                self._close_loop(i, ft.frame)
                st = self.state.loop_stats
                st["ms"] = st.get("ms", 0.0) + (time.perf_counter() - t0) * 1e3

    def _record_odometry(self, i: int) -> None:
        """Keyframe i's pose in the odometry frame (`state.kf_odometry`): the previous keyframe's there, moved by
        the tracked motion between the two now, when i is added; the pose graph's odometry edge stays as measured
        however loops move the poses later. A chain starts at the current pose (the first keyframe, or after a
        resume from a checkpoint without it)."""
        s = self.state
        ids = self.store.frame_ids
        T_i = s.est[i].double().cpu().numpy()
        prev = ids[-2] if len(ids) >= 2 else None
        if prev is None or prev not in s.kf_odometry:
            s.kf_odometry[i] = T_i.tolist()
            return
        rel = np.linalg.solve(s.est[prev].double().cpu().numpy(), T_i)
        s.kf_odometry[i] = (np.asarray(s.kf_odometry[prev]) @ rel).tolist()

    def _odometry_edges(self, kf_ids: list[int], est: np.ndarray) -> np.ndarray:
        """(K - 1, 4, 4) relative poses of consecutive keyframes as tracked (`kf_odometry`), or from `est` (N, 4, 4)
        where a keyframe has none."""
        odo = self.state.kf_odometry
        out = []
        for a, b in zip(kf_ids[:-1], kf_ids[1:]):
            if a in odo and b in odo:
                out.append(np.linalg.solve(np.asarray(odo[a]), np.asarray(odo[b])))
            else:
                out.append(np.linalg.solve(est[a], est[b]))
        return np.stack(out) if out else np.zeros((0, 4, 4))

    def _optimise_graph(self, i: int, est: np.ndarray, rigid_from: int | None) -> np.ndarray:
        """Pose graph of the keyframes up to frame i (tracked odometry + `state.loops`); frames 0..i follow their
        keyframes (from `rigid_from` on, rigidly with the newest). Updates `state.est`; returns how far (m) each
        keyframe moved (as applied: those from `rigid_from` on with the newest, not to their graph optimum)."""
        s = self.state
        kf_ids = list(self.store.frame_ids)
        old_kf = est[kf_ids]
        new_kf = corrected_keyframes(old_kf, kf_ids, s.loops, self.cfg.slam.loop, self._odometry_edges(kf_ids, est))
        new_est = follow_keyframes(est, old_kf, new_kf, kf_ids, s.rel_kf, i, rigid_from=rigid_from)
        s.est[: i + 1] = torch.as_tensor(new_est[: i + 1], dtype=s.est.dtype, device=s.est.device)
        self._local_target = None  # the GICP local map sits at the old poses
        return np.linalg.norm(new_est[kf_ids, :3, 3] - old_kf[:, :3, 3], axis=1)

    def _refit(self) -> dict[str, Any]:
        """Re-fit the map from every keyframe's stored rays at their current poses (slam.loop.refit_*); returns its
        log fields (time, first and last loss)."""
        lc, s = self.cfg.slam.loop, self.state
        s.loop_stats["unfitted_m"] = 0.0
        t0 = time.perf_counter()
        losses = refit(self.model, s.optimizers, self.store, self.est[list(self.store.frame_ids)], lc.refit_iters,
                       lc.refit_pixels, self.generator)
        return {"refit_ms": (time.perf_counter() - t0) * 1e3, "refit_loss_first": losses[0] if losses else None,
                "refit_loss_last": losses[-1] if losses else None}

    def _finish_loops(self, i: int) -> None:
        """After the last frame i of a run with loop edges: the pose graph once more with every frame following its
        own keyframe (no tracking follows, so the tracker's local map need not keep its shape), and a re-fit of the
        map if the keyframes' moves since the last one add up to `refit_final_move` (a re-fit now is paid once,
        not once per loop: a smaller threshold than the run's `refit_min_move`)."""
        s = self.state
        t0 = time.perf_counter()
        moved = self._optimise_graph(i, s.est[: i + 1].double().cpu().numpy(), rigid_from=None)
        rec = {"type": "loop_final", "frame": i, "edges": len(s.loops),
               "keyframes_moved_max_m": round(float(moved.max()), 5), "graph_ms": (time.perf_counter() - t0) * 1e3}
        s.loop_stats["unfitted_m"] = s.loop_stats.get("unfitted_m", 0.0) + float(moved.max())
        rec["unfitted_m"] = round(s.loop_stats["unfitted_m"], 5)
        if s.loop_stats["unfitted_m"] > self.cfg.slam.loop.refit_final_move:
            rec.update(self._refit())
        s.loop_stats["ms"] = s.loop_stats.get("ms", 0.0) + (time.perf_counter() - t0) * 1e3
        self._log(rec)

    def _refine_trajectory(self, i: int) -> None:
        """After the last frame i: the pose graph of every frame (slam.refine, `trajectory_graph`) replaces frames
        0..i's poses; logs the links used and left out and how far the poses moved."""
        rc, s = self.cfg.slam.refine, self.state
        t0 = time.perf_counter()
        est = s.est[: i + 1].double().cpu().numpy()
        links, dropped = photometric_links(lambda k: self._pyramid(self._frame(k)), est, rc.gaps,
                                           self.cfg.slam.photo, rc.max_shift, self.cfg.seed)
        new = refine_trajectory(est, links, rc)
        s.est[: i + 1] = torch.as_tensor(new, dtype=s.est.dtype, device=s.est.device)
        moved = np.linalg.norm(new[:, :3, 3] - est[:, :3, 3], axis=1)
        self._log({"type": "refine", "frame": i, "links": len(links), "links_dropped": dropped,
                   "moved_max_m": round(float(moved.max()), 5), "moved_median_m": round(float(np.median(moved)), 5),
                   "refine_ms": (time.perf_counter() - t0) * 1e3})

    def _close_loop(self, i: int, frame: Frame) -> None:
        """Loop closure at the new keyframe i (slam.loop, docs/loop_closure.md): older keyframes near its estimated
        pose whose depth overlaps its view are candidates; the best are verified by GICP; unless they disagree, each
        verified one is a loop edge of the keyframe pose graph, whose optimum moves every keyframe (frames follow
        their keyframes, the tracker's local map rigidly); once the moves since the last re-fit exceed
        `refit_min_move`, the map is re-fitted (a closure; after the last frame, `_finish_loops`)."""
        lc, g, s = self.cfg.slam.loop, self.cfg.slam.gicp, self.state
        st = s.loop_stats
        kf_ids = list(self.store.frame_ids)
        est = s.est[: i + 1].double().cpu().numpy()
        window = (s.gicp_kfs[-g.local_map_keyframes:][0] if self.cfg.slam.init is PoseInit.GICP
                  and g.target is GicpTarget.LOCAL_MAP else None)  # first frame of the tracker's local map
        near = nearby_keyframes(i, kf_ids[:-1], est, lc, before=window)[:4 * lc.candidates]
        if not near:
            return
        points = depth_points(frame.depth, frame.intrinsics, g)
        frames = {c.frame: self._frame(c.frame) for c in near}
        for c in near:
            c.overlap = overlap(points, est[i], est[c.frame], frames[c.frame].depth, frame.intrinsics,
                                lc.overlap_tol)
        cands = sorted([c for c in near if c.overlap >= lc.min_overlap], key=lambda c: -c.overlap)[: lc.candidates]
        st["candidates"] = st.get("candidates", 0) + len(cands)
        if not cands:
            return
        cur = stage_clouds(points, g, lc)
        grey_k = grey(frame.rgb) if lc.color_check else None  # the keyframe's grey image, for every candidate
        verified = []
        for c in cands:
            cand = stage_clouds(depth_points(frames[c.frame].depth, frame.intrinsics, g), g, lc)
            v = verify(cand, cur, est[c.frame], est[i], path_length(est, c.frame, i), c.frame, g, lc)
            color, first = {}, new_place(c.frame, s.loops, lc)  # the first loop onto this place?
            if v.ok and not significant(v, first, lc):
                v = dataclasses.replace(v, ok=False, reason="small_correction")
            if v.ok and grey_k is not None:
                grey_c = grey(frames[c.frame].rgb)
                loop_e = color_disagreement(frame.depth, grey_k, grey_c, v.T_cand_cur, frame.intrinsics)
                est_e = color_disagreement(frame.depth, grey_k, grey_c, np.linalg.solve(est[c.frame], est[i]),
                                            frame.intrinsics)
                color = {"color_loop": round(loop_e, 5), "color_estimate": round(est_e, 5)}
                if not color_confirms(loop_e, est_e, first, lc.color_margin):
                    v = dataclasses.replace(v, ok=False, reason="color")
            self._log({"type": "loop_candidate", "frame": i, "distance_m": round(c.distance, 4),
                       "angle_deg": round(c.angle, 2), "overlap": round(c.overlap, 4), **v.record(), **color})
            if v.ok:
                verified.append(v)
        st["verified"] = st.get("verified", 0) + len(verified)
        if not verified:
            return
        if not consistent(verified, est, lc.consistency):
            st["ambiguous"] = st.get("ambiguous", 0) + 1
            self._log({"type": "loop_rejected", "frame": i, "reason": "ambiguous",
                       "candidates": [v.frame for v in verified]})
            return
        best = max(verified, key=lambda v: v.fitness)
        s.loops += [{"candidate": v.frame, "frame": i, "T": v.T_cand_cur.tolist()} for v in verified]
        t0 = time.perf_counter()
        moved = self._optimise_graph(i, est, rigid_from=window)
        graph_ms = (time.perf_counter() - t0) * 1e3
        rec = {"type": "loop_edge", "frame": i, "candidate": best.frame, "fitness": round(best.fitness, 4),
               "correction_m": round(best.correction, 5), "edges": len(s.loops),
               "keyframes_moved_max_m": round(float(moved.max()), 5),
               "keyframes_moved_mean_m": round(float(moved.mean()), 5), "graph_ms": graph_ms}
        # keyframe motion the map has not been re-fitted to yet; re-fit once it exceeds refit_min_move (after the
        # last frame `_finish_loops` adds its own move and re-fits above refit_final_move)
        st["unfitted_m"] = st.get("unfitted_m", 0.0) + float(moved.max())
        if st["unfitted_m"] > lc.refit_min_move:
            rec.update(type="loop_closed", **self._refit())
            st["closures"] = st.get("closures", 0) + 1
        self._log(rec)

    # -- results ---------------------------------------------------------------------------------------------------
    def mesh(self) -> trimesh.Trimesh | None:
        """Marching-cubes mesh of the current map (`mesh` config); None, and an `empty_mesh` event, if empty."""
        m = self.cfg.mesh
        mesh = extract_mesh(self.model.field, self.bounds, m.resolution, m.chunk, m.color)
        if mesh is None:
            self._event(self.state.next_frame - 1, "empty_mesh")
        return mesh

    def result(self) -> SlamResult:
        """Trajectories, keyframes and process metrics of the frames processed so far."""
        s = self.state
        est = s.est.double().cpu().numpy()
        rel = relative_trajectory(est, s.rel.double().cpu().numpy(), s.rel_kf, s.store.frame_ids,
                                  self.cfg.slam.faithful_relative)
        return SlamResult(est=est, relative=rel, gt=s.gt, timestamps=s.timestamps, keyframes=list(s.store.frame_ids),
                          metrics=self.process_metrics())

    def process_metrics(self) -> dict[str, Any]:
        """The process metrics of docs/metrics.md so far (timings, model size, PSNR while mapping, events)."""
        from inrslam.fields import model_size_mb

        s = self.state
        return {
            "frames": self.n_frames,
            "track_ms_per_frame": float(np.mean(s.track_ms)) if s.track_ms else None,
            "map_ms_per_call": float(np.mean(s.map_ms)) if s.map_ms else None,
            "map_ms_per_frame": float(np.sum(s.map_ms)) / (s.next_frame - 1) if s.next_frame > 1 else None,
            "init_ms": s.init_ms,
            "model_size_mb": model_size_mb(self.model.field),
            "model_size_with_optimizer_mb": model_size_mb(self.model.field, with_optimizer=True),
            "psnr_process_db": float(np.mean(s.proc_psnr)) if s.proc_psnr else None,
            "depth_l1_process_m": float(np.mean(s.proc_depth_l1)) if s.proc_depth_l1 else None,
            "fallbacks": len(s.events),
            "lost_frames": sum(e["event"].split(",").count("tracking_lost") for e in s.events),
            "encoding": self.cfg.field.encoding,
            "render": self.cfg.render.name,
            "poses": self.given.source["source"] if self.given is not None else "tracked",
            **(self._loop_metrics() if self.cfg.slam.loop_closure else {}),
        }

    def _loop_metrics(self) -> dict[str, Any]:
        """Loop-closure counts and cost (docs/metrics.md)."""
        s = self.state
        st = s.loop_stats
        return {"loop_candidates": int(st.get("candidates", 0)), "loop_verified": int(st.get("verified", 0)),
                "loop_ambiguous": int(st.get("ambiguous", 0)), "loop_edges": len(s.loops),
                "loops_closed": int(st.get("closures", 0)),
                "loop_ms_per_frame": st.get("ms", 0.0) / (s.next_frame - 1) if s.next_frame > 1 else None}
