"""NeuralRGBD synthetic scenes (Azinović et al. 2022; the paper's "Practical" scenario, docs/spec.md §9.2).

Layout::

    <scene>/images/img0.png, img1.png, ...        8-bit colour (natural sort)
    <scene>/depth_filtered/depth0.png, ...        uint16 millimetres (noisy, filtered; the paper's choice)
    <scene>/poses.txt                             4 lines of 4 values per frame, c2w in **OpenGL** axes;
                                                  a pose containing 'nan' is invalid
    <scene>/gt_mesh_cull_virt_cams.ply            the benchmark's ground-truth mesh, pre-culled with virtual cameras
                                                  (Co-SLAM's evaluation data; optional, preferred when present)
    <scene>/gt_mesh.ply or mesh.ply               ground-truth mesh (optional)

Camera: 640 x 480, fx = fy = 554.2562584220408, cx = 320, cy = 240 (the original floors f to 554:
`faithful_intrinsics`). Poses are converted to OpenCV axes here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from inrslam.data.base import (
    FolderDataset,
    check_count,
    first_existing,
    known_bounds,
    numbered_files,
    pair_numbered,
    require_dir,
)
from inrslam.data.frame import NAN_POSE, Intrinsics
from inrslam.data.posefiles import check_pose, read_pose_blocks
from inrslam.data.registry import DATASETS
from inrslam.geometry.conventions import opengl_to_opencv

NEURALRGBD_BOUNDS = {
    "breakfast_room": [[-2.4, 2.0], [-0.6, 2.9], [-1.8, 3.1]],
    "complete_kitchen": [[-5.7, 3.8], [-0.2, 3.3], [-6.6, 3.6]],
    "green_room": [[-2.6, 5.6], [-0.3, 3.0], [0.2, 5.1]],
    "grey_white_room": [[-0.7, 5.4], [-0.2, 3.1], [-3.9, 0.8]],
    "morning_apartment": [[-1.5, 2.2], [-0.3, 2.2], [-2.3, 1.9]],
    "thin_geometry": [[-2.5, 1.1], [-0.3, 1.1], [0.1, 3.9]],
    "whiteroom": [[-2.6, 3.2], [-0.4, 3.6], [0.5, 8.3]],
}
"""Scene boxes of the paper's configs (docs/spec.md §9.2), metres, world frame of poses.txt."""

FOCAL = 554.2562584220408


@DATASETS.register("neuralrgbd", help="NeuralRGBD synthetic: images/img*.png, depth_filtered/depth*.png, poses.txt")
class NeuralRGBDDataset(FolderDataset):
    """NeuralRGBD synthetic sequence."""

    name = "neuralrgbd"
    layout = "images/img*.png, depth_filtered/depth*.png and poses.txt (4 lines per frame, OpenGL c2w)"
    default_depth_scale = 1000.0

    @classmethod
    def detect(cls, root: Path) -> bool:
        root = Path(root)
        return (root / "images").is_dir() and (root / "poses.txt").is_file()

    def _scan(self) -> Optional[Intrinsics]:
        img_dir = self.root / "images"
        depth_dir = self.root / self.cfg.neuralrgbd.depth_dir
        require_dir(img_dir, self.layout)
        require_dir(depth_dir, self.layout)
        colour = numbered_files(img_dir, r"img(\d+)\.(?:png|jpg)")
        depth = numbered_files(depth_dir, r"depth(\d+)\.png")
        ids = pair_numbered(colour, depth, f"{img_dir}/img*.png", f"{depth_dir}/depth*.png")
        pose_file = self.root / "poses.txt"
        raw, has_nan, first = read_pose_blocks(pose_file)
        check_count(len(ids), len(raw), pose_file)
        poses = []
        for k, (T, bad, line) in enumerate(zip(raw, has_nan, first)):
            T, ok = (NAN_POSE.copy(), False) if bad else check_pose(T, f"{pose_file}:{line}: pose {k}")
            poses.append((opengl_to_opencv(T) if ok else T, ok))
        self._set_numbered_frames(colour, depth, ids, poses, time_from_number=False)
        self.bounds = known_bounds(NEURALRGBD_BOUNDS, self.root.name)
        self.gt_mesh = first_existing(  # the benchmark's own GT: pre-culled with virtual cameras, when present
            [self.root / "gt_mesh_cull_virt_cams.ply", self.root / "gt_mesh.ply", self.root / "mesh.ply",
             self.root.parent / f"{self.root.name}_mesh.ply"]
        )
        return Intrinsics(FOCAL, FOCAL, 320.0, 240.0, 640, 480)
