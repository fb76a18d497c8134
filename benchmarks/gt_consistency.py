"""How well a dataset's ground-truth poses agree with its own depth: each pair of consecutive frames is registered
with GICP (fine: 1 cm voxels, 5 cm correspondences, every pixel) from the ground truth's relative pose, and the
registration's relative motion is compared with the ground truth's. Where a well-conditioned registration (every
check passed) and the ground truth disagree by centimetres, one of them is wrong; on real data whose "ground truth"
is itself a tracker's output (7-Scenes: KinectFusion) it is usually the ground truth. Never asserted in tests.

    python benchmarks/gt_consistency.py --data ../shared/data/7scenes_redkitchen --dataset 7scenes
    python benchmarks/gt_consistency.py --data builtin:room     # synthetic: exact poses, sub-millimetre

Prints the median and 90th percentile of the disagreement, the frames where it is largest, the frames whose colour or
depth repeats the previous frame's (`slam.photo.skip_stale`), and the ATE that a
trajectory equal to the ground truth but for the largest disagreement (a step at that frame) would score, ATE and
unaligned drift: what such a ground-truth error alone costs an estimate that does not follow it. With `--runs RUN...`
each run's trajectory is scored against the ground truth and against that corrected ground truth.

    python benchmarks/gt_consistency.py --data ../shared/data/7scenes_redkitchen --dataset 7scenes --runs runs/s7
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--dataset", default="auto")
    ap.add_argument("--max-frames", type=int, default=0)
    ap.add_argument("--top", type=int, default=8, help="frames listed")
    ap.add_argument("--runs", nargs="*", default=[], help="run folders (trajectory.txt) to score against both")
    args = ap.parse_args()

    from inrslam.config import load_config
    from inrslam.data.frame import repeated_streams
    from inrslam.datasets import open_dataset
    from inrslam.eval.trajectory import ate, drift_per_100, rotation_angle_deg
    from inrslam.io.trajectory import read_tum
    from inrslam.slam.config import GicpConfig
    from inrslam.slam.registration import PreparedCloud, depth_points, register

    cfg = load_config(preset="paper", overrides=[f"data.path={args.data}", f"data.dataset={args.dataset}",
                                                 f"data.max_frames={args.max_frames}"])
    ds = open_dataset(cfg.data)
    g = GicpConfig(max_corr=0.05, downsample=0.01, pixel_stride=1)
    prev, prev_cloud = None, None
    repeated: dict[str, list[int]] = {"colour": [], "depth": [], "both": []}  # frames repeating frame i-1's image
    rows = []  # (frame, gt move mm, disagreement mm, disagreement deg, ok)
    gt = []
    for i in range(len(ds)):
        f = ds[i]
        gt.append(f.c2w)
        cloud = PreparedCloud(depth_points(f.depth, f.intrinsics, g), g)
        if prev is not None:
            same = repeated_streams(prev, f)
            if same:
                repeated[same].append(i)
            rel_gt = np.linalg.inv(prev.c2w) @ f.c2w  # frame i -> frame i-1
            reg = register(prev_cloud, cloud, rel_gt, g)
            diff = np.linalg.inv(rel_gt) @ reg.T_target_source
            rows.append((i, 1e3 * np.linalg.norm(rel_gt[:3, 3]), 1e3 * np.linalg.norm(diff[:3, 3]),
                         float(rotation_angle_deg(diff[:3, :3])), reg.ok))
        prev, prev_cloud = f, cloud
    gt = np.stack(gt)
    ok = [r for r in rows if r[4]]
    d = np.array([r[2] for r in ok])
    print(f"{args.data}: {len(rows)} pairs, {len(ok)} well-conditioned; ground truth vs registration: median "
          f"{np.median(d):.1f} mm, 90th percentile {np.percentile(d, 90):.1f} mm")
    print("largest disagreements (frame: gt move mm, disagreement mm / deg):")
    for i, move, dm, dd, _ in sorted(ok, key=lambda r: -r[2])[:args.top]:
        print(f"  {i:5d}: {move:6.1f}  {dm:6.1f} / {dd:.2f}")
    print("frames whose colour / depth / both are bit-identical to the previous frame's (a dropped sensor frame "
          "repeated: colour and depth of different times):")
    for k, v in repeated.items():
        print(f"  {k}: {len(v)}" + (f" (first {v[:12]})" if v else ""))
    worst = max(ok, key=lambda r: r[2])
    # a trajectory equal to the ground truth except that it does not make the worst frame's disputed step
    reg_step = None
    f0, f1 = ds[worst[0] - 1], ds[worst[0]]
    rel_gt = np.linalg.inv(f0.c2w) @ f1.c2w
    reg = register(PreparedCloud(depth_points(f0.depth, f0.intrinsics, g), g),
                   PreparedCloud(depth_points(f1.depth, f1.intrinsics, g), g), rel_gt, g)
    reg_step = f0.c2w @ reg.T_target_source  # frame `worst` placed by the registration
    fix = reg_step @ np.linalg.inv(f1.c2w)  # world correction applied from that frame on
    est = gt.copy()
    est[worst[0]:] = fix @ gt[worst[0]:]
    print(f"the ground truth with frame {worst[0]}'s step replaced by the registration's: ATE "
          f"{100 * ate(est, gt)['rmse']:.2f} cm, drift {100 * drift_per_100(est, gt)['drift_m_per_100']:.2f} cm "
          "per 100 frames")
    for run in args.runs:
        _, traj = read_tum(f"{run}/trajectory.txt")
        if len(traj) != len(gt):
            raise SystemExit(f"{run}/trajectory.txt: {len(traj)} poses, expected {len(gt)} (one per frame)")
        scores = [f"ATE {100 * ate(traj, ref)['rmse']:.3f} cm, drift "
                  f"{100 * drift_per_100(traj, ref)['drift_m_per_100']:.3f} cm per 100 frames" for ref in (gt, est)]
        print(f"{run}: against the ground truth {scores[0]}; against it without frame {worst[0]}'s step {scores[1]}")


if __name__ == "__main__":
    main()
