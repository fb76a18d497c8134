"""Tiny fixtures in each public dataset layout, written with known content (32 x 24 images, known poses)."""

from __future__ import annotations

import os

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

W, H = 32, 24
# Real data sits in ../shared/data beside the repository (override with INRSLAM_SHARED_DATA).
SHARED = Path(os.environ.get("INRSLAM_SHARED_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))


def write_png16(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(arr, dtype=np.uint16)).save(path)


def write_rgb(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(arr, dtype=np.uint8)).save(path, **({"quality": 98} if path.suffix == ".jpg" else {}))


def known_pose(k: int) -> np.ndarray:
    """A distinct rigid c2w per frame k (rotation about a tilted axis, translation (0.1 k, 0.2, -0.3))."""
    T = np.eye(4)
    axis = np.array([0.3, 0.9, 0.3]) / np.linalg.norm([0.3, 0.9, 0.3])
    T[:3, :3] = Rotation.from_rotvec(np.deg2rad(10.0 * (k + 1)) * axis).as_matrix()
    T[:3, 3] = [0.1 * k, 0.2, -0.3]
    return T


def depth_raw(k: int) -> np.ndarray:
    """(H, W) uint16: 1000 * (k + 1) everywhere, 0 at pixel (0, 0) (a hole), 40000 at (row 1, col 2) (> 32767)."""
    d = np.full((H, W), 1000 * (k + 1), dtype=np.uint16)
    d[0, 0] = 0
    d[1, 2] = 40000
    return d


def green(k: int) -> int:
    """Green channel of frame k's uniform colour."""
    return (40 + 30 * k) % 256


def colour(k: int, w: int = W, h: int = H) -> np.ndarray:
    """(h, w, 3) uint8 uniform colour distinct per frame (safe under JPEG)."""
    img = np.zeros((h, w, 3), dtype=np.uint8)
    img[...] = (200, green(k), 100)
    return img


def pose_rows(T: np.ndarray) -> str:
    return "\n".join(" ".join(f"{x:.12g}" for x in row) for row in T)


@dataclass
class Layout:
    root: Path
    n: int
    depth_scale: float
    poses: list = field(default_factory=list)  # expected OpenCV c2w (NaN where invalid)
    valid: list = field(default_factory=list)
    timestamps: list = field(default_factory=list)


def make_replica(base: Path, n: int = 3, scene: str = "room0", mesh: bool = True) -> Layout:
    root = base / scene
    lines = []
    for k in range(n):
        write_rgb(root / "results" / f"frame{k:06d}.jpg", colour(k))
        write_png16(root / "results" / f"depth{k:06d}.png", depth_raw(k))
        lines.append(" ".join(f"{x:.12g}" for x in known_pose(k).ravel()))
    (root / "traj.txt").write_text("\n".join(lines) + "\n")
    if mesh:
        (base / f"{scene}_mesh.ply").write_text("ply\n")
    return Layout(root, n, 6553.5, [known_pose(k) for k in range(n)], [True] * n, [k / 30 for k in range(n)])


def make_neuralrgbd(base: Path, n: int = 3, scene: str = "breakfast_room", nan_frame: int | None = 1) -> Layout:
    root = base / scene
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    blocks, poses, valid = [], [], []
    for k in range(n):
        write_rgb(root / "images" / f"img{k}.png", colour(k))
        write_png16(root / "depth_filtered" / f"depth{k}.png", depth_raw(k))
        write_png16(root / "depth" / f"depth{k}.png", depth_raw(k) + 1)  # the unused unfiltered depth
        T_cv = known_pose(k)
        if k == nan_frame:
            blocks.append("\n".join(["nan nan nan nan"] * 4))
            poses.append(np.full((4, 4), np.nan))
            valid.append(False)
        else:
            blocks.append(pose_rows(T_cv @ flip))  # written in OpenGL axes
            poses.append(T_cv)
            valid.append(True)
    (root / "poses.txt").write_text("\n".join(blocks) + "\n")
    return Layout(root, n, 1000.0, poses, valid, [k / 30 for k in range(n)])


def make_scannet(base: Path, n: int = 3, scene: str = "scene0000_00", inf_frame: int | None = 2) -> Layout:
    root = base / scene
    poses, valid = [], []
    for k in range(n):
        write_rgb(root / "color" / f"{k}.jpg", colour(k, 2 * W, 2 * H))  # colour larger than depth
        write_png16(root / "depth" / f"{k}.png", depth_raw(k))
        if k == inf_frame:
            (root / "pose" / f"{k}.txt").parent.mkdir(parents=True, exist_ok=True)
            (root / "pose" / f"{k}.txt").write_text("\n".join(["-inf -inf -inf -inf"] * 4) + "\n")
            poses.append(np.full((4, 4), np.nan))
            valid.append(False)
        else:
            (root / "pose").mkdir(parents=True, exist_ok=True)
            (root / "pose" / f"{k}.txt").write_text(pose_rows(known_pose(k)) + "\n")
            poses.append(known_pose(k))
            valid.append(True)
    K = np.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = 28.5, 29.5, 15.5, 11.5
    (root / "intrinsic").mkdir(parents=True, exist_ok=True)
    (root / "intrinsic" / "intrinsic_depth.txt").write_text(pose_rows(K) + "\n")
    return Layout(root, n, 1000.0, poses, valid, [k / 30 for k in range(n)])


def make_tum(base: Path, n: int = 4, scene: str = "rgbd_dataset_freiburg1_xyz") -> Layout:
    """Colour at t0 + k/30, depth 5 ms later, plus one extra colour frame with no depth (dropped).

    Ground truth at 100 Hz only for the first n - 1 frames (the last frame gets no pose -> invalid).
    """
    root = base / scene
    t0 = 1305031102.0
    rgb_lines, depth_lines = ["# color images"], ["# depth maps"]
    for k in range(n):
        t = t0 + k / 30
        write_rgb(root / "rgb" / f"{t:.6f}.png", colour(k))
        write_png16(root / "depth" / f"{t + 0.005:.6f}.png", depth_raw(k))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.005:.6f} depth/{t + 0.005:.6f}.png")
    t_extra = t0 + n / 30 + 1.0  # colour without depth
    write_rgb(root / "rgb" / f"{t_extra:.6f}.png", colour(0))
    rgb_lines.append(f"{t_extra:.6f} rgb/{t_extra:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    gt = ["# timestamp tx ty tz qx qy qz qw"]
    for k in range(n - 1):
        T = known_pose(k)
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        t = T[:3, 3]
        gt.append(f"{t0 + k / 30 + 0.003:.4f} {t[0]} {t[1]} {t[2]} {q[0]} {q[1]} {q[2]} {q[3]}")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    poses = [known_pose(k) for k in range(n - 1)] + [np.full((4, 4), np.nan)]
    return Layout(root, n, 5000.0, poses, [True] * (n - 1) + [False], [t0 + k / 30 for k in range(n)])


def make_7scenes(base: Path, n: int = 3, scene: str = "redkitchen", sub: str = "seq-01", numbers=None) -> Layout:
    root = base / scene
    folder = root / sub if sub else root
    numbers = list(numbers) if numbers is not None else list(range(n))
    for j, k in enumerate(numbers):
        write_rgb(folder / f"frame-{k:06d}.color.png", colour(j))
        d = depth_raw(j)
        d[2, 3] = 65535  # invalid in 7-Scenes
        write_png16(folder / f"frame-{k:06d}.depth.png", d)
        (folder / f"frame-{k:06d}.pose.txt").write_text(pose_rows(known_pose(j)) + "\n")
    (root / "camera-intrinsics.txt").write_text("30.5 0 16.25\n0 30.5 12.5\n0 0 1\n")
    return Layout(root, len(numbers), 1000.0, [known_pose(j) for j in range(len(numbers))], [True] * len(numbers),
                  [k / 30 for k in numbers])


MAKERS = {
    "replica": make_replica,
    "neuralrgbd": make_neuralrgbd,
    "scannet": make_scannet,
    "tum": make_tum,
    "7scenes": make_7scenes,
}
