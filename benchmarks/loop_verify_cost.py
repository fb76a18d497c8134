"""Loop verification: cost and accuracy of two settings on the same candidate pairs, in one run.

    python benchmarks/loop_verify_cost.py runs/lc_loop runs/lc_handheld
    python benchmarks/loop_verify_cost.py runs/lc_loop --perturb-cm 5 --perturb-deg 2

Takes every (keyframe, candidate) pair a loop-closure run verified (`loop_candidate` records of its `log.jsonl`;
the run's config gives the scene and settings), starts GICP from the ground-truth relative pose perturbed by a
random drift (`--perturb-cm`, `--perturb-deg`, seeded), and verifies it (`inrslam.slam.loop_closure.verify`)
under each setting:
`before` (every stage on the tracker's cloud, converged at the tracker's `slam.gicp.eps_*`: the verification before
`slam.loop.coarse_downsample` / `slam.loop.epsilon`) and `now` (the run's own). Prints, per setting, the pairs
accepted (GICP's checks and the drift bound, here for 1 m travelled: 10 cm), how many of those are true (< 1 cm
from the ground truth) and false (their errors), the error of the true ones, and the milliseconds per candidate
(preparing both clouds and the GICP stages), and the ratio of the two times (both measured in this one process).
The significance and colour checks that follow in a run are not applied.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np


def perturbation(rng: np.random.Generator, cm: float, deg: float) -> np.ndarray:
    """A random rigid motion (4, 4): translation of norm ~`cm` centimetres, rotation of ~`deg` degrees."""
    from scipy.spatial.transform import Rotation

    P = np.eye(4)
    P[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.radians(deg)).as_matrix()
    P[:3, 3] = rng.normal(size=3) / np.sqrt(3) * cm / 100
    return P


def pairs_of(run: Path) -> list[tuple[int, int]]:
    """(keyframe, candidate) of every verified candidate in a run's log."""
    recs = (json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip())
    return sorted({(r["frame"], r["candidate"]) for r in recs if r.get("type") == "loop_candidate"})


def main() -> None:
    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.eval.trajectory import rotation_angle_deg
    from inrslam.slam.loop_closure import stage_clouds, verify
    from inrslam.slam.registration import depth_points

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--perturb-cm", type=float, default=3.0)
    ap.add_argument("--perturb-deg", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    rows: dict[str, list[tuple[bool, float, float, float]]] = {"before": [], "now": []}
    for run in args.runs:
        cfg = load_config(run / "config.yaml", preset=None, check_variants=False)
        ds = open_dataset(cfg.data)
        g, lc = cfg.slam.gicp, cfg.slam.loop
        settings = {"before": (dataclasses.replace(lc, coarse_downsample=0.0, epsilon=g.eps_trans), g), "now": (lc, g)}
        for i, c in pairs_of(run):
            fi, fc = ds[i], ds[c]
            G = np.linalg.solve(fc.c2w, fi.c2w)  # candidate <- keyframe, ground truth
            start = fc.c2w @ G @ perturbation(rng, args.perturb_cm, args.perturb_deg)
            pts_i, pts_c = depth_points(fi.depth, fi.intrinsics, g), depth_points(fc.depth, fi.intrinsics, g)
            for name, (lcs, gs) in settings.items():
                t0 = time.perf_counter()
                v = verify(stage_clouds(pts_c, gs, lcs), stage_clouds(pts_i, gs, lcs), fc.c2w, start, 1.0, c, gs, lcs)
                dt = time.perf_counter() - t0
                D = np.linalg.solve(G, v.T_cand_cur)
                ang = float(rotation_angle_deg(D[:3, :3]))
                rows[name].append((v.ok, float(np.linalg.norm(D[:3, 3]) * 100), ang, dt))
    print(f"{len(rows['now'])} candidate pairs from {len(args.runs)} run(s), start {args.perturb_cm} cm / "
          f"{args.perturb_deg} deg off the ground truth")
    print("| setting | accepted | true (< 1 cm) | false | true: median / p90 error [cm] | [deg] | ms per candidate |")
    print("|:--|--:|--:|--:|--:|--:|--:|")
    ms = {}
    for name, r in rows.items():
        a = np.array(r, dtype=np.float64)
        ok = a[:, 0] > 0
        true = ok & (a[:, 1] < 1.0)
        ms[name] = a[:, 3].mean() * 1e3
        err = (f"{np.median(a[true, 1]):.3f} / {np.percentile(a[true, 1], 90):.3f} | {np.median(a[true, 2]):.3f}"
               if true.any() else "- | -")
        false = ", ".join(f"{x:.1f}" for x in a[ok & ~true, 1])
        print(f"| {name} | {ok.sum()} | {true.sum()} | {(ok & ~true).sum()}{f' ({false} cm)' if false else ''} | "
              f"{err} | {ms[name]:.0f} |")
    print(f"verification speed-up now vs before: {ms['before'] / ms['now']:.2f}x")


if __name__ == "__main__":
    main()
