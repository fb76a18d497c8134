"""Two dense checks of a sequence's cameras against its poses, independent of the SLAM code's own alignment (plain
torch: bilinear `grid_sample`, Huber costs, L-BFGS). Pairs (a, a + gap) every 12th frame. Never asserted in tests.

1. `--calibrate`: the colour camera's fx, fy, cx, cy (and with `--extrinsics` its rotation and offset against the
   depth camera) that best explain the colour: frame a's depth pixels (every `--stride`-th) are moved into b by the
   poses and both grey images are sampled where the colour camera sees the point; the Huber grey difference is
   minimised over the camera (images blurred by each `--sigma` in turn, px). Prints the fit and the mean |grey
   difference| at the nominal (depth) camera and at the fit.
2. `--align`: each pair's relative pose re-estimated from the poses' one (6 unknowns per pair) on the same warp,
   with the colour camera `--color` (fx fy cx cy, default the depth camera's) and weights `--color-weight` /
   `--depth-weight` (the depth term: b's depth at the warped point against its warped depth, Huber 1 cm). Prints
   the rotation and translation scales of the estimates against the poses, overall and per camera axis (x tilt, y
   pan, z roll; 1 = unbiased), like `gt_rotation_scale.py --photo` does for the SLAM code's alignment.

Poses: the dataset's ground truth, or `--trajectory RUN/trajectory.txt` (no ground truth used).

    K=../shared/data/7scenes_redkitchen
    python benchmarks/dense_alignment.py --data $K --dataset 7scenes --calibrate --gaps 5 10
    python benchmarks/dense_alignment.py --data $K --dataset 7scenes --align --color 525 525 319.5 239.5
    python benchmarks/dense_alignment.py --data $K --dataset 7scenes --align --color-weight 0 --depth-weight 1
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
import torch.nn.functional as F


def blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """(H, W) image -> the same blurred by a separable Gaussian of std `sigma` px (zero padding)."""
    r = max(1, int(3 * sigma))
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    k = torch.exp(-x * x / (2 * sigma * sigma))
    k = k / k.sum()
    out = F.conv2d(img[None, None], k.view(1, 1, 1, -1), padding=(0, r))
    return F.conv2d(out, k.view(1, 1, -1, 1), padding=(r, 0))[0, 0]


def sample(img: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of an (H, W) image at pixel coordinates u, v (N,) -> (N,), differentiable in u, v."""
    h, w = img.shape
    grid = torch.stack([u / (w - 1) * 2 - 1, v / (h - 1) * 2 - 1], -1).to(img.dtype)[None, None]
    return F.grid_sample(img[None, None], grid, align_corners=True)[0, 0, 0]


def huber_mean(r: torch.Tensor, delta: float) -> torch.Tensor:
    """Mean Huber cost of residuals r (N,) in float64; 0 without residuals (a line-search step that moved every
    point out of view must not make the cost NaN)."""
    a = r.abs().double()
    cost = torch.where(a < delta, 0.5 * a * a, delta * (a - 0.5 * delta))
    return cost.sum() / max(1, cost.numel())


def project(P: torch.Tensor, cam) -> tuple[torch.Tensor, torch.Tensor]:
    fx, fy, cx, cy = cam
    return fx * P[:, 0] / P[:, 2] + cx, fy * P[:, 1] / P[:, 2] + cy


def inside(u, v, w: int, h: int) -> torch.Tensor:
    return (u > 2) & (u < w - 3) & (v > 2) & (v < h - 3)


