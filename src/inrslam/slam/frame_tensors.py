"""One RGB-D frame on the device, with the ray and pixel-sampling helpers tracking, mapping and keyframes use."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from inrslam.data.frame import Frame
from inrslam.geometry.camera import pixel_directions
from inrslam.rendering.sampling import distinct_indices, sample_pixels


class FrameTensors:
    """`frame` as flat tensors on `device`: rgb (H*W, 3) in [0, 1], depth (H*W,) metres (0 = none)."""

    def __init__(self, frame: Frame, device: torch.device):
        self.frame = frame
        self.intr = frame.intrinsics
        self.rgb = torch.from_numpy(np.ascontiguousarray(frame.rgb, dtype=np.float32)).to(device).reshape(-1, 3)
        self.depth = torch.from_numpy(np.ascontiguousarray(frame.depth, dtype=np.float32)).to(device).reshape(-1)
        self.device = device
        self._silhouettes: tuple[float, float, int] | None = None  # `set_silhouettes`' arguments
        self._behind: Tensor | None = None

    def set_silhouettes(self, behind: float, jump: float, radius: int) -> None:
        """Give the silhouette pixels (`silhouettes`) the SDF band end `behind` (units of T), every other pixel 1;
        computed on first use (a frame that is neither mapped nor kept never pays for it)."""
        self._silhouettes, self._behind = (behind, jump, radius), None

    @property
    def behind(self) -> Tensor | None:
        """(H*W,) per-pixel end of the SDF band, units of T; None when no silhouettes are set."""
        if self._behind is None and self._silhouettes is not None:
            behind, jump, radius = self._silhouettes
            H, W = self.intr.height, self.intr.width
            sil = silhouettes(self.depth.reshape(H, W), jump, radius).reshape(-1)
            self._behind = torch.where(sil, torch.full_like(self.depth, behind), torch.ones_like(self.depth))
        return self._behind

    def behind_of(self, idx: Tensor) -> Tensor | None:
        """(n,) band ends of the pixels `idx`, or None when no silhouettes are set."""
        behind = self.behind
        return None if behind is None else behind[idx]

    def training_rays(self, idx: Tensor) -> tuple[Tensor, ...]:
        """`rays(idx)`, plus the pixels' band ends (n,) when silhouettes are set: what mapping's losses take."""
        behind = self.behind_of(idx)
        return self.rays(idx) if behind is None else self.rays(idx) + (behind,)

    def rays(self, idx: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(n,) flat pixel indices -> dirs_cam (n, 3) with z = 1, rgb (n, 3), depth (n,)."""
        W = self.intr.width
        u, v = (idx % W).float(), torch.div(idx, W, rounding_mode="floor").float()
        return pixel_directions(self.intr, u, v), self.rgb[idx], self.depth[idx]

    def sample(self, n: int, generator: torch.Generator, edge: int = 0) -> tuple[Tensor, Tensor, Tensor]:
        """n distinct pixels uniformly inside an `edge`-pixel border (no border if it would leave none)."""
        return self.rays(self.sample_index(n, generator, edge))

    def sample_distinct(self, n: int, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
        """n distinct pixels of the whole image, uniformly (`distinct_indices`: no full permutation of H*W, which
        costs ~3 ms at 640x480; a different draw from `sample` for the same generator state)."""
        H, W = self.intr.height, self.intr.width
        return self.rays(distinct_indices(H * W, min(n, H * W), generator).to(self.device))

    def sample_index(self, n: int, generator: torch.Generator, edge: int = 0) -> Tensor:
        """The (n,) flat pixel indices `sample` draws."""
        H, W = self.intr.height, self.intr.width
        if H - 2 * edge <= 0 or W - 2 * edge <= 0:
            edge = 0
        n = min(n, (H - 2 * edge) * (W - 2 * edge))
        u, v = sample_pixels(H, W, n, edge, generator, self.device)
        return v * W + u

    def edge_pixels(self, jump: float, near_only: bool = False) -> Tensor:
        """Flat indices of the depth-edge pixels: valid depth differing by more than `jump` metres from a valid
        4-neighbour (both sides of a silhouette), or with `near_only` the near side only (`silhouettes`, radius 1)."""
        H, W = self.intr.height, self.intr.width
        depth = self.depth.reshape(H, W)
        edge = silhouettes(depth, jump, 1) if near_only else depth_edges(depth, jump)
        return torch.nonzero(edge.reshape(-1)).reshape(-1)

    def random_rays(self, n: int, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
        """n distinct pixels drawn from a full random permutation (the keyframe ray store's choice)."""
        return self.rays(self.random_index(n, generator))

    def random_index(self, n: int, generator: torch.Generator) -> Tensor:
        """The (n,) flat pixel indices `random_rays` draws."""
        H, W = self.intr.height, self.intr.width
        return torch.randperm(H * W, generator=generator)[:n].to(self.device)


def depth_edges(depth: Tensor, jump: float) -> Tensor:
    """(H, W) bool: valid depth (> 0) whose difference to a valid 4-neighbour exceeds `jump` (same unit)."""
    edge = torch.zeros_like(depth, dtype=torch.bool)
    valid = depth > 0
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        step = valid[a] & valid[b] & ((depth[a] - depth[b]).abs() > jump)
        edge[a] |= step
        edge[b] |= step
    return edge


def silhouettes(depth: Tensor, jump: float, radius: int) -> Tensor:
    """(H, W) bool: the near side of depth silhouettes — valid depth with a valid pixel at most `radius` pixels away
    (Chebyshev) whose depth is more than `jump` larger (same unit). A ray there grazes an object and leaves it just
    behind its depth."""
    far = torch.where(depth > 0, depth, torch.zeros_like(depth))
    k = 2 * int(radius) + 1
    farthest = torch.nn.functional.max_pool2d(far[None, None], k, stride=1, padding=int(radius))[0, 0]
    return (depth > 0) & (farthest - depth > jump)
