"""Evaluation: trajectory (ATE/RPE), image (PSNR/SSIM/depth L1), mesh (culling, Acc/Comp/Comp%) and run directories.

Core maths (`trajectory`, `image`, `mesh`) never reads files; `run` is the thin layer that reads a run directory or
files and calls it. Definitions and protocol: docs/metrics.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from inrslam.lazy import lazy_attributes

if TYPE_CHECKING:  # the names below load on first use (PEP 562): `import inrslam.eval.trajectory` needs no torch
    from inrslam.eval.config import Alignment, EvalConfig
    from inrslam.eval.image import depth_l1, lpips_available, psnr, ssim
    from inrslam.eval.mesh import cull_mesh, mesh_metrics, render_mesh_depth
    from inrslam.eval.run import eval_mesh_files, eval_trajectory_files, evaluate_run, format_table
    from inrslam.eval.trajectory import align_umeyama, associate, associate_indices, ate, rpe, select_frames

_SOURCES = {
    "config": ("Alignment", "EvalConfig"),
    "image": ("depth_l1", "lpips_available", "psnr", "ssim"),
    "mesh": ("cull_mesh", "mesh_metrics", "render_mesh_depth"),
    "run": ("eval_mesh_files", "eval_trajectory_files", "evaluate_run", "format_table"),
    "trajectory": ("align_umeyama", "associate", "associate_indices", "ate", "rpe", "select_frames"),
}
__getattr__ = lazy_attributes(__name__, globals(), _SOURCES)

__all__ = [
    "Alignment",
    "EvalConfig",
    "align_umeyama",
    "associate",
    "associate_indices",
    "ate",
    "cull_mesh",
    "depth_l1",
    "eval_mesh_files",
    "eval_trajectory_files",
    "evaluate_run",
    "format_table",
    "lpips_available",
    "mesh_metrics",
    "psnr",
    "render_mesh_depth",
    "rpe",
    "select_frames",
    "ssim",
]
