"""Does the depth camera carry an error pattern fixed in the image, and does removing it help tracking?

Model: observed depth = true depth x (1 + e(u, v)), e fixed in the sensor. For frame pairs (b - gap, b), frame a's
depth is moved into b by the poses and the relative difference (d_b - z) / d_b of pixels within 5 cm is averaged per
`--block` x `--block` pixel block; e is raised by that average and the pairs are warped again with the corrected
depth (`--iters` rounds). Pairs only see e's differences between pixels, so its smooth part is least determined:
`--highpass SIGMA` keeps e minus its Gaussian blur (SIGMA pixels). Poses: the dataset's reference poses, or
`--trajectory` (a run's `trajectory.txt`: a self-calibration that uses no ground truth). Each pair is warped both
ways unless `--one-way`. Never asserted in tests; results in docs/accurate.md.

    K=../shared/data/7scenes_redkitchen
    python benchmarks/depth_pattern.py --data $K --dataset 7scenes --save /tmp/e_ref.npy --highpass 32 \
        --write /tmp/k_ref
    python benchmarks/depth_pattern.py --data $K --dataset 7scenes --trajectory runs/s7/trajectory.txt \
        --compare /tmp/e_ref.npy --highpass 32 --write /tmp/k_self

`--write FOLDER` makes a copy of a 7-Scenes demo-layout folder (`data/frame-NNNNNN.depth.png`, millimetres) with
every depth image divided by 1 + e and everything else linked, to run `inrslam run --data FOLDER` on.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np


def pair_residual(da: np.ndarray, db: np.ndarray, rel: np.ndarray, K) -> np.ndarray:
    """(H, W) relative difference (d_b - z) / d_b where a's depth (H, W) m, moved by rel (4, 4) a-camera -> b-camera,
    lands nearest in b; NaN elsewhere or where |d_b - z| >= 5 cm."""
    from inrslam.geometry.pinhole import backproject_np, project_np

    H, W = db.shape
    p = backproject_np(da, K.fx, K.fy, K.cx, K.cy) @ rel[:3, :3].T + rel[:3, 3]
    u, v, z = project_np(p[p[:, 2] > 1e-6], K.fx, K.fy, K.cx, K.cy)
    ub, vb = np.round(u).astype(int), np.round(v).astype(int)
    inside = (ub >= 0) & (ub < W) & (vb >= 0) & (vb < H)
    zbuf = np.full((H, W), np.inf)
    np.minimum.at(zbuf, (vb[inside], ub[inside]), z[inside])
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(db > 0, db - zbuf, np.nan)
        r = np.where(np.abs(r) < 0.05, r / db, np.nan)
    return r


def block_mean(r: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Sum and count of the finite values of r (H, W) per block x block tile: two (H // block, W // block)."""
    H, W = r.shape
    t = r[: H // block * block, : W // block * block].reshape(H // block, block, W // block, block)
    ok = np.isfinite(t)
    return np.where(ok, t, 0.0).sum((1, 3)), ok.sum((1, 3))


def estimate(depths, poses, K, gaps, step: int, block: int, iters: int, both_ways: bool = True
             ) -> tuple[np.ndarray, float]:
    """Pattern e (H, W) from depths (N, H, W) m and c2w poses (N, 4, 4); also the correlation of the first round's
    block means between the two interleaved halves of the pairs (near 1: a pattern fixed in the sensor). both_ways
    warps each pair both ways: a pose error then moves the two residuals in opposite directions and cancels to first
    order, where one way it biases e as the camera's motion does."""
    from scipy.ndimage import zoom

    H, W = depths[0].shape
    e = np.zeros((H, W))
    halves = 0.0
    for it in range(iters):
        s = np.zeros((2, H // block, W // block))
        c = np.zeros_like(s)
        for gap in gaps:
            for k, b in enumerate(range(gap, len(depths), step)):
                for a, t in ((b - gap, b), (b, b - gap))[: 2 if both_ways else 1]:
                    rel = np.linalg.inv(poses[t]) @ poses[a]
                    sb, cb = block_mean(pair_residual(depths[a] / (1 + e), depths[t] / (1 + e), rel, K), block)
                    s[k % 2] += sb
                    c[k % 2] += cb
        m = s.sum(0) / np.maximum(c.sum(0), 1)
        ok = c.sum(0) > 50 * block
        if it == 0:
            h = s / np.maximum(c, 1)
            both = ok & (c.min(0) > 25 * block)
            halves = float(np.corrcoef(h[0][both], h[1][both])[0, 1])
        print(f"round {it}: mean |block residual| {np.abs(m[ok]).mean():.5f} ({ok.sum()} blocks)", flush=True)
        e = e + zoom(np.where(ok, m, 0.0), block, order=1)[:H, :W]
    return e, halves


def write_corrected(src: Path, dst: Path, e: np.ndarray) -> int:
    """Copy of the demo-layout folder src with depth PNGs (mm) divided by 1 + e; returns the images written."""
    from PIL import Image

    n = 0
    (dst / "data").mkdir(parents=True, exist_ok=True)
    for f in sorted((src / "data").iterdir()):
        out = dst / "data" / f.name
        if out.exists() or out.is_symlink():
            out.unlink()
        if f.name.endswith(".depth.png"):
            d = np.asarray(Image.open(f)).astype(np.float64)
            bad = (d == 0) | (d == 65535)
            Image.fromarray(np.where(bad, d, np.round(d / (1 + e))).astype(np.uint16)).save(out)
            n += 1
        else:
            os.symlink(f.resolve(), out)
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--dataset", default="auto")
    ap.add_argument("--trajectory", default=None, help="TUM-format c2w trajectory (default: the reference poses)")
    ap.add_argument("--gaps", type=int, nargs="+", default=[3, 10, 30])
    ap.add_argument("--step", type=int, default=3, help="every step-th frame b")
    ap.add_argument("--block", type=int, default=4, help="pixels per block side")
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--one-way", action="store_true", help="warp each pair earlier -> later only")
    ap.add_argument("--highpass", type=float, default=0.0, help="keep e minus its blur of this sigma (px); 0 = off")
    ap.add_argument("--save", default=None, help="write e (H, W) as .npy (before --highpass)")
    ap.add_argument("--compare", default=None, help="a pattern .npy to correlate with, by spatial band")
    ap.add_argument("--write", default=None, help="folder for a depth-corrected copy (7-Scenes demo layout)")
    args = ap.parse_args()
    from scipy.ndimage import gaussian_filter

    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.io.trajectory import read_tum

    cfg = load_config(overrides=[f"data.path={args.data}", f"data.dataset={args.dataset}"])
    ds = open_dataset(cfg.data)
    frames = [ds[i] for i in range(len(ds))]
    depths = np.stack([f.depth.astype(np.float64) for f in frames])
    poses = read_tum(args.trajectory)[1] if args.trajectory else np.stack([f.c2w for f in frames])
    if len(poses) != len(depths):
        raise SystemExit(f"{args.trajectory}: {len(poses)} poses for {len(depths)} frames")
    e, halves = estimate(depths, poses, ds.intrinsics, args.gaps, args.step, args.block, args.iters,
                         not args.one_way)
    print(f"pattern: std {e.std():.5f}, range {e.min():.4f} .. {e.max():.4f}; first-round block means of the two"
          f" halves of the pairs correlate {halves:.3f}")
    if args.compare:
        ref = np.load(args.compare)
        for sigma in (8, 32):
            lo, lo_ref = gaussian_filter(e, sigma), gaussian_filter(ref, sigma)
            print(f"  against {args.compare}, finer than sigma {sigma} px: corr"
                  f" {np.corrcoef((e - lo).ravel(), (ref - lo_ref).ravel())[0, 1]:.3f}; coarser:"
                  f" {np.corrcoef(lo.ravel(), lo_ref.ravel())[0, 1]:.3f}")
    if args.save:
        np.save(args.save, e)
    if args.highpass > 0:
        e = e - gaussian_filter(e, args.highpass)
    if args.write:
        n = write_corrected(Path(args.data), Path(args.write), e)
        print(f"{args.write}: {n} depth images corrected")


if __name__ == "__main__":
    main()
