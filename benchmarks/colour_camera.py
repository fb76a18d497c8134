"""Which colour focal length explains a sequence best: frame a's grey image is warped into frame a+gap through a's
depth (depth camera intrinsics, the sequence's) and projected with a colour camera of focal length f (principal
point as given, baseline neglected); printed is the mean absolute grey difference over pairs spread over the sequence,
per f. Poses: the dataset's ground truth, or a run's `trajectory.txt` (no ground truth used). Never asserted in tests.

    K=../shared/data/7scenes_redkitchen
    python benchmarks/colour_camera.py --data $K --dataset 7scenes --focal 585 525 535
    python benchmarks/colour_camera.py --data $K --dataset 7scenes --trajectory runs/x/trajectory.txt --focal 585 525

A lower difference at f than at the depth camera's focal length means the colour camera is not the depth camera:
`data.color_intrinsics=[f, f, cx, cy]` resamples colour into the depth camera (docs/accurate.md).
"""

from __future__ import annotations

import argparse

import numpy as np


def warp_error(ref, cur, T_cur_ref: np.ndarray, f: float, cx: float, cy: float) -> float:
    """Mean |grey_ref - grey_cur| over ref's valid-depth pixels seen by both colour cameras (bilinear)."""
    from scipy.ndimage import map_coordinates

    from inrslam.geometry.pinhole import backproject_np, project_np

    intr = ref.intrinsics
    X = backproject_np(ref.depth, intr.fx, intr.fy, intr.cx, intr.cy)  # (N, 3) in ref's depth camera
    Y = X @ T_cur_ref[:3, :3].T + T_cur_ref[:3, 3]
    h, w = ref.rgb.shape[:2]
    ua, va, _ = project_np(X, f, f, cx, cy)
    ub, vb, zb = project_np(Y, f, f, cx, cy)
    inside = lambda x, y: (x > 1) & (x < w - 2) & (y > 1) & (y < h - 2)  # noqa: E731
    m = inside(ua, va) & inside(ub, vb) & (zb > 0)
    ga, gb = ref.rgb.mean(-1), cur.rgb.mean(-1)
    a = map_coordinates(ga, [va[m], ua[m]], order=1)
    b = map_coordinates(gb, [vb[m], ub[m]], order=1)
    return float(np.mean(np.abs(a - b)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--dataset", default="auto")
    ap.add_argument("--trajectory", help="TUM trajectory of the same frames (default: the dataset's ground truth)")
    ap.add_argument("--focal", type=float, nargs="+", default=[585.0, 525.0])
    ap.add_argument("--principal", type=float, nargs=2, help="colour cx cy (default: the depth camera's)")
    ap.add_argument("--gap", type=int, default=10)
    ap.add_argument("--pairs", type=int, default=7)
    args = ap.parse_args()

    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.io.trajectory import read_tum

    ds = open_dataset(load_config(preset="paper", overrides=[f"data.path={args.data}",
                                                             f"data.dataset={args.dataset}"]).data)
    poses = read_tum(args.trajectory)[1] if args.trajectory else ds.poses
    starts = np.linspace(0, len(ds) - 1 - args.gap, args.pairs).round().astype(int)
    cx, cy = args.principal if args.principal else (ds.intrinsics.cx, ds.intrinsics.cy)
    frames = {i: ds[i] for i in sorted(set(starts) | set(starts + args.gap))}
    print(f"{args.data}: {args.pairs} pairs (a, a+{args.gap}), poses from "
          f"{args.trajectory or 'the ground truth'}; colour principal point ({cx}, {cy})")
    for f in args.focal:
        errs = [warp_error(frames[a], frames[a + args.gap], np.linalg.inv(poses[a + args.gap]) @ poses[a], f, cx, cy)
                for a in starts]
        print(f"  f = {f:6.1f} px: mean |grey difference| {np.mean(errs):.4f}")


if __name__ == "__main__":
    main()
