"""KinectFusion-style depth odometry (Open3D's frame-to-model tracker), ATE / drift against the dataset's poses.
An exploratory check of docs/accurate.md ("The reference's own method"): 7-Scenes' reference poses come from
KinectFusion, so does tracking by the same method (a TSDF of every frame so far, point-to-plane ICP of each depth
frame onto the model's raycast from the previous pose) land nearer the reference than our trackers? Never asserted in
tests; needs Open3D, which inrslam does not depend on (`pip install open3d`, about 400 MB).

    python benchmarks/kinfu_open3d.py --data ../shared/data/7scenes_redkitchen --dataset 7scenes
    python benchmarks/kinfu_open3d.py --data ../shared/data/7scenes_redkitchen --dataset 7scenes --voxel 0.006
    python benchmarks/kinfu_open3d.py --data builtin:handheld --out /tmp/kinfu_hh.txt

Frames come through inrslam's loader (its depth in metres, invalid = 0; its intrinsics); the first pose is the
reference's. `--out` writes the estimate as a TUM file like a run's `trajectory.txt` (`inrslam eval --traj OUT --gt
RUN/trajectory_gt.txt`).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--dataset", default="auto")
    ap.add_argument("--max-frames", type=int, default=0)
    ap.add_argument("--voxel", type=float, default=0.01, help="TSDF voxel size, metres")
    ap.add_argument("--trunc", type=float, default=8.0, help="truncation, in voxels")
    ap.add_argument("--depth-max", type=float, default=4.0, help="metres")
    ap.add_argument("--depth-diff", type=float, default=0.07, help="ICP correspondence distance, metres")
    ap.add_argument("--blocks", type=int, default=40000, help="voxel blocks (16^3 voxels each) to allocate")
    ap.add_argument("--out", help="write the estimated trajectory here")
    args = ap.parse_args()
    try:
        import open3d as o3d
        import open3d.core as o3c
    except ImportError as e:
        sys.exit(f"kinfu_open3d.py needs Open3D (pip install open3d): {e}")

    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.eval.trajectory import ate, drift_per_100

    cfg = load_config(preset="paper", overrides=[f"data.path={args.data}", f"data.dataset={args.dataset}",
                                                 f"data.max_frames={args.max_frames}"])
    ds = open_dataset(cfg.data)
    first = ds[0]
    k = first.intrinsics
    h, w = first.depth.shape
    K = o3c.Tensor(np.array([[k.fx, 0, k.cx], [0, k.fy, k.cy], [0, 0, 1]]), o3c.Dtype.Float64)
    dev = o3c.Device("CPU:0")
    pose = np.asarray(first.c2w, np.float64)
    model = o3d.t.pipelines.slam.Model(args.voxel, 16, args.blocks, o3c.Tensor(pose), dev)
    frame = o3d.t.pipelines.slam.Frame(h, w, K, dev)
    raycast = o3d.t.pipelines.slam.Frame(h, w, K, dev)
    scale = 1000.0  # depth handed over as uint16 millimetres
    est, t0 = [], time.perf_counter()
    for i in range(len(ds)):
        f = ds[i]
        depth = f.depth
        mm = np.where(np.isfinite(depth) & (depth > 0), np.round(depth * scale), 0).clip(0, 65535).astype(np.uint16)
        frame.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(mm)))
        rgb = np.ascontiguousarray((np.clip(f.rgb, 0, 1) * 255).round().astype(np.uint8))  # integrated, not tracked on
        frame.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(rgb)))
        if i > 0:
            res = model.track_frame_to_model(frame, raycast, scale, args.depth_max, args.depth_diff)
            pose = pose @ res.transformation.numpy()
        model.update_frame_pose(i, o3c.Tensor(pose))
        model.integrate(frame, scale, args.depth_max, args.trunc)
        model.synthesize_model_frame(raycast, scale, 0.1, args.depth_max, args.trunc, False)
        est.append(pose.copy())
    seconds = time.perf_counter() - t0
    est_a = np.stack(est)
    gt = np.stack([np.asarray(ds[i].c2w, np.float64) for i in range(len(ds))])
    if args.out:
        from inrslam.io.trajectory import write_tum

        write_tum(args.out, np.array([ds[i].timestamp for i in range(len(ds))]), est_a, header="kinfu_open3d.py")
    a, d = ate(est_a, gt), drift_per_100(est_a, gt)
    print(f"# Open3D {o3d.__version__}, {args.data}, {len(ds)} frames, voxel {args.voxel} m, trunc {args.trunc} "
          f"voxels, depth diff {args.depth_diff} m")
    print(f"ATE {a['rmse'] * 100:.3f} cm, drift {d['drift_m_per_100'] * 100:.3f} cm / 100 frames, last frame "
          f"{d['final_m'] * 100:.2f} cm off, {seconds / len(ds) * 1e3:.0f} ms per frame")


if __name__ == "__main__":
    main()
