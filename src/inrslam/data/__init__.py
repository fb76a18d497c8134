"""Datasets: one protocol (`RGBDDataset`) yielding `Frame`s; readers per public layout."""

from inrslam.data.frame import NAN_POSE, Frame, Intrinsics, RGBDDataset  # noqa: I001
from inrslam.data.config import DataConfig
from inrslam.data.registry import DATASETS
from inrslam.data.detect import detect_layout
from inrslam.data.bounds import estimate_bounds
from inrslam.data.view import DatasetView
from inrslam.data.open import open_folder

__all__ = [
    "NAN_POSE",
    "Frame",
    "Intrinsics",
    "RGBDDataset",
    "DataConfig",
    "DATASETS",
    "detect_layout",
    "estimate_bounds",
    "DatasetView",
    "open_folder",
]
