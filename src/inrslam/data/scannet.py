"""ScanNet, exported with the official SensReader (docs/spec.md §9.3).

Layout::

    <scene>/color/0.jpg, 1.jpg, ...             8-bit colour (1296 x 968), resized here to the depth size
    <scene>/depth/0.png, ...                    uint16 millimetres (640 x 480)
    <scene>/pose/0.txt, ...                     4x4 c2w, OpenCV axes, 4 lines; may hold -inf / nan (= invalid)
    <scene>/intrinsic/intrinsic_depth.txt       4x4 (the upper-left 3x3 is K of the depth image)
    <scene>/<scene>_vh_clean_2.ply              ground-truth mesh (optional)

Files are matched by the number in their stem (numeric sort).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from inrslam.data.base import FolderDataset, check_count, first_existing, numbered_files, pair_numbered, require_dir
from inrslam.data.images import image_size
from inrslam.data.posefiles import check_pose, read_matrix, read_pose_matrix
from inrslam.data.registry import DATASETS
from inrslam.errors import DataError
from inrslam.geometry.intrinsics import Intrinsics


@DATASETS.register("scannet", help="ScanNet SensReader export: color/, depth/, pose/, intrinsic/intrinsic_depth.txt")
class ScanNetDataset(FolderDataset):
    """ScanNet sequence; colour is resized to the depth resolution."""

    name = "scannet"
    layout = "color/N.jpg, depth/N.png, pose/N.txt and intrinsic/intrinsic_depth.txt"
    default_depth_scale = 1000.0
    resize_colour = True

    @classmethod
    def detect(cls, root: Path) -> bool:
        root = Path(root)
        return all((root / d).is_dir() for d in ("color", "depth", "pose"))

    def _scan(self) -> Optional[Intrinsics]:
        for d in ("color", "depth", "pose"):
            require_dir(self.root / d, self.layout)
        colour = numbered_files(self.root / "color", r"(\d+)\.(?:jpg|jpeg|png)")
        depth = numbered_files(self.root / "depth", r"(\d+)\.png")
        ids = pair_numbered(colour, depth, f"{self.root}/color/N.jpg", f"{self.root}/depth/N.png")
        pose_files = numbered_files(self.root / "pose", r"(\d+)\.txt")
        missing = [n for n in ids if n not in pose_files]
        if missing:
            raise DataError(
                f"{self.root / 'pose' / f'{missing[0]}.txt'}: pose file missing for frame {missing[0]} "
                f"({len(pose_files)} pose files for {len(ids)} colour/depth frames)"
            )
        check_count(len(ids), len(pose_files), self.root / "pose")
        poses = [check_pose(read_pose_matrix(pose_files[n]), str(pose_files[n])) for n in ids]
        self._set_numbered_frames(colour, depth, ids, poses, time_from_number=True)
        self.gt_mesh = first_existing([self.root / f"{self.root.name}_vh_clean_2.ply", self.root / "mesh.ply"])
        k_file = self.root / "intrinsic" / "intrinsic_depth.txt"
        if self.cfg.intrinsics is not None:
            return None  # the override wins; the file is not needed
        if not k_file.is_file():
            raise DataError(f"{k_file}: intrinsics file not found (or set data.intrinsics = [fx, fy, cx, cy])")
        M = read_matrix(k_file, 4, 4, "4x4 intrinsic matrix")
        if not np.all(np.isfinite(M[:3, :3])) or M[0, 0] <= 0 or M[1, 1] <= 0:
            raise DataError(f"{k_file}: invalid intrinsic matrix {M[:3, :3].tolist()}")
        width, height = image_size(self._depth[0])
        return Intrinsics(float(M[0, 0]), float(M[1, 1]), float(M[0, 2]), float(M[1, 2]), width, height)
