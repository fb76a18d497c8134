"""Replica, NICE-SLAM release (docs/spec.md §9.1).

Layout::

    <scene>/results/frame000000.jpg ...   8-bit colour
    <scene>/results/depth000000.png ...   uint16, metres = value / 6553.5
    <scene>/traj.txt                      one line per frame: 16 values, row-major 4x4 c2w, OpenCV axes
    <scene>/../<scene>_mesh.ply           ground-truth mesh (optional)

Camera: `cam_params.json` ({"camera": {w, h, fx, fy, cx, cy, scale}}, in the scene folder or its parent) when
present, else 1200 x 680, fx = fy = 600, cx = 599.5, cy = 339.5 (the original floor-divides to 599 / 339:
`faithful_intrinsics`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from inrslam.data.base import (
    FolderDataset,
    check_count,
    checked_depth_scale,
    first_existing,
    known_bounds,
    numbered_files,
    pair_numbered,
    read_camera_json,
    require_dir,
)
from inrslam.data.posefiles import check_pose, read_pose_rows
from inrslam.data.registry import DATASETS
from inrslam.geometry.intrinsics import Intrinsics

REPLICA_BOUNDS = {
    "room0": [[-2.9, 8.9], [-3.2, 5.5], [-3.5, 3.3]],
    "room1": [[-6.0, 1.8], [-3.6, 3.3], [-2.0, 1.9]],
    "room2": [[-3.3, 8.5], [-5.7, 4.2], [-5.4, 3.2]],
    "office0": [[-4.5, 4.9], [-5.7, 4.4], [-3.7, 4.3]],
    "office1": [[-4.3, 5.5], [-4.1, 5.0], [-3.5, 4.2]],
    "office2": [[-4.0, 3.6], [-3.4, 5.9], [-1.8, 2.1]],
    "office3": [[-5.7, 4.1], [-6.5, 3.9], [-1.8, 2.5]],
    "office4": [[-2.7, 6.8], [-3.8, 5.7], [-2.7, 3.1]],
}
"""Scene boxes of the paper's configs (docs/spec.md §9.1), metres, world frame of traj.txt."""


@DATASETS.register("replica", help="NICE-SLAM Replica: results/frame*.jpg, results/depth*.png, traj.txt")
class ReplicaDataset(FolderDataset):
    """Replica sequence (NICE-SLAM release)."""

    name = "replica"
    layout = "results/frame%06d.jpg, results/depth%06d.png and traj.txt (16 values per line)"
    default_depth_scale = 6553.5

    @classmethod
    def detect(cls, root: Path) -> bool:
        root = Path(root)
        return (root / "traj.txt").is_file() and (root / "results").is_dir()

    def _scan(self) -> Optional[Intrinsics]:
        res = self.root / "results"
        require_dir(res, self.layout)
        colour = numbered_files(res, r"frame(\d+)\.(?:jpg|jpeg|png)")
        depth = numbered_files(res, r"depth(\d+)\.png")
        ids = pair_numbered(colour, depth, f"{res}/frame*.jpg", f"{res}/depth*.png")
        traj = self.root / "traj.txt"
        raw, line_numbers = read_pose_rows(traj)
        check_count(len(ids), len(raw), traj)
        poses = [check_pose(T, f"{traj}:{n}") for T, n in zip(raw, line_numbers)]
        self._set_numbered_frames(colour, depth, ids, poses, time_from_number=False)
        self.bounds = known_bounds(REPLICA_BOUNDS, self.root.name)
        self.gt_mesh = first_existing([self.root.parent / f"{self.root.name}_mesh.ply", self.root / "mesh.ply"])
        cam_file = first_existing([self.root / "cam_params.json", self.root.parent / "cam_params.json"])
        if cam_file is None:
            return Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
        cam = read_camera_json(cam_file, "camera")
        if self.cfg.depth_scale is None and "scale" in cam:
            self.depth_scale = checked_depth_scale(cam["scale"], f"{cam_file}: camera.scale")
        return Intrinsics(cam["fx"], cam["fy"], cam["cx"], cam["cy"], int(cam.get("w", 1200)), int(cam.get("h", 680)))

