"""`EheSystem`: mapping-only SLAM loop with the Explicit Hybrid Encoding (docs/ehe.md §5). Every frame takes its
given pose, allocates voxels from its depth, initialises new SDF priors, then is mapped with a keyframe window; it
becomes a keyframe by the voxel-overlap rule. Frame 0 is mapped with `ehe.first_iters` (reported as init_ms)."""

from __future__ import annotations

import time
from typing import Any, Protocol, cast

import numpy as np
import torch
import trimesh

from inrslam.data.frame import Frame, RGBDDataset
from inrslam.errors import ConfigError
from inrslam.geometry.backproject import world_points
from inrslam.geometry.camera import grid_directions, world_rays
from inrslam.geometry.intrinsics import Intrinsics
from inrslam.slam.ehe.config import EheConfig
from inrslam.slam.ehe.field import EheField
from inrslam.slam.ehe.mapper import MapResult, needs_keyframe, optimise, select_window, voxel_overlap
from inrslam.slam.ehe.mesh import voxel_mesh
from inrslam.slam.ehe.model import EheModel
from inrslam.slam.ehe.state import EheState
from inrslam.slam.frame_tensors import FrameTensors
from inrslam.slam.keyframes import KeyframeStore
from inrslam.slam.registration import depth_noise, filtered_depth
from inrslam.slam.system import SlamRunConfig, SlamSystem


class EheRunConfig(SlamRunConfig, Protocol):
    """The sections of a run's config the EHE loop reads."""

    ehe: EheConfig


