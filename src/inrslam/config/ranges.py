"""The valid range of every numeric config key, checked when a config is loaded (before any work starts).

A value out of range is a `ConfigError` naming the key, where it was set and what is expected; every float must be
finite. Keys not listed here take any finite value of their type.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

from inrslam.errors import ConfigError

Rule = tuple[Callable[[Any], bool], str]


def at_least(lo: float) -> Rule:
    return (lambda v: v >= lo), f">= {lo:g}"


def above(lo: float) -> Rule:
    return (lambda v: v > lo), f"> {lo:g}"


def between(lo: float, hi: float, open_lo: bool = False) -> Rule:
    return ((lambda v: lo < v <= hi) if open_lo else (lambda v: lo <= v <= hi)), f"in {'(' if open_lo else '['}" \
                                                                                f"{lo:g}, {hi:g}]"


def zero_or_at_least(lo: int) -> Rule:
    return (lambda v: v == 0 or v >= lo), f"0 (default) or >= {lo}"


NONNEG, POS, COUNT, FRACTION = at_least(0), above(0), at_least(1), between(0.0, 1.0)
SEED: Rule = (lambda v: 0 <= v < 2**63), "in [0, 2^63)"  # torch.manual_seed's range

RANGES: dict[str, Rule] = {
    # data
    "data.max_frames": NONNEG, "data.stride": COUNT, "data.start": NONNEG, "data.depth_scale": POS,
    "data.bounds_frames": COUNT, "data.bounds_margin": NONNEG, "data.crop_edge": NONNEG, "data.depth_max": NONNEG,
    "data.builtin.frames": NONNEG, "data.builtin.width": zero_or_at_least(16),
    "data.builtin.height": zero_or_at_least(16), "data.builtin.depth_noise": NONNEG,
    "data.builtin.missing_depth": ((lambda v: 0.0 <= v < 1.0), "in [0, 1)"),
    "data.builtin.motion_scale": POS, "data.builtin.seed": SEED, "seed": SEED, "eval.seed": SEED,
    "data.tum.max_dt_depth": NONNEG, "data.tum.max_dt_pose": NONNEG,
    # field
    "field.levels": COUNT, "field.feature_dim": COUNT, "field.block_coarse": POS, "field.block_fine": POS,
    "field.app_block_coarse": POS, "field.app_block_fine": POS, "field.plane_block_coarse": POS,
    "field.log2_hashmap_size": between(1, 30), "field.geo_feat_dim": COUNT, "field.hidden_dim": COUNT,
    "field.truncation": POS, "field.grid_init": NONNEG, "field.plane_init_std": NONNEG, "field.mlp.width": COUNT,
    "field.mlp.depth": COUNT,
    # rendering, sampling, losses
    "render.beta_lr": NONNEG, "render.density.beta": POS, "render.neus.fd_eps": POS,
    "render.neus.anneal_end": NONNEG, "render.volsdf.beta_init": POS, "render.volsdf.beta_min": POS,
    "sampling.n_free": NONNEG, "sampling.n_surface": NONNEG, "sampling.n_uniform": at_least(2), "sampling.near": NONNEG,
    "sampling.far_factor": POS, "sampling.band": POS,
    "loss.color": NONNEG, "loss.depth": NONNEG, "loss.free_space": NONNEG, "loss.center": NONNEG,
    "loss.tail": NONNEG, "loss.center_band": between(0.0, 1.0, open_lo=True),
    "loss.behind": between(0.0, 1.0), "loss.silhouette_behind": between(0.0, 1.0), "loss.silhouette_jump": POS,
    "loss.silhouette_radius": COUNT,
    # slam
    "slam.init_iters": NONNEG, "slam.init_pixels": COUNT, "slam.init_stop_window": NONNEG,
    "slam.init_stop_tol": NONNEG, "slam.track_iters": NONNEG, "slam.track_pixels": COUNT,
    "slam.track_lr": POS, "slam.track_edge": NONNEG, "slam.map_every": COUNT, "slam.map_iters": NONNEG,
    "slam.map_pixels": COUNT, "slam.map_current_min": NONNEG, "slam.map_lr": POS, "slam.ba_lr": POS,
    "slam.ba_pose_every": COUNT, "slam.keyframe_fraction": between(0.0, 1.0, open_lo=True),
    "slam.keyframe_edge_fraction": between(0.0, 1.0), "slam.keyframe_edge_jump": POS,
    "slam.max_pose_jump": NONNEG, "slam.checkpoint_every": NONNEG, "slam.mesh_every": NONNEG,
    "slam.poses_tolerance": NONNEG,
    "slam.gicp.downsample": POS, "slam.gicp.max_corr": POS, "slam.gicp.neighbors": COUNT,
    "slam.gicp.max_iterations": COUNT, "slam.gicp.eps_trans": POS, "slam.gicp.eps_rot": POS,
    "slam.gicp.pixel_stride": COUNT, "slam.gicp.max_depth": POS, "slam.gicp.min_fitness": FRACTION,
    "slam.gicp.degeneracy_ratio": NONNEG, "slam.gicp.max_step": POS, "slam.gicp.threads": COUNT,
    "slam.gicp.kf_dist": POS, "slam.gicp.kf_angle": POS, "slam.gicp.kf_fitness": FRACTION,
    "slam.gicp.local_map_keyframes": COUNT, "slam.gicp.depth_filter": NONNEG, "slam.gicp.depth_noise": NONNEG,
    "slam.gicp.filter_min_noise": NONNEG, "slam.photo.min_depth_noise": NONNEG, "slam.photo.levels": COUNT,
    "slam.photo.iters": COUNT, "slam.photo.tol": POS, "slam.photo.grad_threshold": NONNEG,
    "slam.photo.max_points": COUNT, "slam.photo.min_points": COUNT, "slam.photo.huber": POS,
    "slam.photo.max_step": POS, "slam.photo.weak_degeneracy": NONNEG, "slam.photo.weak_max_step": POS,
    "slam.photo.jump_factor": NONNEG, "slam.photo.jump_window": COUNT, "slam.photo.jump_rms_factor": NONNEG,
    "slam.photo.kf_dist": POS, "slam.photo.kf_angle": POS, "slam.photo.kf_rms_factor": NONNEG,
    "slam.photo.kf_refs": COUNT, "slam.photo.track_refs": COUNT, "slam.photo.gicp_prior": NONNEG,
    "slam.photo.depth_weight": NONNEG,
    "slam.sdf_track.iters": NONNEG, "slam.sdf_track.points": COUNT, "slam.sdf_track.huber": POS,
    "slam.sdf_track.band": POS, "slam.sdf_track.min_points": COUNT, "slam.sdf_track.tol_trans": POS,
    "slam.sdf_track.tol_rot": POS, "slam.sdf_track.damping": NONNEG, "slam.sdf_track.max_step": POS,
    "slam.lost.factor": above(1), "slam.lost.window": COUNT, "slam.lost.recover_max_corr": POS,
    "slam.lost.stop_after": NONNEG,
    "slam.loop.min_gap": COUNT, "slam.loop.max_dist": POS, "slam.loop.max_angle": POS,
    "slam.loop.min_overlap": FRACTION, "slam.loop.overlap_tol": POS, "slam.loop.candidates": COUNT,
    "slam.loop.corr_stages": POS, "slam.loop.coarse_downsample": NONNEG, "slam.loop.epsilon": POS,
    "slam.loop.min_fitness": FRACTION, "slam.loop.max_correction": NONNEG,
    "slam.loop.max_correction_per_m": NONNEG, "slam.loop.max_correction_angle": POS, "slam.loop.consistency": POS,
    "slam.loop.min_correction": NONNEG, "slam.loop.color_margin": FRACTION,
    "slam.loop.refit_min_move": NONNEG, "slam.loop.refit_final_move": NONNEG,
    "slam.loop.odom_sigma_t": POS, "slam.loop.odom_sigma_r": POS,
    "slam.loop.loop_sigma_t": POS, "slam.loop.loop_sigma_r": POS, "slam.loop.huber": NONNEG,
    "slam.loop.refit_iters": NONNEG, "slam.loop.refit_pixels": COUNT,
    "slam.refine.gaps": COUNT, "slam.refine.sigma_t": POS, "slam.refine.sigma_r": POS,
    "slam.refine.odom_sigma_t": POS, "slam.refine.odom_sigma_r": POS, "slam.refine.huber": NONNEG,
    "slam.refine.max_shift": POS,
    # outputs, evaluation
    "mesh.resolution": at_least(0.001), "mesh.chunk": COUNT,
    "eval.max_time_diff": NONNEG, "eval.rpe_delta": COUNT, "eval.cull_every": COUNT, "eval.cull_eps": NONNEG,
    "eval.n_samples": COUNT, "eval.threshold": POS, "eval.heldout_every": NONNEG, "eval.heldout_max": NONNEG,
    "eval.heldout_samples": at_least(2), "eval.heldout_refine": NONNEG,
    "threads": NONNEG,
    # the EHE mapper (docs/ehe.md)
    "ehe.voxel_size": POS, "ehe.min_points": NONNEG, "ehe.margin": between(0.0, 0.5), "ehe.max_vertices": COUNT,
    "ehe.point_stride": COUNT, "ehe.fine_cell": POS, "ehe.feature_dim": COUNT, "ehe.hidden_dim": COUNT,
    "ehe.grid_init": NONNEG, "ehe.truncation": POS, "ehe.step": POS, "ehe.max_hits": COUNT, "ehe.max_depth": POS,
    "ehe.depth_min": NONNEG, "ehe.depth_max": POS, "ehe.rays": COUNT, "ehe.iters": NONNEG, "ehe.first_iters": NONNEG,
    "ehe.window": NONNEG, "ehe.random_fraction": FRACTION, "ehe.kf_overlap": FRACTION, "ehe.kf_max_gap": COUNT,
    "ehe.kf_ray_fraction": between(0.0, 1.0, open_lo=True), "ehe.lr": POS, "ehe.color_weight": NONNEG,
    "ehe.depth_weight": NONNEG, "ehe.free_space_weight": NONNEG, "ehe.sdf_weight": NONNEG, "ehe.mesh_samples": COUNT,
}


def _leaves(cfg: Any, prefix: str = ""):
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            yield from _leaves(value, f"{key}.")
        else:
            yield key, value


def check_ranges(cfg: Any, sources: dict[str, str]) -> None:
    """Raise ConfigError for the first numeric key of `cfg` out of its range (or not finite)."""

    def fail(key: str, value: Any, expected: str) -> ConfigError:
        return ConfigError(f"config key {key!r} in {sources.get(key, 'defaults')}: expected {expected}, got {value!r}")

    for key, value in _leaves(cfg):
        values = value if isinstance(value, list) else [value]
        for v in values:
            if isinstance(v, float) and not math.isfinite(v):
                raise fail(key, value, "a finite number")
        rule = RANGES.get(key)
        if rule is not None and isinstance(value, list) and not value:
            raise fail(key, value, f"a list of at least one number {rule[1]}")
        if rule is not None and value is not None and not all(rule[0](v) for v in values):
            kind = "an integer" if isinstance(value, int) else "a number"
            raise fail(key, value, f"{kind} {rule[1]}" if not isinstance(value, list) else f"numbers {rule[1]}")
    e = getattr(cfg, "ehe", None)
    if e is not None and not e.depth_min < e.depth_max:
        raise fail("ehe.depth_min", e.depth_min, f"a number below ehe.depth_max ({e.depth_max:g})")
    s = getattr(cfg, "sampling", None)
    if s is not None and s.n_free + s.n_surface < 2:
        raise fail("sampling.n_surface", s.n_surface,
                   "at least two samples per ray with depth (n_free + n_surface >= 2)")
