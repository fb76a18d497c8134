"""`EheModel`: the EHE field with its ray marcher, objective and full-frame renderer (the interface the SLAM loop,
the run writer and `LoadedRun` use of a scene model)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from inrslam.fields import make_optimizer
from inrslam.fields.config import KernelChoice
from inrslam.geometry.camera import grid_directions, world_rays
from inrslam.geometry.intrinsics import Intrinsics
from inrslam.rendering import surface_depth
from inrslam.slam.ehe.config import EheConfig
from inrslam.slam.ehe.field import EheField
from inrslam.slam.ehe.fused_loss import bells, fused_losses, fused_weights
from inrslam.slam.ehe.losses import ehe_losses
from inrslam.slam.ehe.raymarch import PackedSamples, packed_samples_in_voxels
from inrslam.slam.ehe.rendering import COLOR_MIN_WEIGHT, EheRender, render_samples


class EheModel(nn.Module):
    """EHE scene model over `bounds` ((3, 2) metres) from a run config with an `ehe` section (and `field.kernel`,
    `field.decoder_kernel`).

    Attributes: field (`EheField`), truncation T metres, bounds (3, 2) buffer.
    """

    bounds: Tensor
    field: EheField

    def __init__(self, cfg, bounds: np.ndarray):
        super().__init__()
        self.ecfg: EheConfig = cfg.ehe
        self.field = EheField(self.ecfg, bounds, kernel=cfg.field.kernel, decoder_kernel=cfg.field.decoder_kernel)
        self.truncation = float(self.ecfg.truncation)
        self.kernel = KernelChoice(cfg.field.kernel).value  # auto / numba: fused losses on CPU (`loss`)
        self.register_buffer("bounds", torch.as_tensor(np.asarray(bounds), dtype=torch.float32))

    def make_optimizers(self, lr: float) -> dict[str, torch.optim.Optimizer]:
        """"field": Adam at `lr` on priors and decoders, row-wise lazy Adam on the dense level."""
        return {"field": make_optimizer(self.field, lr)}

    def samples(self, origins: Tensor, dirs: Tensor, generator: torch.Generator | None) -> PackedSamples:
        """The packed samples of world rays (R, 3) (t = z-depth) inside their hit voxels, every `step` · voxel_size
        (lattice offset jittered with `generator`; None: centred)."""
        c = self.ecfg
        return packed_samples_in_voxels(self.field.voxels, origins, dirs, c.step * c.voxel_size, c.max_hits,
                                        c.max_depth, generator)

    def render(self, origins: Tensor, dirs: Tensor, generator: torch.Generator | None) -> EheRender:
        """Render world rays (R, 3) (t = z-depth): samples inside the hit voxels (jittered with `generator`)."""
        return render_samples(self.field, origins, dirs, self.samples(origins, dirs, generator), self.truncation)

    def loss(self, origins: Tensor, dirs: Tensor, rgb: Tensor, depth: Tensor,
             generator: torch.Generator | None) -> dict[str, Tensor]:
        """Loss terms (`ehe_losses`) of world rays with observed rgb (R, 3) and depth (R,) metres.

        With `field.kernel` auto or numba on CPU tensors, compositing and losses run fused (`fused_losses`, one
        numba pass each way); with torch (or on another device) `render` then `ehe_losses`, the reference.
        """
        c = self.ecfg
        if self.kernel == "torch" or origins.device.type != "cpu":
            return ehe_losses(self.render(origins, dirs, generator), rgb, depth, c)
        z, ray, start, pts = self.samples(origins, dirs, generator)
        p, f = self.field.encode(pts)
        sdf = self.field.sdf_from(pts, p, f)
        bell = bells(sdf, self.truncation)
        use = torch.nonzero(fused_weights(sdf, z, start, self.truncation, bell[0]) > COLOR_MIN_WEIGHT).reshape(-1)
        colors = torch.sigmoid(self.field.rgb_from(p[use], f[use]))
        crow = torch.full_like(ray, -1)
        crow[use] = torch.arange(use.numel())
        has_d = (start[1:] > start[:-1]) & (depth > c.depth_min) & (depth < c.depth_max)
        terms, mse = fused_losses(sdf, colors, z, start, crow, rgb, depth, has_d, self.truncation, bell)
        l_rgb, l_depth, fs, sd = terms.unbind()
        total = c.color_weight * l_rgb + c.depth_weight * l_depth + c.free_space_weight * fs + c.sdf_weight * sd
        return {"total": total, "rgb": l_rgb, "depth": l_depth, "free_space": fs, "sdf": sd, "mse": mse,
                "depth_l1": l_depth.detach()}

    @torch.no_grad()
    def render_image(self, c2w: Tensor, intr: Intrinsics, n_coarse: int = 0,
                     chunk: int = 8192, depth: str = "expected", refine: int = 0) -> tuple[Tensor, Tensor]:
        """Full frame without measured depth (samples inside hit voxels need none; `n_coarse` and `refine` are
        unused).
        `depth`: "expected" (weighted mean) or "surface" (first + to - SDF crossing of the samples, `first_crossing`;
        the weighted mean where there is none), as `SceneModel.render_image`.
        Returns rgb (H, W, 3) in [0, 1] and depth (H, W) metres (0 where a ray hits no voxel)."""
        if depth not in ("expected", "surface"):
            raise ValueError(f"render_image: depth must be 'expected' or 'surface', got {depth!r}")
        dev = self.bounds.device
        H, W = intr.height, intr.width
        _, dirs_cam = grid_directions(intr, device=dev)
        rgbs, depths = [], []
        for s in range(0, dirs_cam.shape[0], chunk):
            o, d = world_rays(c2w, dirs_cam[s:s + chunk])
            out = self.render(o, d, None)
            rgbs.append(out.rgb)
            # padding repeats the last valid SDF: no crossing there
            depths.append(surface_depth(out.padded(out.sdf), out.padded(out.z), out.depth) if depth == "surface"
                          else out.depth)
        return torch.cat(rgbs).reshape(H, W, 3), torch.cat(depths).reshape(H, W)
