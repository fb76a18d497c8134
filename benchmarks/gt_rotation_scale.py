"""Do the reference's rotations agree with the depth, and how biased is a single registration? Two checks on frame
pairs `gap` apart (every 13th frame; `--min-turn` skips pairs that turn less). Never asserted in tests.

1. Depth warp: frame a's depth (every 4th pixel) is moved into frame b by the reference's relative pose with its
   rotation scaled by s (translation kept) and compared with b's depth (median |difference| of pixels within 10 cm).
   The s with the smallest median is the rotation scale the depth itself supports.
2. `--gicp`: GICP of b's depth onto a's (accurate's and coarser voxels), started from the reference's relative pose
   and from identity; the fitted rotation scale of its rotations against the reference's (1 = unbiased).
3. `--axes`: the depth warp of 1. and the same warp of a's grey image into b's (mean |difference|) with one rotation
   axis of the camera scaled at a time: x (tilt), y (pan), z (roll).
4. `--photo`: the photometric refinement (`accurate`'s `slam.photo`, `--photo-iters` per level) of each pair from the
   reference's relative pose; rotation scale overall and per axis, translation scale per axis.
`--set KEY=VALUE` passes config overrides, e.g. `data.color_intrinsics=[525,525,319.5,239.5]` (colour resampled
into the depth camera) or `slam.photo.levels=1`.

    python benchmarks/gt_rotation_scale.py --data ../shared/data/7scenes_redkitchen --dataset 7scenes --gap 1 --gicp
    python benchmarks/gt_rotation_scale.py --data ../shared/data/7scenes_redkitchen --dataset 7scenes --gap 5 --gicp
    python benchmarks/gt_rotation_scale.py --data ../shared/data/7scenes_redkitchen --dataset 7scenes --axes --photo
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


def scaled_axis(rel: np.ndarray, axis: int, s: float) -> np.ndarray:
    """rel (4, 4) with component `axis` of its rotation vector scaled by s (translation kept)."""
    from scipy.spatial.transform import Rotation

    w = Rotation.from_matrix(rel[:3, :3]).as_rotvec()
    w[axis] *= s
    out = rel.copy()
    out[:3, :3] = Rotation.from_rotvec(w).as_matrix()
    return out


def colour_warp_error(fa, fb, rel: np.ndarray, K) -> float:
    """Mean |grey_b - grey_a| (grey in [0, 1]) over a's valid depth pixels (every 4th) moved into b by rel (4, 4)."""
    from inrslam.slam.loop_closure import color_disagreement
    from inrslam.slam.photometric import grey

    return color_disagreement(fa.depth, grey(fa.rgb), grey(fb.rgb), rel, K)


