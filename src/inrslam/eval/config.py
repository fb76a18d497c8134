"""Evaluation protocol settings (`EvalConfig`, the `eval:` section of a run config)."""

from __future__ import annotations

import enum
from dataclasses import dataclass, fields
from typing import Any


class Alignment(str, enum.Enum):
    """How the estimated trajectory is aligned to ground truth before ATE."""

    SE3 = "se3"  # rotation + translation (Horn 1987 / Umeyama 1991 without scale) — the benchmark's choice
    SIM3 = "sim3"  # rotation + translation + scale (monocular-style)
    NONE = "none"  # no alignment (both trajectories already share a frame)


class HeldoutDepth(str, enum.Enum):
    """Which depth of a held-out render is compared with the observed depth (`SlamModel.render_image`)."""

    EXPECTED = "expected"  # G's weighted mean depth sum_i w_i z_i (the benchmark's)
    SURFACE = "surface"  # the first + to - SDF crossing along the ray (expected where there is none, and for nerf)


@dataclass
class EvalConfig:
    """Protocol of `inrslam.eval.run.evaluate_run` (defaults = the benchmark's protocol, docs/spec.md §8, ICP off)."""

    align: Alignment = Alignment.SE3  # ATE alignment: se3 | sim3 | none
    max_time_diff: float = 1e-3  # s, timestamp association tolerance between trajectory.txt and trajectory_gt.txt
    rpe_delta: int = 1  # frames between the two poses of an RPE pair
    cull_every: int = 2  # use every n-th ground-truth camera for culling (`--skip 2`)
    cull_eps: float = 0.03  # m, occlusion tolerance: observed if z < rendered depth + eps
    cull_occlusion: bool = True  # also remove occluded faces (`--remove_occlusion`), not only out-of-frustum ones
    n_samples: int = 200_000  # points sampled on each mesh surface (area-weighted)
    threshold: float = 0.05  # m, completion-ratio distance threshold
    icp: bool = False  # point-to-point ICP of the reconstruction onto the GT mesh before the 3-D metrics
    seed: int = 0  # surface-sampling seed (reconstruction uses seed, GT uses seed + 1)
    mesh_metrics: bool = True  # compute Acc / Comp / Comp% when both meshes exist
    virtual_cameras: str = ""  # TUM file of extra (virtual) camera poses added to the culling cameras (Co-SLAM)
    cull_gt: bool = False  # also cull the GT mesh with the same cameras (unseen GT regions then do not count)
    enabled: bool = True  # evaluate at the end of a SLAM run
    heldout_every: int = 10  # held-out full-frame renders of every N-th frame (PSNR/SSIM/depth L1; 0 = off)
    heldout_max: int = 20  # at most this many held-out renders, spread over the sequence when there are more
    heldout_samples: int = 96  # uniform samples per ray used to find the surface in held-out renders
    heldout_refine: int = 0  # > 0: held-out surface search looks again with this many samples inside each of the first
    # intervals that may hold a thin surface the uniform samples stepped over (0 = off, the paper's search)
    heldout_depth: HeldoutDepth = HeldoutDepth.EXPECTED  # held-out depth: expected (weighted mean) | surface (SDF zero)

    @classmethod
    def from_any(cls, obj: Any = None) -> "EvalConfig":
        """An `EvalConfig` from None, an `EvalConfig`, a mapping or any object with some of these attribute names
        (e.g. the run config's `eval` section, which also holds unrelated keys: those are ignored)."""
        if obj is None:
            return cls()
        if isinstance(obj, cls):
            return obj
        get = obj.get if isinstance(obj, dict) else (lambda k, d: getattr(obj, k, d))
        kw = {}
        for f in fields(cls):
            v = get(f.name, None)
            if v is not None:
                kw[f.name] = v
        if "align" in kw:
            kw["align"] = Alignment(getattr(kw["align"], "value", kw["align"]))
        if "heldout_depth" in kw:
            kw["heldout_depth"] = HeldoutDepth(getattr(kw["heldout_depth"], "value", kw["heldout_depth"]))
        return cls(**kw)

    def protocol(self) -> dict:
        """JSON-ready description of this protocol (stored under `metrics["protocol"]`)."""
        return {
            "alignment": Alignment(self.align).value,
            "association": {"method": "timestamp", "max_diff_s": self.max_time_diff},
            "rpe_delta": self.rpe_delta,
            "culling": {
                "every": self.cull_every,
                "eps": self.cull_eps,
                "occlusion": self.cull_occlusion,
                "cameras": "ground truth",
                "culled": "reconstructed and ground-truth meshes" if self.cull_gt else "reconstructed mesh",
                "virtual_cameras": self.virtual_cameras or None,
            },
            "n_samples": self.n_samples,
            "threshold": self.threshold,
            "icp": self.icp,
            "seed": self.seed,
        }
