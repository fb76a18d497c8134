"""The scene model of a run: a field F, a rendering function G and the ray-batch objective they share in
initialisation, tracking and mapping (docs/spec.md §6: the same total loss everywhere)."""

from __future__ import annotations

import dataclasses
from typing import Protocol

import numpy as np
import torch
from torch import Tensor, nn

from inrslam.fields import Field, FieldConfig, build_field, make_optimizer
from inrslam.geometry.camera import grid_directions, world_rays
from inrslam.geometry.intrinsics import Intrinsics
from inrslam.rendering import (
    LossConfig,
    RenderConfig,
    RenderOutput,
    SamplingConfig,
    SdfToWeights,
    build_renderer,
    first_crossing,
    refine_crossing,
    render_losses,
    render_rays,
    renderer_param_groups,
    sample_depths,
    surface_depth,
)


class ModelConfig(Protocol):
    """The sections of a run's configuration the scene model reads. `inrslam.config.RunConfig` (a layer above
    slam, so not imported here) has them; so does any object with these four attributes."""

    field: FieldConfig
    render: RenderConfig
    sampling: SamplingConfig
    loss: LossConfig


class SceneModel(nn.Module):
    """F x G with the configured sampling and losses.

    Args:
        cfg: the run's configuration (`RunConfig`; only `field`, `render`, `sampling` and `loss` are read).
        bounds: (3, 2) scene box in metres.
    """

    bounds: Tensor  # (3, 2) metres, a buffer
    field: Field  # F: (N, 3) metres -> sdf (N,) T-units, rgb_logits (N, 3)
    renderer: SdfToWeights  # G: per-sample SDF -> compositing weights
    truncation: float  # T, metres

    def __init__(self, cfg: ModelConfig, bounds: np.ndarray):
        super().__init__()
        self.cfg = cfg
        self.field = build_field(cfg.field, np.asarray(bounds, dtype=np.float64))
        self.renderer = build_renderer(cfg.render)
        self.truncation = float(cfg.field.truncation)
        self.register_buffer("bounds", torch.as_tensor(np.asarray(bounds), dtype=torch.float32))

    # -- optimisers -------------------------------------------------------------------------------------------
    def make_optimizers(self, lr: float) -> dict[str, torch.optim.Optimizer]:
        """Scene optimiser(s): "field", the field's (sparse-aware) Adam at `lr`, plus "render", Adam on the learnable
        G parameters if any (at `render.beta_lr`)."""
        opts: dict[str, torch.optim.Optimizer] = {"field": make_optimizer(self.field, lr)}
        groups = renderer_param_groups(self.renderer, self.cfg.render)
        if groups:
            opts["render"] = torch.optim.Adam(groups)
        return opts

    # -- objective ----------------------------------------------------------------------------------------------
    def loss(
        self,
        c2w: Tensor,
        dirs_cam: Tensor,
        rgb: Tensor,
        depth: Tensor,
        generator: torch.Generator | None,
        behind: Tensor | None = None,
    ) -> tuple[dict[str, Tensor], RenderOutput]:
        """Render rays and compute the loss terms (differentiable in the field, G's parameters and `c2w`).

        Args:
            c2w: (4, 4) shared or (R, 4, 4) per-ray camera-to-world, metres.
            dirs_cam: (R, 3) camera-frame directions (z = 1).
            rgb: (R, 3) observed colours in [0, 1]; depth: (R,) observed z-depth in metres (0 = none).
            generator: sample-jitter generator (None: the global one).
            behind: (R,) per-ray end of the SDF band behind the depth, units of T (None: `loss.behind`).
        Returns:
            (loss terms: 0-d tensors, 'total' the weighted sum; the RenderOutput of the R rays)
        """
        origins, dirs = world_rays(c2w, dirs_cam)
        with torch.no_grad():
            z = sample_depths(depth, dirs.detach(), origins.detach(), self.bounds, self.cfg.sampling,
                              self.truncation, generator)
        return render_losses(self.field, self.renderer, origins, dirs, z, rgb, depth, self.cfg.loss, self.truncation,
                             behind)

    # -- held-out rendering (no measured depth) -----------------------------------------------------------
    @torch.no_grad()
    def render_image(self, c2w: Tensor, intr: Intrinsics, n_coarse: int = 96,
                     chunk: int = 4096, depth: str = "expected", refine: int = 0) -> tuple[Tensor, Tensor]:
        """Render a full frame *without* the measured depth: coarse uniform samples to the box exit, the first
        + to - SDF crossing then serves as the depth guiding the standard free-space + surface sampling.

        Args:
            c2w: (4, 4) camera-to-world, metres; intr: the camera (H = intr.height, W = intr.width).
            n_coarse: uniform samples per ray of the surface search; chunk: rays per field batch.
            depth: "expected" = G's weighted mean depth sum_i w_i z_i; "surface" = the first + to - SDF crossing
                among the final samples (`first_crossing`), the weighted mean where a ray has none (and for a
                G that is not SDF-based: nerf).
            refine: > 0: the surface search looks again, with this many more samples each, inside the first
                intervals of the uniform samples that may hold a surface (`refine_crossing`: thin objects the
                uniform samples step over), and "surface" reports that crossing where it finds one.
        Returns: rgb (H, W, 3) in [0, 1], depth (H, W) in metres.
        """
        if depth not in ("expected", "surface"):
            raise ValueError(f"render_image: depth must be 'expected' or 'surface', got {depth!r}")
        surface = depth == "surface" and getattr(self.renderer, "sdf_based", True)  # nerf: no SDF to cross
        dev = self.bounds.device
        H, W = intr.height, intr.width
        _, dirs_cam = grid_directions(intr, device=dev)
        dirs_all = dirs_cam @ c2w[:3, :3].T
        rgb_out, depth_out = [], []
        no_jitter = dataclasses.replace(self.cfg.sampling, jitter=False)  # deterministic evaluation renders
        for s in range(0, dirs_all.shape[0], chunk):
            dirs = dirs_all[s:s + chunk]
            origins = c2w[:3, 3].expand_as(dirs)
            guess, refined = self.surface_guess(origins, dirs, n_coarse, refine)
            z = sample_depths(guess, dirs, origins, self.bounds, no_jitter, self.truncation, None)
            out = render_rays(self.field, self.renderer, origins, dirs, z, self.truncation)
            rgb_out.append(out.rgb)
            d = surface_depth(out.sdf, out.z, out.depth) if surface else out.depth
            depth_out.append(torch.where(refined, guess, d) if surface else d)
        return torch.cat(rgb_out).reshape(H, W, 3), torch.cat(depth_out).reshape(H, W)

    @torch.no_grad()
    def surface_guess(self, origins: Tensor, dirs: Tensor, n: int, refine: int = 0) -> tuple[Tensor, Tensor]:
        """(R,) z of the first + to - SDF crossing on n uniform samples up to the box exit (0 where none), and (R,)
        bool: where `refine` > 0 found it again with `refine_crossing` (then that z; else always False)."""
        zero = torch.zeros(dirs.shape[0], device=dirs.device)
        sampling = _uniform_only(self.cfg.sampling, n)
        z = sample_depths(zero, dirs, origins, self.bounds, sampling, self.truncation, None)
        pts = origins[:, None, :] + z[..., None] * dirs[:, None, :]
        sdf = self.field.sdf(pts.reshape(-1, 3)).reshape(z.shape)
        coarse = first_crossing(sdf, z)[0]
        if refine <= 0:
            return coarse, torch.zeros_like(coarse, dtype=torch.bool)
        T = self.truncation
        zr, found = refine_crossing(lambda p: self.field.sdf(p) * T, origins, dirs, z, sdf * T, refine)
        return torch.where(found, zr, coarse), found


def _uniform_only(sampling_cfg: SamplingConfig, n: int) -> SamplingConfig:
    return dataclasses.replace(sampling_cfg, n_uniform=n, jitter=False)