class EheSystem(SlamSystem):
    """EHE mapping with given poses (`slam.poses`); same interface and outputs as `SlamSystem`."""

    model_class = EheModel
    cfg: EheRunConfig
    state: EheState

    def __init__(self, cfg: EheRunConfig, dataset: RGBDDataset):
        if not cfg.slam.poses:
            raise ConfigError("mapper 'ehe' maps with given poses: set slam.poses=gt or a TUM file (--poses)")
        super().__init__(cfg, dataset)
        state = EheState.fresh(self.model, self.model.make_optimizers(cfg.ehe.lr), KeyframeStore(device=self.device),
                               torch.Generator().manual_seed(cfg.seed), self.n_frames, self.device)
        assert isinstance(state, EheState)
        self.state = state
        self._grids: dict[tuple[Intrinsics, int], tuple[torch.Tensor, torch.Tensor]] = {}  # `_point_grid`

    def _make_model(self) -> EheModel:  # type: ignore[override]
        return EheModel(self.cfg, self.bounds)

    @property
    def field(self) -> EheField:
        """The EHE field (`self.model` is an `EheModel`; the base class types it as its own model)."""
        return cast(EheModel, self.model).field

    # -- the loop ----------------------------------------------------------------------------------------------
    def _process(self, i: int, frame: Frame) -> None:
        mapped, noise = self.mapped_frame(frame)
        ft = FrameTensors(mapped, self.device)
        s = self.state
        s.timestamps[i] = frame.timestamp
        if frame.pose_valid and np.all(np.isfinite(frame.c2w)):
            s.gt[i] = frame.c2w
        assert self.given is not None
        c2w = torch.as_tensor(self.given.c2w[i], dtype=torch.float32, device=self.device)
        if i == 0:
            s.est[0], s.rel[0], s.rel_kf[0] = c2w, torch.eye(4, device=self.device), 0
        else:
            self._set_pose(i, c2w)
            self._log({"type": "pose", "frame": i, "source": self.given.source["source"]})
        depth = {"depth_filtered": mapped is not frame,
                 "depth_noise": round(noise, 6) if noise is not None and np.isfinite(noise) else None}
        self._map_ehe(i, ft, c2w, depth)

    def mapped_frame(self, frame: Frame) -> tuple[Frame, float | None]:
        """The frame the map learns, and the depth noise at 1 m (metres; None when not filtering) it was judged by:
        with `slam.map_filtered_depth` and `slam.gicp.depth_filter` > 0, the frame with its depth after the bilateral
        filter where that noise reaches `slam.gicp.filter_min_noise` (`filtered_depth`); else `frame` itself."""
        g = self.cfg.slam.gicp
        if not (self.cfg.slam.map_filtered_depth and g.depth_filter > 0):
            return frame, None
        noise = depth_noise(frame.depth, g)
        return self._map_frame(frame, filtered_depth(frame.depth, g, noise=noise)), noise

    def _frame_points(self, ft: FrameTensors, c2w: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) of the frame's valid depth (every `point_stride`-th row / column)."""
        c = self.cfg.ehe
        idx, dirs = self._point_grid(ft.intr, c.point_stride)
        return world_points(ft.depth, idx, dirs, c2w, c.depth_min, c.depth_max)

    def _point_grid(self, intr: Intrinsics, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(flat pixel indices (M,), camera directions (M, 3) with z = 1) of every `stride`-th row / column, computed
        once per camera (about 5 ms of a 640 x 480 frame's back-projection otherwise)."""
        key = (intr, stride)
        if key not in self._grids:
            self._grids[key] = grid_directions(intr, stride, self.device)
        return self._grids[key]

    def _map_ehe(self, i: int, ft: FrameTensors, c2w: torch.Tensor, depth: dict) -> None:
        """Allocate, initialise priors and optimise over the keyframe window for frame i; `depth` (which depth
        was mapped: `depth_filtered`, `depth_noise`) goes into its map record."""
        c, s = self.cfg.ehe, self.state
        t0 = time.perf_counter()
        vg = self.field.voxels
        alloc = vg.allocate(self._frame_points(ft, c2w), c.min_points, c.margin, c.max_vertices)
        if alloc.capped:
            self._event(i, "ehe_vertex_cap")
        depth_img = ft.depth.reshape(ft.intr.height, ft.intr.width)
        accepted = vg.init_priors(alloc.observed, depth_img, ft.intr, c2w, c.truncation)
        observed = alloc.observed.cpu()  # keyframe voxel sets live on the CPU (checkpointed as they are)
        window = select_window(observed, s.kf_voxels, c.window, c.random_fraction, self.generator)
        # the first frame runs all its iterations: early ending starts from frame 1 (docs/ehe.md §5)
        res = optimise(self.model, s.optimizers, self._batch(ft, c2w, window), c.first_iters if i == 0 else c.iters,
                       c.early_stop and i > 0, self.generator)
        ms = (time.perf_counter() - t0) * 1e3
        if i == 0:
            s.init_ms = ms
        else:
            s.map_ms.append(ms)
        self._record(i, ms, res, window, alloc.new.numel(), accepted, depth)
        last = len(s.kf_voxels) - 1
        if i == 0 or needs_keyframe(voxel_overlap(observed, s.kf_voxels[last]), i - s.store.frame_ids[-1], c,
                                    observed.numel()):
            self._add_keyframe(i, ft)
            s.kf_voxels.append(observed)

    def _batch(self, ft: FrameTensors, c2w: torch.Tensor, window: list[int]):
        """Ray batches of one frame's mapping: `ehe.rays` spread evenly over the window's keyframes (their stored
        rays, at their given poses) and the current frame (any pixel)."""
        c, store = self.cfg.ehe, self.state.store
        n_per = c.rays // (len(window) + 1)
        counts = torch.bincount(store.slot[: store.n_rays], minlength=len(store)) if window else None
        starts = torch.cumsum(counts, 0) - counts if counts is not None else None
        poses = self.est[[store.frame_ids[k] for k in window]] if window else None

        def batch():
            dirs, rgb, depth = ft.sample_distinct(c.rays - n_per * len(window), self.generator)
            o, d = world_rays(c2w, dirs)
            parts = [(o, d, rgb, depth)]
            if window:
                k = torch.tensor(window, device=self.device).repeat_interleave(n_per)
                j = torch.randint(0, 2**62, (k.numel(),), generator=self.generator).to(self.device)
                idx = starts[k] + j % counts[k]
                T = poses.repeat_interleave(n_per, dim=0)
                parts.append((*world_rays(T, store.dirs[idx]), store.rgb[idx], store.depth[idx]))
            return tuple(torch.cat(x) for x in zip(*parts))

        return batch

    def _record(self, i: int, ms: float, res: MapResult, window: list[int], new: int, accepted: int,
                depth: dict) -> None:
        s = self.state
        psnr = [p for p in res.psnr if np.isfinite(p)]  # none finite: nothing was rendered (no voxel yet)
        depth_l1 = [d for d in res.depth_l1 if np.isfinite(d)]
        s.proc_psnr += psnr
        s.proc_depth_l1 += depth_l1
        if res.skipped:
            self._event(i, f"nan_loss_x{res.skipped}")
        vg = self.field.voxels
        self._log({"type": "map", "frame": i, "map_ms": ms, "iters": res.iters, "keyframes": len(window),
                   "loss": res.losses[-1] if res.losses else None,
                   "psnr": float(np.mean(psnr)) if psnr else None,
                   "depth_l1": float(np.mean(depth_l1)) if depth_l1 else None,
                   "voxels": vg.n_allocated, "new_voxels": new, "priors_accepted": accepted, **depth})

    def _add_keyframe(self, i: int, ft: FrameTensors) -> None:
        n = max(1, int(round(self.cfg.ehe.kf_ray_fraction * ft.intr.height * ft.intr.width)))
        self.store.add(i, *ft.random_rays(n, self.generator))

    # -- results -----------------------------------------------------------------------------------------------
    def mesh(self) -> trimesh.Trimesh | None:
        """Marching cubes over the voxels (`ehe.mesh_samples` per edge, `ehe.mesh_voxels`); None and an `empty_mesh`
        event if empty."""
        mesh = voxel_mesh(self.field, self.cfg.ehe.mesh_samples, self.cfg.mesh.chunk, self.cfg.mesh.color,
                          self.cfg.ehe.mesh_voxels)
        if mesh is None:
            self._event(self.state.next_frame - 1, "empty_mesh")
        return mesh

    def progress_info(self, i: int) -> dict:
        info = super().progress_info(i)
        vs = self.cfg.ehe.voxel_size
        info["mesh"] = lambda resolution: voxel_mesh(self.field, max(1, int(round(vs / resolution))),
                                                     self.cfg.mesh.chunk, self.cfg.mesh.color,
                                                     self.cfg.ehe.mesh_voxels)
        return info

    def process_metrics(self) -> dict[str, Any]:
        """`SlamSystem.process_metrics` plus the voxel structure's size (docs/ehe.md)."""
        m = super().process_metrics()
        vg = self.field.voxels
        m.update(encoding="ehe", render="direct", mapper="ehe", ehe_voxels=vg.n_allocated,
                 ehe_vertices=vg.n_vertices, ehe_priors_initialised=int(vg.vertex_init.sum()),
                 ehe_keyframes=len(self.store))
        return m
