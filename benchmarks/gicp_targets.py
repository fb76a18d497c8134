"""The GICP stage alone (no map, no mapping): odometry with each registration target, ATE / drift per scene.
The numbers of docs/accurate.md's target table; never asserted in tests.

    python benchmarks/gicp_targets.py --data builtin:room --target keyframe --kf-dist 0.15
    python benchmarks/gicp_targets.py --data ../shared/data/7scenes_redkitchen --dataset 7scenes \\
        --target local_map --keyframes 10 --kf-dist 0.1 --max-corr 0.05
    python benchmarks/gicp_targets.py --data builtin:handheld --depth-filter 2 --downsample 0.03 --neighbors 20

Same registration code and checks as `slam.init=gicp` (`inrslam.slam.registration`); a failed check keeps the
constant-velocity prediction. Keyframes are renewed on `--kf-dist` metres / 10 degrees of motion, a fitness below
0.85 or a failed check, as in the SLAM loop.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--dataset", default="auto")
    ap.add_argument("--max-frames", type=int, default=0)
    ap.add_argument("--target", choices=["previous", "keyframe", "local_map"], default="local_map")
    ap.add_argument("--keyframes", type=int, default=10, help="local_map: keyframes merged")
    ap.add_argument("--kf-dist", type=float, default=0.1)
    ap.add_argument("--max-corr", type=float, default=0.05)
    ap.add_argument("--downsample", type=float, default=0.02, help="voxel size, metres")
    ap.add_argument("--neighbors", type=int, default=10, help="neighbours per covariance")
    ap.add_argument("--depth-filter", type=int, default=0, help="bilateral filter radius, px (noisy depth only)")
    args = ap.parse_args()

    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.eval.trajectory import ate, drift_per_100
    from inrslam.slam.config import GicpConfig
    from inrslam.slam.registration import PreparedCloud, depth_points, moved_beyond, register

    cfg = load_config(preset="paper", overrides=[f"data.path={args.data}", f"data.dataset={args.dataset}",
                                                 f"data.max_frames={args.max_frames}"])
    ds = open_dataset(cfg.data)
    g = GicpConfig(max_corr=args.max_corr, kf_dist=args.kf_dist, downsample=args.downsample,
                   neighbors=args.neighbors, depth_filter=args.depth_filter)
    pts = [None] * len(ds)

    def points(i: int) -> np.ndarray:
        if pts[i] is None:
            f = ds[i]
            pts[i] = depth_points(f.depth, f.intrinsics, g)
        return pts[i]

    def target_of(kfs: list[int], est: list[np.ndarray]) -> tuple[PreparedCloud, np.ndarray]:
        if args.target == "local_map":
            ids = kfs[-args.keyframes:]
            world = np.concatenate([points(k) @ est[k][:3, :3].T + est[k][:3, 3] for k in ids])
            return PreparedCloud(world, g), np.eye(4)
        return PreparedCloud(points(kfs[-1]), g), est[kfs[-1]]

    est = [ds[0].c2w]
    kfs, fails, t0 = [0], 0, time.perf_counter()
    target, base = target_of(kfs, est)
    for i in range(1, len(ds)):
        cur = PreparedCloud(points(i), g)
        pred = est[-1] @ (np.linalg.inv(est[-2]) @ est[-1] if len(est) >= 2 else np.eye(4))
        reg = register(target, cur, np.linalg.inv(base) @ pred, g)
        c2w = base @ reg.T_target_source
        est.append(c2w if reg.ok else pred)
        fails += not reg.ok
        from_kf = np.linalg.inv(est[kfs[-1]]) @ c2w
        if (args.target == "previous" or not reg.ok or reg.fitness < g.kf_fitness
                or moved_beyond(from_kf, g.kf_dist, g.kf_angle)):
            kfs.append(i)
            target, base = target_of(kfs, est)
        if args.target != "local_map":
            pts[i - 1] = None  # keep memory flat
    est_a = np.stack(est)
    gt = np.stack([ds[i].c2w for i in range(len(ds))])
    a, d = ate(est_a, gt), drift_per_100(est_a, gt)
    print(f"{args.data} target={args.target} downsample={g.downsample} neighbors={g.neighbors} "
          f"depth_filter={g.depth_filter} frames={len(ds)} keyframes={len(kfs)} failed_checks={fails}: "
          f"ATE {100 * a['rmse']:.3f} cm, drift {100 * d['drift_m_per_100']:.3f} cm/100 frames, "
          f"{1e3 * (time.perf_counter() - t0) / max(len(ds) - 1, 1):.0f} ms/frame")


if __name__ == "__main__":
    main()
