"""Do the reference's rotations agree with the depth, and how biased is a single registration? Two checks on frame
pairs `gap` apart (every 13th frame; `--min-turn` skips pairs that turn less). Never asserted in tests.

1. Depth warp: frame a's depth (every 4th pixel) is moved into frame b by the reference's relative pose with its
   rotation scaled by s (translation kept) and compared with b's depth (median |difference| of pixels within 10 cm).
   The s with the smallest median is the rotation scale the depth itself supports.
2. `--gicp`: GICP of b's depth onto a's (accurate's and coarser voxels), started from the reference's relative pose
   and from identity; the fitted rotation scale of its rotations against the reference's (1 = unbiased).

    python benchmarks/gt_rotation_scale.py --data ../shared/data/7scenes_redkitchen --dataset 7scenes --gap 1 --gicp
    python benchmarks/gt_rotation_scale.py --data ../shared/data/7scenes_redkitchen --dataset 7scenes --gap 5 --gicp
"""

from __future__ import annotations

import argparse

import numpy as np

SCALES = (0.7, 0.8, 0.85, 0.9, 0.95, 1.0, 1.05)


def warp_error(depth_a: np.ndarray, depth_b: np.ndarray, rel: np.ndarray, s: float, K) -> float:
    """Median |depth_b - warped depth_a| (m) with rel (4, 4) a-camera -> b-camera, its rotation scaled by s."""
    from scipy.spatial.transform import Rotation

    from inrslam.geometry.pinhole import backproject_np, project_np

    R = Rotation.from_rotvec(s * Rotation.from_matrix(rel[:3, :3]).as_rotvec()).as_matrix()
    q = backproject_np(depth_a, K.fx, K.fy, K.cx, K.cy, stride=4) @ R.T + rel[:3, 3]
    u, v, z = project_np(q, K.fx, K.fy, K.cx, K.cy)
    ui, vi = np.round(u).astype(int), np.round(v).astype(int)
    ok = (ui >= 0) & (ui < K.width) & (vi >= 0) & (vi < K.height) & (z > 0)
    d = depth_b[vi[ok], ui[ok]]
    r = np.abs(d - z[ok])[d > 0]
    r = r[r < 0.1]
    return float(np.median(r)) if r.size else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--dataset", default="auto")
    ap.add_argument("--gap", type=int, default=5)
    ap.add_argument("--min-turn", type=float, default=0.0, help="skip pairs turning less, degrees")
    ap.add_argument("--gicp", action="store_true", help="also register each pair with GICP")
    args = ap.parse_args()
    from scipy.spatial.transform import Rotation

    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.slam.config import GicpConfig
    from inrslam.slam.registration import PreparedCloud, depth_points, register

    cfg = load_config(preset="paper", overrides=[f"data.path={args.data}", f"data.dataset={args.dataset}"])
    ds = open_dataset(cfg.data)
    K = ds.intrinsics
    gicps = {f"{v * 100:.0f} cm voxels": GicpConfig(downsample=v, max_corr=max(0.1, 3 * v)) for v in (0.02, 0.04, 0.06)}
    errs, w_ref, w_reg = [], [], {(k, init): [] for k in gicps for init in ("reference", "identity")}
    for a in range(0, len(ds) - args.gap, 13):
        fa, fb = ds[a], ds[a + args.gap]
        rel = np.linalg.inv(fb.c2w) @ fa.c2w  # a-camera -> b-camera
        if np.degrees(np.linalg.norm(Rotation.from_matrix(rel[:3, :3]).as_rotvec())) < args.min_turn:
            continue
        errs.append([warp_error(fa.depth, fb.depth, rel, s, K) for s in SCALES])
        w_ref.append(Rotation.from_matrix(np.linalg.inv(rel)[:3, :3]).as_rotvec())
        for name, g in gicps.items() if args.gicp else ():
            ca = PreparedCloud(depth_points(fa.depth, fa.intrinsics, g), g)
            cb = PreparedCloud(depth_points(fb.depth, fb.intrinsics, g), g)
            for init, T0 in (("reference", np.linalg.inv(rel)), ("identity", np.eye(4))):
                T = register(ca, cb, T0, g).T_target_source  # b -> a
                w_reg[name, init].append(Rotation.from_matrix(T[:3, :3]).as_rotvec())
    e = 1e3 * np.nanmean(np.array(errs), axis=0)
    turn = np.degrees(np.linalg.norm(np.array(w_ref), axis=1)).mean()
    print(f"{args.data}: {len(errs)} pairs {args.gap} frames apart (mean turn {turn:.2f} degrees); mean over pairs of the median depth difference [mm]"
          " after warping with the reference's rotation scaled by s:")
    print("| s | " + " | ".join(f"{s:g}" for s in SCALES) + " |\n|:--|" + "--:|" * len(SCALES))
    print("| mm | " + " | ".join(f"{x:.2f}" for x in e) + f" |\nbest s = {SCALES[int(np.argmin(e))]:g}")
    if args.gicp:
        wr = np.array(w_ref)
        print("GICP rotation scale against the reference (least squares over the pairs):")
        for (name, init), w in w_reg.items():
            w = np.array(w)
            print(f"  {name}, from the {init}: {(w * wr).sum() / (wr * wr).sum():.3f}")


if __name__ == "__main__":
    main()
