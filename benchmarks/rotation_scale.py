"""Systematic scale of a trajectory's relative motions against the ground truth: every `--gap` frames, the relative
rotation (as a rotation vector) and translation of the estimate are fitted as s x the ground truth's (least squares);
s < 1 means the tracker under-estimates the motion (a biased camera model or registration, not random error). Also
the net rotation from the first frame, estimate over reference (median over frames turned > 5 degrees): when it is
about s at every frame, the orientation error is that bias accumulated, not a random walk. And two views of the
positions: the 90th percentile of the translation error over 10 frames (`eval.trajectory.rpe`, delta 10: how noisy
the relative motions are) and the scale of a similarity alignment of the estimate onto the reference (> 1: the
estimated path is too short). Never asserted in tests.

    python benchmarks/rotation_scale.py runs/acc_7s runs/gicp_7s       # run directories with trajectory_gt.txt
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def motion_scale(est: np.ndarray, gt: np.ndarray, gap: int) -> tuple[float, float]:
    """(rotation scale, translation scale) of (N, 4, 4) `est` against `gt` over relative motions `gap` frames apart."""
    from scipy.spatial.transform import Rotation

    idx = np.arange(0, len(est) - gap, gap)
    rel = lambda T: np.linalg.inv(T[idx]) @ T[idx + gap]  # noqa: E731
    re, rg = rel(est), rel(gt)
    we, wg = (Rotation.from_matrix(r[:, :3, :3]).as_rotvec() for r in (re, rg))
    te, tg = re[:, :3, 3], rg[:, :3, 3]
    return float((we * wg).sum() / (wg * wg).sum()), float((te * tg).sum() / (tg * tg).sum())


def net_rotation_ratio(est: np.ndarray, gt: np.ndarray, min_deg: float = 5.0) -> float:
    """Median over frames whose reference turned more than `min_deg` from frame 0 of the estimate's net rotation
    from frame 0 projected on the reference's, over the reference's (1 = no bias)."""
    from scipy.spatial.transform import Rotation

    we = Rotation.from_matrix(np.swapaxes(est[:1, :3, :3], 1, 2) @ est[:, :3, :3]).as_rotvec()
    wg = Rotation.from_matrix(np.swapaxes(gt[:1, :3, :3], 1, 2) @ gt[:, :3, :3]).as_rotvec()
    n2 = (wg * wg).sum(1)
    keep = n2 > np.deg2rad(min_deg) ** 2
    return float(np.median((we * wg).sum(1)[keep] / n2[keep])) if keep.any() else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--gap", type=int, default=5)
    args = ap.parse_args()
    from inrslam.eval.trajectory import align_umeyama, rpe
    from inrslam.io.trajectory import read_tum

    print("| run | rotation scale | translation scale | net rotation ratio | 10-frame RPE p90 [mm] | similarity scale |")
    print("|:--|--:|--:|--:|--:|--:|")
    for run in args.runs:
        est, gt = read_tum(run / "trajectory.txt")[1], read_tum(run / "trajectory_gt.txt")[1]
        r, t = motion_scale(est, gt, args.gap)
        p90 = 1e3 * float(np.percentile(rpe(est, gt, delta=10)["trans_errors"], 90))
        s = align_umeyama(est[:, :3, 3], gt[:, :3, 3], with_scale=True)[2]
        print(f"| {run.name} | {r:.3f} | {t:.3f} | {net_rotation_ratio(est, gt):.3f} | {p90:.1f} | {s:.4f} |")


if __name__ == "__main__":
    main()