def lbfgs(params: torch.Tensor, loss_fn, rounds: int = 3) -> float:
    opt = torch.optim.LBFGS([params], lr=1, max_iter=50, line_search_fn="strong_wolfe", tolerance_grad=1e-12,
                            tolerance_change=1e-15)

    def closure():
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    for _ in range(rounds):
        loss = opt.step(closure)
    return float(loss.detach())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--dataset", default="auto")
    ap.add_argument("--trajectory", help="TUM trajectory of the same frames (default: the dataset's ground truth)")
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--calibrate", action="store_true", help="fit the colour camera")
    mode.add_argument("--align", action="store_true", help="re-estimate each pair's relative pose")
    ap.add_argument("--gaps", type=int, nargs="+", default=[5])
    ap.add_argument("--stride", type=int, default=2, help="every stride-th depth pixel in u and v")
    ap.add_argument("--sigma", type=float, nargs="+", default=[2.0, 1.0], help="blur per round, px")
    ap.add_argument("--extrinsics", action="store_true", help="--calibrate: also the colour camera's rotation, offset")
    ap.add_argument("--color", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"), help="--align: colour camera")
    ap.add_argument("--color-weight", type=float, default=1.0)
    ap.add_argument("--depth-weight", type=float, default=0.0)
    args = ap.parse_args()

    from scipy.spatial.transform import Rotation

    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.geometry.se3 import se3_exp, so3_exp
    from inrslam.io.trajectory import read_tum

    torch.manual_seed(0)
    ds = open_dataset(load_config(preset="paper", overrides=[f"data.path={args.data}",
                                                             f"data.dataset={args.dataset}"]).data)
    poses = read_tum(args.trajectory)[1] if args.trajectory else ds.poses
    K = ds.intrinsics
    h, w = K.height, K.width
    pairs = [(a, a + g) for a in range(3, len(ds), 12) for g in args.gaps if a + g < len(ds)]
    frames = {}
    for i in sorted({i for p in pairs for i in p}):
        f = ds[i]
        frames[i] = (torch.tensor(f.rgb.mean(-1), dtype=torch.float32), torch.tensor(f.depth, dtype=torch.float32))
    items = []  # (a, b, points of a in its depth camera (N, 3) float64, poses' a -> b transform (4, 4))
    for a, b in pairs:
        d = frames[a][1][:: args.stride, :: args.stride]
        v, u = torch.nonzero((d > 0) & torch.isfinite(d), as_tuple=True)
        z = d[v, u].double()
        u, v = u.double() * args.stride, v.double() * args.stride
        X = torch.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], -1)
        items.append((a, b, X, torch.tensor(np.linalg.inv(poses[b]) @ poses[a], dtype=torch.float64)))
    print(f"{args.data}: {len(pairs)} pairs (gaps {args.gaps}), {sum(len(it[2]) for it in items)} points, poses "
          f"from {args.trajectory or 'the ground truth'}")
    nominal = (K.fx, K.fy, K.cx, K.cy)

    if args.calibrate:
        p = torch.zeros(10, dtype=torch.float64, requires_grad=True)

        def camera(q):  # unknowns of similar magnitude: focal (1 + q), principal point f q, 1 cm, 0.57 deg
            cam = (K.fx * (1 + q[0]), K.fy * (1 + q[1]), K.cx + K.fx * q[2], K.cy + K.fy * q[3])
            R = so3_exp(0.01 * q[4:7]) if args.extrinsics else torch.eye(3, dtype=q.dtype)
            t = 0.01 * q[7:10] if args.extrinsics else torch.zeros(3, dtype=q.dtype)
            return cam, R, t

        def grey_terms(grey, q, fn):
            cam, R, t = camera(q)
            out = []
            for a, b, X, T in items:
                Y = X @ T[:3, :3].T + T[:3, 3]
                ua, va = project(X @ R.T + t, cam)
                ub, vb = project(Y @ R.T + t, cam)
                m = inside(ua, va, w, h) & inside(ub, vb, w, h) & (Y[:, 2] > 0.1)
                out.append(fn(sample(grey[a], ua[m], va[m]) - sample(grey[b], ub[m], vb[m])))
            return out

        raw = {i: f[0] for i, f in frames.items()}

        def mean_abs() -> float:
            return float(np.mean(grey_terms(raw, p.detach(), lambda r: float(r.abs().mean()))))

        def cost(grey) -> torch.Tensor:
            return 1000 * torch.stack([huber_mean(r, 0.05) for r in grey_terms(grey, p, lambda r: r)]).mean()

        print(f"  mean |grey difference| at the depth camera {mean_abs():.4f}")
        for s in args.sigma:
            grey = {i: blur(f[0], s) for i, f in frames.items()}
            loss = lbfgs(p, lambda g=grey: cost(g))
            (fx, fy, cx, cy), R, t = camera(p.detach())
            extra = ""
            if args.extrinsics:
                rot = np.degrees(Rotation.from_matrix(R.numpy()).as_rotvec()).round(3)
                extra = f"  rotation {rot} deg, offset {(100 * t.numpy()).round(2)} cm"
            print(f"  blur {s} px: loss {loss:.4f}  fx {float(fx):.1f} fy {float(fy):.1f} cx {float(cx):.1f} "
                  f"cy {float(cy):.1f}{extra}")
        print(f"  mean |grey difference| at the fit {mean_abs():.4f}")
        return

    cam = tuple(args.color) if args.color else nominal
    P = torch.zeros(len(items), 6, dtype=torch.float64, requires_grad=True)  # per pair: 1 cm, 0.57 deg units

    def rel(k: int, T0: torch.Tensor) -> torch.Tensor:  # a left twist (rho, omega) of the poses' a -> b transform
        return se3_exp(0.01 * P[k]) @ T0

    def loss_fn(grey):
        tot = []
        for k, (a, b, X, T0) in enumerate(items):
            T = rel(k, T0)
            Y = X @ T[:3, :3].T + T[:3, 3]
            term = torch.zeros((), dtype=torch.float64)
            if args.color_weight > 0:
                ua, va = project(X, cam)
                ub, vb = project(Y, cam)
                m = inside(ua, va, w, h) & inside(ub, vb, w, h) & (Y[:, 2] > 0.1)
                r = sample(grey[a], ua[m], va[m]) - sample(grey[b], ub[m], vb[m])
                term = term + args.color_weight * huber_mean(r, 0.05)
            if args.depth_weight > 0:  # in grey units: 1 cm of depth weighs as 0.05 of grey
                ud, vd = project(Y, nominal)
                m = inside(ud, vd, w, h) & (Y[:, 2] > 0.1)
                db = sample(frames[b][1], ud[m], vd[m]).double()
                rz = db - Y[m, 2]
                ok = (db > 0) & (rz.abs() < 0.05)
                term = term + args.depth_weight * huber_mean(rz[ok], 0.01) * (0.05 / 0.01) ** 2
            tot.append(term)
        return 1000 * torch.stack(tot).sum()

    for s in args.sigma:
        grey = {i: blur(f[0], s) for i, f in frames.items()}
        print(f"  blur {s} px: loss {lbfgs(P, lambda g=grey: loss_fn(g)):.4f}")
    est_w, ref_w, est_t, ref_t = [], [], [], []
    with torch.no_grad():
        for k, (_, _, _, T0) in enumerate(items):
            Me, Mr = np.linalg.inv(rel(k, T0).numpy()), np.linalg.inv(T0.numpy())  # camera motion a -> b, in a
            est_w.append(Rotation.from_matrix(Me[:3, :3]).as_rotvec())
            ref_w.append(Rotation.from_matrix(Mr[:3, :3]).as_rotvec())
            est_t.append(Me[:3, 3])
            ref_t.append(Mr[:3, 3])
    ew, rw, et, rt = map(np.array, (est_w, ref_w, est_t, ref_t))
    scale = lambda e, r: float((e * r).sum() / (r * r).sum())  # noqa: E731
    print(f"colour camera {cam}, weights colour {args.color_weight} / depth {args.depth_weight}: rotation scale "
          f"{scale(ew, rw):.3f}, translation scale {scale(et, rt):.3f}")
    print("| axis | rotation scale | translation scale |\n|:--|--:|--:|")
    for ax, name in enumerate(("x (tilt)", "y (pan)", "z (roll)")):
        print(f"| {name} | {scale(ew[:, ax], rw[:, ax]):.3f} | {scale(et[:, ax], rt[:, ax]):.3f} |")


if __name__ == "__main__":
    main()
