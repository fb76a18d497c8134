"""The global keyframe ray store (spec §5.3): a random fraction of each keyframe's pixels, sampled uniformly
over the union of all stored rays at mapping time and transformed with the keyframe's *current* pose."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor


@dataclass
class KeyframeStore:
    """Stored rays of all keyframes (on `device`).

    Attributes:
        frame_ids: frame index of each keyframe, in insertion order (slot k = keyframe k).
        dirs: (M, 3) camera-frame ray directions (z = 1).
        rgb: (M, 3) colours in [0, 1].
        depth: (M,) measured depth in metres (0 = none).
        slot: (M,) keyframe slot of each ray.
    """

    device: torch.device = torch.device("cpu")
    frame_ids: list[int] = field(default_factory=list)
    dirs: Tensor = None  # type: ignore[assignment]
    rgb: Tensor = None  # type: ignore[assignment]
    depth: Tensor = None  # type: ignore[assignment]
    slot: Tensor = None  # type: ignore[assignment]

    def __post_init__(self):
        if self.dirs is None:
            self.dirs = torch.zeros(0, 3, device=self.device)
            self.rgb = torch.zeros(0, 3, device=self.device)
            self.depth = torch.zeros(0, device=self.device)
            self.slot = torch.zeros(0, dtype=torch.long, device=self.device)

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def n_rays(self) -> int:
        return int(self.depth.shape[0])

    def add(self, frame_id: int, dirs: Tensor, rgb: Tensor, depth: Tensor) -> None:
        """Append the chosen rays of one keyframe."""
        k = len(self.frame_ids)
        self.frame_ids.append(int(frame_id))
        self.dirs = torch.cat([self.dirs, dirs.to(self.device)])
        self.rgb = torch.cat([self.rgb, rgb.to(self.device)])
        self.depth = torch.cat([self.depth, depth.to(self.device)])
        self.slot = torch.cat([self.slot, torch.full((dirs.shape[0],), k, dtype=torch.long, device=self.device)])

    def sample(self, n: int, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """n rays uniformly over all stored rays (with replacement when n exceeds the store).

        Returns: slot (n,), dirs (n, 3), rgb (n, 3), depth (n,).
        """
        m = self.n_rays
        if n >= m:
            idx = torch.randint(0, m, (n,), generator=generator, device=generator.device).to(self.device)
        else:
            idx = torch.randperm(m, generator=generator, device=generator.device)[:n].to(self.device)
        return self.slot[idx], self.dirs[idx], self.rgb[idx], self.depth[idx]

    def state_dict(self) -> dict:
        return {"frame_ids": list(self.frame_ids), "dirs": self.dirs.cpu(), "rgb": self.rgb.cpu(),
                "depth": self.depth.cpu(), "slot": self.slot.cpu()}

    def load_state_dict(self, state: dict) -> None:
        self.frame_ids = list(state["frame_ids"])
        self.dirs = state["dirs"].to(self.device)
        self.rgb = state["rgb"].to(self.device)
        self.depth = state["depth"].to(self.device)
        self.slot = state["slot"].to(self.device)
