"""The global keyframe ray store (docs/spec.md §5.3): a random fraction of each keyframe's pixels, sampled uniformly
over the union of all stored rays at mapping time and transformed with the keyframe's *current* pose."""

from __future__ import annotations

from typing import Any, Mapping

import torch
from torch import Tensor


class KeyframeStore:
    """Stored rays of all keyframes (on `device`).

    Attributes:
        frame_ids: frame index of each keyframe, in insertion order (slot k = keyframe k).
        dirs: (M', 3) camera-frame ray directions (z = 1); rgb: (M', 3) in [0, 1]; depth: (M',) metres (0 = none);
        slot: (M',) int64 keyframe slot of each ray. Buffers grow by doubling; the first `n_rays` rows are in use.
        behind: (M',) per-ray end of the SDF band behind the depth (units of T), or None when no keyframe gave one
            (`loss.silhouette_behind`); a store holds it for all its rays or for none.
    """

    device: torch.device
    frame_ids: list[int]
    dirs: Tensor  # (M', 3)
    rgb: Tensor  # (M', 3)
    depth: Tensor  # (M',)
    slot: Tensor  # (M',) int64
    behind: Tensor | None  # (M',) or None

    def __init__(self, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.frame_ids: list[int] = []
        self.dirs = torch.zeros(0, 3, device=self.device)
        self.rgb = torch.zeros(0, 3, device=self.device)
        self.depth = torch.zeros(0, device=self.device)
        self.slot = torch.zeros(0, dtype=torch.long, device=self.device)
        self.behind = None
        self._n = 0

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def n_rays(self) -> int:
        return self._n

    def add(self, frame_id: int, dirs: Tensor, rgb: Tensor, depth: Tensor, behind: Tensor | None = None) -> None:
        """Append the chosen rays of one keyframe as the next slot: dirs (n, 3) camera frame (z = 1), rgb (n, 3),
        depth (n,) metres, behind (n,) band ends in units of T (None: the loss's own; all keyframes or none)."""
        k, n = len(self.frame_ids), dirs.shape[0]
        if k and (behind is None) != (self.behind is None):
            raise ValueError("KeyframeStore.add: `behind` must be given for every keyframe or for none")
        if behind is not None and self.behind is None:
            self.behind = torch.ones(self.depth.shape[0], device=self.device)
        need = self._n + n
        if need > self.depth.shape[0]:
            cap = max(need, 2 * self.depth.shape[0])
            self.dirs, self.rgb, self.depth, self.slot = (
                _grow(t, cap) for t in (self.dirs, self.rgb, self.depth, self.slot))
            if self.behind is not None:
                self.behind = _grow(self.behind, cap)
        sl = slice(self._n, need)
        self.dirs[sl], self.rgb[sl], self.depth[sl] = dirs.to(self.device), rgb.to(self.device), depth.to(self.device)
        if behind is not None and self.behind is not None:
            self.behind[sl] = behind.to(self.device)
        self.slot[sl] = k
        self._n = need
        self.frame_ids.append(int(frame_id))

    def sample(self, n: int, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """n rays uniformly over all stored rays: without replacement while the store is small (n < rays < 8 n), with
        replacement beyond (a full permutation of millions of rays every iteration would dominate mapping) and when
        it holds at most n rays (a batch larger than the store repeats rays).

        Returns: slot (n,), dirs (n, 3), rgb (n, 3), depth (n,).
        """
        return self.take(self.sample_index(n, generator))

    def sample_index(self, n: int, generator: torch.Generator) -> Tensor:
        """The (n,) ray indices `sample` draws."""
        m = self._n
        if m >= 8 * n or n >= m:
            idx = torch.randint(0, m, (n,), generator=generator, device=generator.device)
        else:
            idx = torch.randperm(m, generator=generator, device=generator.device)[:n]
        return idx.to(self.device)

    def take(self, idx: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Rays `idx` (n,): slot (n,), dirs (n, 3), rgb (n, 3), depth (n,)."""
        return self.slot[idx], self.dirs[idx], self.rgb[idx], self.depth[idx]

    def behind_of(self, idx: Tensor) -> Tensor | None:
        """(n,) band ends of rays `idx`, or None when the store holds none."""
        return None if self.behind is None else self.behind[idx]

    def state_dict(self) -> dict[str, Any]:
        """The rays in use (on the CPU) and the keyframe frame ids, for checkpoints."""
        m = self._n

        def rows(t: Tensor) -> Tensor:  # a copy of the rows in use: torch.save of a view writes its whole buffer,
            return t[:m].cpu() if t.device.type != "cpu" else t[:m].clone()  # up to twice them (`_grow` doubles)

        state = {"frame_ids": list(self.frame_ids), "dirs": rows(self.dirs), "rgb": rows(self.rgb),
                 "depth": rows(self.depth), "slot": rows(self.slot)}
        if self.behind is not None:
            state["behind"] = rows(self.behind)
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore a `state_dict` (moved to this store's device)."""
        self.frame_ids = list(state["frame_ids"])
        self.dirs = state["dirs"].to(self.device)
        self.rgb = state["rgb"].to(self.device)
        self.depth = state["depth"].to(self.device)
        self.slot = state["slot"].to(self.device)
        self.behind = state["behind"].to(self.device) if "behind" in state else None
        self._n = int(self.depth.shape[0])


def _grow(t: Tensor, capacity: int) -> Tensor:
    out = t.new_zeros((capacity,) + tuple(t.shape[1:]))
    out[: t.shape[0]] = t
    return out
