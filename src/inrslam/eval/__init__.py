"""Evaluation: trajectory (ATE/RPE), image (PSNR/SSIM/depth L1), mesh (culling, Acc/Comp/Comp%) and run directories.

Core maths (`trajectory`, `image`, `mesh`) never reads files; `run` is the thin layer that reads a run directory or
files and calls it. Definitions and protocol: docs/metrics.md.
"""

from inrslam.eval.config import Alignment, EvalConfig
from inrslam.eval.image import depth_l1, lpips_available, psnr, ssim
from inrslam.eval.mesh import cull_mesh, mesh_metrics, render_mesh_depth
from inrslam.eval.run import eval_mesh_files, eval_trajectory_files, evaluate_run, format_table
from inrslam.eval.trajectory import align_umeyama, associate, associate_indices, ate, rpe, select_frames

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
