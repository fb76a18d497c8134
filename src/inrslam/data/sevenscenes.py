"""Microsoft 7-Scenes, and the 3DMatch / SUN3D packaging of the same layout.

Layout (frames in the root or in one sub-folder such as `data/` or `seq-01/`)::

    [<sub>/]frame-000000.color.jpg|png     8-bit colour
    [<sub>/]frame-000000.depth.png         uint16 millimetres; 0 and 65535 = no measurement
    [<sub>/]frame-000000.pose.txt          4x4 c2w, OpenCV axes, metres (non-finite = invalid)
    camera-intrinsics.txt                  3x3 K, in the frame folder or the root (7-Scenes default
                                           fx = fy = 585, cx = 320, cy = 240 when absent)

Timestamps = frame number / 30 s (the files carry none).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from inrslam.data.base import FolderDataset, first_existing, numbered_files, pair_numbered
from inrslam.data.images import image_size
from inrslam.data.posefiles import check_pose, read_matrix, read_pose_matrix
from inrslam.data.registry import DATASETS
from inrslam.errors import DataError
from inrslam.geometry.intrinsics import Intrinsics

_COLOUR = r"frame-(\d+)\.color\.(?:jpg|png)"
_DEPTH = r"frame-(\d+)\.depth\.png"
_POSE = r"frame-(\d+)\.pose\.txt"


def _has_frames(folder: Path) -> bool:
    return folder.is_dir() and any(folder.glob("frame-*.depth.png"))


def frame_folders(root: Path) -> list[Path]:
    """The root if it holds frame files, else its sub-folders that do (sorted)."""
    if _has_frames(root):
        return [root]
    return sorted((p for p in root.iterdir() if _has_frames(p)), key=lambda p: p.name) if root.is_dir() else []


@DATASETS.register("7scenes", help="7-Scenes / 3DMatch / SUN3D: frame-NNNNNN.{color.jpg,depth.png,pose.txt}")
class SevenScenesDataset(FolderDataset):
    """7-Scenes-style sequence (also 3DMatch / SUN3D)."""

    name = "7scenes"
    layout = "frame-NNNNNN.color.jpg|png, frame-NNNNNN.depth.png, frame-NNNNNN.pose.txt (in the root, data/ or seq-XX/)"
    default_depth_scale = 1000.0
    invalid_depth = (65535,)
    floors_intrinsics = False  # not a layout of the original code

    @classmethod
    def detect(cls, root: Path) -> bool:
        return bool(frame_folders(Path(root)))

    def _scan(self) -> Optional[Intrinsics]:
        folders = frame_folders(self.root)
        sequence = self.cfg.sevenscenes.sequence
        if sequence:
            folder = self.root / sequence
            if not _has_frames(folder):
                raise DataError(f"{folder}: no frame-*.depth.png files (data.sevenscenes.sequence = {sequence!r})")
        elif not folders:
            raise DataError(f"{self.root}: no frames found (expected {self.layout})")
        elif len(folders) > 1:
            names = ", ".join(p.name for p in folders)
            raise DataError(f"{self.root}: several sequences ({names}); choose one with data.sevenscenes.sequence")
        else:
            folder = folders[0]
        self.frame_dir = folder
        colour = numbered_files(folder, _COLOUR)
        depth = numbered_files(folder, _DEPTH)
        ids = pair_numbered(colour, depth, f"{folder}/frame-*.color.jpg", f"{folder}/frame-*.depth.png")
        pose_files = numbered_files(folder, _POSE)
        missing = [n for n in ids if n not in pose_files]
        if missing or len(pose_files) != len(ids):
            first = folder / f"frame-{missing[0]:06d}.pose.txt" if missing else folder
            raise DataError(
                f"{first}: count mismatch: {len(pose_files)} pose files for {len(ids)} colour/depth frames "
                "(expected frame-NNNNNN.pose.txt for every frame)"
            )
        poses = [check_pose(read_pose_matrix(pose_files[n]), str(pose_files[n])) for n in ids]
        self._set_numbered_frames(colour, depth, ids, poses, time_from_number=True)
        self.gt_mesh = first_existing([self.root / "mesh.ply", folder / "mesh.ply"])
        width, height = image_size(self._depth[0])
        k_file = first_existing([folder / "camera-intrinsics.txt", self.root / "camera-intrinsics.txt"])
        if k_file is None:
            return Intrinsics(585.0, 585.0, 320.0, 240.0, width, height)
        K = read_matrix(k_file, 3, 3, "3x3 camera matrix K")
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise DataError(f"{k_file}: invalid camera matrix {K.tolist()}")
        return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height)
