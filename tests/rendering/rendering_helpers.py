"""Analytic fields and rays shared by the rendering tests."""

from __future__ import annotations

from dataclasses import dataclass

import math

import torch
from torch import Tensor

T = 0.1  # truncation, metres
COLOR_LOGITS = torch.tensor([0.3, -0.8, 1.2], dtype=torch.float64)
COLOR = torch.sigmoid(COLOR_LOGITS)


@dataclass
class Out:
    sdf: Tensor
    rgb_logits: Tensor


class PlaneField:
    """Exact SDF of the plane n·x = h in T-units (metric / T), positive on the camera side; constant colour."""

    def __init__(self, normal, offset: float, density_scale: float | None = None):
        n = torch.as_tensor(normal, dtype=torch.float64)
        self.n = n / n.norm()
        self.h = offset
        self.density_scale = density_scale  # for `nerf`: output -k*sdf_metric (raw density, 1/m) instead

    def metric_sdf(self, x: Tensor) -> Tensor:
        return self.h - x @ self.n.to(x)

    def __call__(self, x: Tensor) -> Out:
        d = self.metric_sdf(x)
        s = -self.density_scale * d if self.density_scale else d / T
        return Out(s, COLOR_LOGITS.to(x).expand(x.shape[0], 3))

    def true_depth(self, origins: Tensor, dirs: Tensor) -> Tensor:
        n = self.n.to(dirs)
        return (self.h - origins @ n) / (dirs @ n)


class SphereField:
    """Exact SDF |x - c| - r in T-units; constant colour."""

    def __init__(self, centre, radius: float, density_scale: float | None = None):
        self.c = torch.as_tensor(centre, dtype=torch.float64)
        self.r = radius
        self.density_scale = density_scale

    def metric_sdf(self, x: Tensor) -> Tensor:
        return (x - self.c.to(x)).norm(dim=-1) - self.r

    def __call__(self, x: Tensor) -> Out:
        d = self.metric_sdf(x)
        s = -self.density_scale * d if self.density_scale else d / T
        return Out(s, COLOR_LOGITS.to(x).expand(x.shape[0], 3))

    def true_depth(self, origins: Tensor, dirs: Tensor) -> Tensor:
        """First intersection parameter t (z-depth for camera-z-1 dirs); NaN for misses."""
        oc = origins - self.c.to(dirs)
        a = (dirs * dirs).sum(-1)
        b = 2 * (oc * dirs).sum(-1)
        c = (oc * oc).sum(-1) - self.r**2
        disc = b * b - 4 * a * c
        return (-b - disc.sqrt()) / (2 * a)


def rotation_x(deg: float) -> Tensor:
    a = math.radians(deg)
    return torch.tensor([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]],
                        dtype=torch.float64)


def camera_rays(n_side: int = 7, half_fov: float = 0.6, c2w_rot: Tensor | None = None,
                origin=(0.0, 0.0, 0.0), dtype=torch.float64) -> tuple[Tensor, Tensor]:
    """Grid of camera-z-1 directions (x, y in [-half_fov, half_fov]) rotated into the world."""
    g = torch.linspace(-half_fov, half_fov, n_side, dtype=torch.float64)
    y, x = torch.meshgrid(g, g, indexing="ij")
    d = torch.stack([x.reshape(-1), y.reshape(-1), torch.ones(n_side * n_side, dtype=torch.float64)], -1)
    if c2w_rot is not None:
        d = d @ c2w_rot.T
    o = torch.tensor(origin, dtype=torch.float64).expand_as(d)
    return o.to(dtype).contiguous(), d.to(dtype)