def fitted_scale(est: np.ndarray, ref: np.ndarray) -> float:
    """Least-squares s of est ~ s ref over (N, ...) arrays."""
    return float((est * ref).sum() / (ref * ref).sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--dataset", default="auto")
    ap.add_argument("--gap", type=int, default=5)
    ap.add_argument("--min-turn", type=float, default=0.0, help="skip pairs turning less, degrees")
    ap.add_argument("--gicp", action="store_true", help="also register each pair with GICP")
    ap.add_argument("--axes", action="store_true", help="depth and colour warps with one rotation axis scaled")
    ap.add_argument("--photo", action="store_true", help="also align each pair photometrically")
    ap.add_argument("--photo-iters", type=int, default=50, help="Gauss-Newton iterations per pyramid level")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides")
    args = ap.parse_args()
    import torch
    from scipy.spatial.transform import Rotation

    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.slam.config import GicpConfig
    from inrslam.slam.photometric import align_photometric, build_pyramid
    from inrslam.slam.registration import PreparedCloud, depth_points, filtered_depth, register

    cfg = load_config(preset="accurate", overrides=[f"data.path={args.data}", f"data.dataset={args.dataset}",
                                                    f"slam.photo.iters={args.photo_iters}", *args.set])
    ds = open_dataset(cfg.data)
    K = ds.intrinsics
    gicps = {f"{v * 100:.0f} cm voxels": GicpConfig(downsample=v, max_corr=max(0.1, 3 * v)) for v in (0.02, 0.04, 0.06)}
    errs, w_ref, w_reg = [], [], {(k, init): [] for k in gicps for init in ("reference", "identity")}
    axis_depth, axis_colour, photo, t_ref = [], [], [], []
    pc = cfg.slam.photo

    def pyramid(f):
        i = f.intrinsics
        return build_pyramid(f.rgb, filtered_depth(f.depth, cfg.slam.gicp), (i.fx, i.fy, i.cx, i.cy), pc.levels)

    for a in range(0, len(ds) - args.gap, 13):
        fa, fb = ds[a], ds[a + args.gap]
        rel = np.linalg.inv(fb.c2w) @ fa.c2w  # a-camera -> b-camera
        if np.degrees(np.linalg.norm(Rotation.from_matrix(rel[:3, :3]).as_rotvec())) < args.min_turn:
            continue
        errs.append([warp_error(fa.depth, fb.depth, rel, s, K) for s in SCALES])
        w_ref.append(Rotation.from_matrix(np.linalg.inv(rel)[:3, :3]).as_rotvec())
        t_ref.append(rel)
        if args.axes:
            axis_depth.append([[warp_error(fa.depth, fb.depth, scaled_axis(rel, k, s), 1.0, K) for s in SCALES]
                               for k in range(3)])
            axis_colour.append([[colour_warp_error(fa, fb, scaled_axis(rel, k, s), K) for s in SCALES]
                                for k in range(3)])
        if args.photo:
            res = align_photometric(pyramid(fa), pyramid(fb), torch.as_tensor(rel), pc,
                                    torch.Generator().manual_seed(a))
            photo.append(res.T_ik.numpy())
        for name, g in gicps.items() if args.gicp else ():
            ca = PreparedCloud(depth_points(fa.depth, fa.intrinsics, g), g)
            cb = PreparedCloud(depth_points(fb.depth, fb.intrinsics, g), g)
            for init, T0 in (("reference", np.linalg.inv(rel)), ("identity", np.eye(4))):
                T = register(ca, cb, T0, g).T_target_source  # b -> a
                w_reg[name, init].append(Rotation.from_matrix(T[:3, :3]).as_rotvec())
    e = 1e3 * np.nanmean(np.array(errs), axis=0)
    turn = np.degrees(np.linalg.norm(np.array(w_ref), axis=1)).mean()
    print(f"{args.data}: {len(errs)} pairs {args.gap} frames apart (mean turn {turn:.2f} degrees); mean over pairs"
          " of the median depth difference [mm]"
          " after warping with the reference's rotation scaled by s:")
    print("| s | " + " | ".join(f"{s:g}" for s in SCALES) + " |\n|:--|" + "--:|" * len(SCALES))
    print("| mm | " + " | ".join(f"{x:.2f}" for x in e) + f" |\nbest s = {SCALES[int(np.argmin(e))]:g}")
    if args.gicp:
        wr = np.array(w_ref)
        print("GICP rotation scale against the reference (least squares over the pairs):")
        for (name, init), w in w_reg.items():
            w = np.array(w)
            print(f"  {name}, from the {init}: {(w * wr).sum() / (wr * wr).sum():.3f}")
    names = ("x (tilt)", "y (pan)", "z (roll)")
    if args.axes:
        for title, arr in (("depth warp, median |difference| [mm]", 1e3 * np.nanmean(axis_depth, axis=0)),
                           ("colour warp, mean |grey difference| x 1000", 1e3 * np.nanmean(axis_colour, axis=0))):
            print(f"{title}, one rotation axis scaled by s:")
            print("| axis | " + " | ".join(f"{s:g}" for s in SCALES) + " | best s |")
            print("|:--|" + "--:|" * (len(SCALES) + 1))
            for k in range(3):
                best = SCALES[int(np.argmin(arr[k]))]
                print(f"| {names[k]} | " + " | ".join(f"{x:.3f}" for x in arr[k]) + f" | {best:g} |")
    if args.photo:
        rel = np.array(t_ref)
        wr = np.array([Rotation.from_matrix(T[:3, :3]).as_rotvec() for T in rel])
        we = np.array([Rotation.from_matrix(T[:3, :3]).as_rotvec() for T in photo])
        te, tr = np.array(photo)[:, :3, 3], rel[:, :3, 3]
        print(f"photometric alignment from the reference ({args.photo_iters} iterations per level): rotation scale"
              f" {fitted_scale(we, wr):.3f}, translation scale {fitted_scale(te, tr):.3f}")
        print("| axis | rotation scale | translation scale |\n|:--|--:|--:|")
        for k in range(3):
            print(f"| {names[k]} | {fitted_scale(we[:, k], wr[:, k]):.3f} | {fitted_scale(te[:, k], tr[:, k]):.3f} |")


if __name__ == "__main__":
    main()
