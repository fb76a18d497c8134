"""Explicit Hybrid Encoding (EHE): a mapping-only system with given poses — sparse 10 cm voxels holding SDF priors,
one 2 cm dense feature level and two small bias-free decoders (docs/ehe.md)."""

from inrslam.slam.ehe.config import EheConfig

__all__ = ["EheConfig"]
