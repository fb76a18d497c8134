"""Rendering: ray sampling, rendering functions G (SDF -> weights), compositing and losses.

Data flow: `sample_depths` -> `render_rays(field, renderer, ...)` (F queried once, G = `build_renderer(cfg)`,
`composite`) -> `compute_losses`. Any field F works with any renderer G.
"""

from inrslam.rendering.compositing import composite, first_crossing, refine_crossing, surface_depth, surface_intervals
from inrslam.rendering.config import (
    DensityConfig,
    LossConfig,
    LossReduction,
    NerfActivation,
    NerfConfig,
    NeusConfig,
    NormalsMethod,
    RenderConfig,
    SamplingConfig,
    SamplingVariant,
    VolSdfConfig,
)
from inrslam.rendering.losses import compute_losses, depth_l1, psnr_from_mse, render_losses
from inrslam.rendering.render import RenderOutput, render_rays
from inrslam.rendering.renderers import RENDERERS, SdfToWeights, build_renderer, renderer_param_groups
from inrslam.rendering.sampling import aabb_exit, sample_depths, sample_pixels

__all__ = [
    "RENDERERS",
    "DensityConfig",
    "LossConfig",
    "LossReduction",
    "NerfActivation",
    "NerfConfig",
    "NeusConfig",
    "NormalsMethod",
    "RenderConfig",
    "RenderOutput",
    "SamplingConfig",
    "SamplingVariant",
    "SdfToWeights",
    "VolSdfConfig",
    "aabb_exit",
    "build_renderer",
    "composite",
    "compute_losses",
    "depth_l1",
    "first_crossing",
    "refine_crossing",
    "surface_depth",
    "surface_intervals",
    "psnr_from_mse",
    "render_losses",
    "render_rays",
    "renderer_param_groups",
    "sample_depths",
    "sample_pixels",
]
