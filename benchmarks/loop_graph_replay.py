"""Replay a loop-closure run's loop edges on the same sequence without loop closure: what the pose graph alone
does to the trajectory, under different graph rules. Never asserted in tests.

    python benchmarks/loop_graph_replay.py runs/acc_loop runs/lc_loop

Reads the run without loop closure (`trajectory.txt`, `trajectory_gt.txt`, `keyframes.json`, the GICP targets in
`log.jsonl`) and the loop edges of the run with it (`checkpoints/latest.pt`). At each keyframe where the loop run
accepted edges, the replay adds them, optimises the keyframe graph (`corrected_keyframes`) and lets the frames follow
(`follow_keyframes`); frames after the keyframe move with it (as tracking onto the corrected map would place them).
Rules compared (ATE RMSE, aligned, cm):
- odometry edges measured from the current poses, or as tracked (the poses of the run without loop closure);
- frames of the tracker's local map (its last `slam.gicp.local_map_keyframes` GICP keyframes onward) moved rigidly
  with the newest keyframe, or following their own keyframes;
- a last optimisation after the last frame with every frame following its own keyframe.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("off", type=Path, help="run without loop closure")
    ap.add_argument("lc", type=Path, help="the same run with slam.loop_closure=true")
    ap.add_argument("--window", type=int, default=10, help="GICP keyframes in the tracker's local map")
    args = ap.parse_args()
    from inrslam.eval.trajectory import ate
    from inrslam.io.trajectory import read_tum
    from inrslam.runner.checkpoint import load_checkpoint
    from inrslam.slam.config import LoopConfig
    from inrslam.slam.loop_closure import corrected_keyframes, follow_keyframes

    _, est0 = read_tum(args.off / "trajectory.txt")
    _, gt = read_tum(args.off / "trajectory_gt.txt")
    kfs = json.loads((args.off / "keyframes.json").read_text())
    kfs = [int(k["frame"]) if isinstance(k, dict) else int(k) for k in (kfs["keyframes"] if isinstance(kfs, dict)
                                                                         else kfs)]
    loops = load_checkpoint(args.lc / "checkpoints" / "latest.pt")["loops"]
    n = len(est0)
    rel_kf = np.array([max(k for k in kfs if k <= j) for j in range(n)])
    recs = [json.loads(line) for line in (args.off / "log.jsonl").read_text().splitlines()]
    targets = {r["frame"]: r["gicp_target"] for r in recs if r.get("type") == "track" and "gicp_target" in r}
    cfg = LoopConfig()

    def window_start(i: int) -> int | None:
        ks = sorted({v for f, v in targets.items() if f <= i + 1})
        return ks[-args.window:][0] if ks else None

    def replay(tracked: bool, rigid: bool, final: bool) -> np.ndarray:
        est, added = est0.copy(), []
        for i in kfs:
            new = [lp for lp in loops if lp["frame"] == i]
            if not new:
                continue
            added += new
            ids = [k for k in kfs if k <= i]
            odo = np.stack([np.linalg.solve(est0[a], est0[b]) for a, b in zip(ids[:-1], ids[1:])]) if tracked else None
            old = est[ids]
            new_kf = corrected_keyframes(old, ids, added, cfg, odo)
            out = follow_keyframes(est, old, new_kf, ids, rel_kf, i, rigid_from=window_start(i) if rigid else None)
            out[i + 1:] = (new_kf[-1] @ np.linalg.inv(old[-1])) @ est[i + 1:]
            est = out
        if final and added:
            odo = np.stack([np.linalg.solve(est0[a], est0[b]) for a, b in zip(kfs[:-1], kfs[1:])]) if tracked else None
            old = est[kfs]
            est = follow_keyframes(est, old, corrected_keyframes(old, kfs, added, cfg, odo), kfs, rel_kf, n - 1)
        return est

    print(f"{args.off.name} -> {len(loops)} loop edges of {args.lc.name}; ATE [cm] without loop closure "
          f"{100 * ate(est0, gt)['rmse']:.3f}")
    print("| odometry edges | local map moved rigidly | final pass | ATE [cm] |\n|:--|:--|:--|--:|")
    for tracked in (False, True):
        for rigid in (True, False):
            for final in (False, True):
                e = replay(tracked, rigid, final)
                print(f"| {'tracked' if tracked else 'from current poses'} | {'yes' if rigid else 'no'} | "
                      f"{'yes' if final else 'no'} | {100 * ate(e, gt)['rmse']:.3f} |")


if __name__ == "__main__":
    main()
