"""Check every loop edge a run accepted against its ground truth: was any of them a false loop?

    python benchmarks/loop_edges_check.py runs/lc_symmetric [runs/lc_loop ...]

Reads the run's checkpoint (`checkpoints/latest.pt`, which holds the loop edges) and `trajectory_gt.txt`. For each
edge (candidate keyframe a, keyframe b, measured T_ab) it prints how far T_ab is from the ground-truth relative
pose, in cm and degrees; a false loop (a look-alike place) is off by metres or tens of degrees.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def edge_errors(run_dir: Path) -> list[tuple[int, int, float, float]]:
    """(candidate, frame, translation error cm, rotation error deg) of every loop edge of a run."""
    from inrslam.eval.trajectory import rotation_angle_deg
    from inrslam.io.trajectory import read_tum
    from inrslam.runner.checkpoint import load_checkpoint

    state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    _, gt = read_tum(run_dir / "trajectory_gt.txt")
    out = []
    for lp in state.get("loops", []):
        a, b, T = lp["candidate"], lp["frame"], np.asarray(lp["T"], dtype=np.float64)
        G = np.linalg.solve(gt[a], gt[b])
        ang = float(rotation_angle_deg(T[:3, :3] @ G[:3, :3].T))  # atan2 form: exact near 0
        out.append((a, b, float(np.linalg.norm(T[:3, 3] - G[:3, 3]) * 100), ang))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    args = ap.parse_args()
    print("| run | loop edges | max error [cm] | max error [deg] | median [cm] |")
    print("|:--|--:|--:|--:|--:|")
    for run in args.runs:
        if not (run / "checkpoints" / "latest.pt").is_file() or not (run / "trajectory_gt.txt").is_file():
            print(f"| {run.name} | not a finished run directory (checkpoint and trajectory_gt.txt; skipped) | | | |")
            continue
        e = edge_errors(run)
        if not e:
            print(f"| {run.name} | 0 | — | — | — |")
            continue
        t = np.array([x[2] for x in e])
        r = np.array([x[3] for x in e])
        print(f"| {run.name} | {len(e)} | {t.max():.2f} | {r.max():.2f} | {np.median(t):.2f} |")


if __name__ == "__main__":
    main()
