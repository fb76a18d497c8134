"""`SlamState`: everything the SLAM loop carries from one frame to the next, saved and restored as one unit.

A checkpoint is `SlamState.state_dict()` (plus what the run writer adds about the process: log size, wall time,
peak memory); `load_state_dict` restores a state so that the remaining frames run exactly as without interruption.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from inrslam.slam.keyframes import KeyframeStore

# fields a checkpoint from an older version may lack, with how to fill them in
_OPTIONAL = {"rel", "rel_kf", "gicp_kfs", "photo_kfs", "photo_shifts", "photo_kf_rms", "track_losses", "lost_run",
             "loops", "loop_stats", "kf_odometry"}


@dataclass(eq=False)
class SlamState:
    """The loop's state for a sequence of `n` frames (tensors on the run's device unless noted).

    Attributes:
        model: the scene model F x G (an `nn.Module`); optimizers: its optimisers by name.
        store: the keyframe ray store; generator: the one random generator of every choice of the loop.
        next_frame: first frame not processed yet.
        est: (n, 4, 4) float32 estimated c2w (NaN = not yet processed).
        rel: (n, 4, 4) tracked pose of each frame relative to its keyframe `rel_kf` (n,) int64 numpy
            (docs/spec.md §7.6).
        gt: (n, 4, 4) float64 numpy ground-truth c2w (NaN = none); timestamps: (n,) float64 numpy, seconds.
        track_ms, map_ms: per tracked frame / per mapping call, milliseconds; init_ms: initialisation, ms.
        proc_psnr, proc_depth_l1: per-batch PSNR (dB) and depth L1 (m) seen while mapping.
        events: fallbacks and other exceptional events, `{"frame": i, "event": str}`.
        gicp_kfs: GICP keyframes (slam.gicp.target keyframe / local_map); the last is the current target.
        photo_kfs: photometric keyframes (slam.photo); the last is the current reference.
        photo_shifts: how far the last accepted photometric refinements moved their poses, metres (slam.photo.jump_*).
        photo_kf_rms: residual RMS of the first refinement onto the current photometric keyframe (0 = none yet;
            slam.photo.kf_rms_factor).
        track_losses: recent rendered-tracking losses of frames not lost (slam.lost.window; init's final first);
        lost_run: consecutive lost frames up to now.
        loops: accepted loop closures, `{"candidate": frame, "frame": frame, "T": (4, 4) list}` (slam.loop_closure);
        loop_stats: counts and times of loop closure (candidates, verified, rejected, accepted, ms).
        kf_odometry: each keyframe's c2w (4, 4) list in the odometry frame: the previous keyframe's moved by the
            tracked motion between them when it was added, whatever loops did to the poses since (the pose graph's
            odometry edges; slam.loop_closure).
    """

    model: torch.nn.Module
    optimizers: dict[str, torch.optim.Optimizer]
    store: KeyframeStore
    generator: torch.Generator
    est: Tensor
    rel: Tensor
    rel_kf: np.ndarray
    gt: np.ndarray
    timestamps: np.ndarray
    next_frame: int = 0
    track_ms: list[float] = field(default_factory=list)
    map_ms: list[float] = field(default_factory=list)
    init_ms: float = 0.0
    proc_psnr: list[float] = field(default_factory=list)
    proc_depth_l1: list[float] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)
    gicp_kfs: list[int] = field(default_factory=lambda: [0])
    photo_kfs: list[int] = field(default_factory=lambda: [0])
    photo_shifts: list[float] = field(default_factory=list)
    photo_kf_rms: float = 0.0
    track_losses: list[float] = field(default_factory=list)
    lost_run: int = 0
    loops: list[dict] = field(default_factory=list)
    loop_stats: dict[str, float] = field(default_factory=dict)
    kf_odometry: dict[int, list] = field(default_factory=dict)

    @classmethod
    def fresh(cls, model: torch.nn.Module, optimizers: dict, store: KeyframeStore, generator: torch.Generator,
              n_frames: int, device: torch.device) -> "SlamState":
        """The state before frame 0 of an `n_frames` sequence."""
        nan = torch.full((n_frames, 4, 4), float("nan"), dtype=torch.float32, device=device)
        return cls(model=model, optimizers=optimizers, store=store, generator=generator, est=nan.clone(),
                   rel=nan.clone(), rel_kf=np.full(n_frames, -1, dtype=np.int64),
                   gt=np.full((n_frames, 4, 4), np.nan), timestamps=np.zeros(n_frames))

    @property
    def device(self) -> torch.device:
        return self.est.device

    def state_dict(self) -> dict[str, Any]:
        """Every field, as CPU tensors / numpy arrays / plain Python values (`torch.save`-able)."""
        return {f.name: _save(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore every field from `state_dict()` output (in place for the model, optimisers, store, generator)."""
        names = [f.name for f in dataclasses.fields(self)]
        missing = [n for n in names if n not in state and n not in _OPTIONAL]
        if missing:
            raise KeyError(f"checkpoint lacks {', '.join(missing)}")
        for name in names:
            if name in state:
                setattr(self, name, _load(getattr(self, name), state[name], self.device))


def _save(value: Any) -> Any:
    if isinstance(value, torch.Generator):
        return value.get_state()
    if isinstance(value, Tensor):
        return value.detach().cpu()
    if isinstance(value, dict) and value and all(hasattr(v, "state_dict") for v in value.values()):
        return {k: v.state_dict() for k, v in value.items()}
    if isinstance(value, dict):
        return dict(value)
    if hasattr(value, "state_dict"):
        return value.state_dict()
    if isinstance(value, np.ndarray):
        return value.copy()
    if isinstance(value, list):
        return list(value)
    return value


def _load(current: Any, saved: Any, device: torch.device) -> Any:
    """The value to hold after loading `saved` into a field holding `current`."""
    if isinstance(current, torch.Generator):
        current.set_state(saved)
        return current
    if isinstance(current, Tensor):
        return saved.to(device)
    if isinstance(current, dict) and current and all(hasattr(v, "load_state_dict") for v in current.values()):
        for k, v in current.items():
            v.load_state_dict(saved[k])
        return current
    if hasattr(current, "load_state_dict"):
        current.load_state_dict(saved)
        return current
    if isinstance(current, list):
        return list(saved)
    if isinstance(current, dict):
        return dict(saved)
    return saved
