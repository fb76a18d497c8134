"""Registry of dataset readers by name (`DataConfig.dataset`)."""

from __future__ import annotations

from inrslam.registry import Registry

DATASETS: Registry = Registry("dataset")
"""name -> reader class; each class has `detect(root) -> bool`, a `layout` description and `__init__(root, cfg)`."""
