"""The EHE scene representation (docs/ehe.md §2): s(x) = trilinear SDF prior of the sparse voxels + a residual
decoded from one 2 cm dense feature level; colour decoded from the same features."""

from __future__ import annotations

from typing import cast

import numpy as np
import torch
from torch import Tensor, nn

from inrslam.fields.config import KernelChoice, TouchedRows
from inrslam.fields.encoders import GridEncoder
from inrslam.fields.models import FieldOutput, grid_decoder, run_grid_decoder
from inrslam.slam.ehe.config import EheConfig
from inrslam.slam.ehe.sdf_kernel import ehe_sdf, fusable
from inrslam.slam.ehe.voxels import VoxelGrid


class EheField(nn.Module):
    """x (N, 3) metres -> FieldOutput(sdf (N,) T-units, rgb_logits (N, 3)).

    s(x) = s_prior(x) + D_s([f(p̂), p̂]),  c(x) = D_c([p̂, f(p̂)]) (sigmoid at render time), where s_prior is the
    trilinear interpolation of the containing voxel's 8 vertex priors (`VoxelGrid.prior_at`), f the dense level
    (one level, `fine_cell` metres, `feature_dim` features, fused kernels) and D_s, D_c Linear-ReLU-Linear without
    biases (`hidden_dim`). p̂ = (x − b_min)/(b_max − b_min) over the scene box.
    """

    bounds: Tensor  # (3, 2) metres
    voxels: VoxelGrid
    grid: GridEncoder

    def __init__(self, cfg: EheConfig, bounds: np.ndarray, kernel: KernelChoice = KernelChoice.AUTO,
                 decoder_kernel: KernelChoice = KernelChoice.TORCH):
        super().__init__()
        self.decoder_kernel = KernelChoice(decoder_kernel).value
        b = np.asarray(bounds, dtype=np.float64)
        self.truncation = float(cfg.truncation)
        self.register_buffer("bounds", torch.tensor(b, dtype=torch.float32))
        self.voxels = VoxelGrid(b, cfg.voxel_size, kernel)
        self.grid = GridEncoder(b[:, 1] - b[:, 0], cfg.fine_cell, cfg.fine_cell, 1, cfg.feature_dim, hashed=False,
                                log2_hashmap_size=19, faithful=False, init=cfg.grid_init, kernel=kernel)
        self.grid.touched = TouchedRows(cfg.touched_rows)
        self.sdf_net = grid_decoder(cfg.feature_dim + 3, cfg.hidden_dim, 1)
        self.rgb_net = grid_decoder(3 + cfg.feature_dim, cfg.hidden_dim, 3)

    def normalise(self, x: Tensor) -> Tensor:
        """p̂ = (x − b_min)/(b_max − b_min), (N, 3)."""
        return (x - self.bounds[:, 0]) / (self.bounds[:, 1] - self.bounds[:, 0])

    def encode(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """(p̂ (N, 3), dense-level features f (N, F)) of points x (N, 3) metres."""
        p = self.normalise(x)
        return p, self.grid(p)

    def sdf_from(self, x: Tensor, p: Tensor, f: Tensor) -> Tensor:
        """s = s_prior(x) + D_s([f, p̂]), (N,) T-units, from `encode`'s outputs.

        With the fused kernels on (`field.kernel` and `field.decoder_kernel` not torch) and CPU tensors, one numba
        pass each way (`sdf_kernel.ehe_sdf`); else the prior lookup, then the decoder (the reference)."""
        w1, w2 = cast(nn.Linear, self.sdf_net[0]).weight, cast(nn.Linear, self.sdf_net[2]).weight
        if (self.decoder_kernel != "torch" and self.voxels.priors.kernel != KernelChoice.TORCH
                and fusable(x, f, self.voxels.priors.table, w1, w2)):
            return ehe_sdf(x, f, p, self.voxels, w1, w2)
        return self.voxels.prior_at(x) + self._dec(self.sdf_net, torch.cat([f, p], dim=-1))[:, 0]

    def rgb_from(self, p: Tensor, f: Tensor) -> Tensor:
        """Colour logits D_c([p̂, f]), (N, 3), from `encode`'s outputs."""
        return self._dec(self.rgb_net, torch.cat([p, f], dim=-1))

    def residual(self, x: Tensor) -> Tensor:
        """The decoded SDF residual alone, (N,) T-units."""
        p, f = self.encode(x)
        return self._dec(self.sdf_net, torch.cat([f, p], dim=-1))[:, 0]

    def _dec(self, net: nn.Sequential, x: Tensor) -> Tensor:
        """A Linear-ReLU-Linear decoder on x (N, in) -> (N, out), by `field.decoder_kernel`."""
        return run_grid_decoder(net, x, self.decoder_kernel)

    def forward(self, x: Tensor) -> FieldOutput:
        p, f = self.encode(x)
        return FieldOutput(self.sdf_from(x, p, f), self.rgb_from(p, f))

    def sdf(self, x: Tensor) -> Tensor:
        """SDF only, (N,) T-units."""
        p, f = self.encode(x)
        return self.sdf_from(x, p, f)
