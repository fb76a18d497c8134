"""Model size as the paper counts it (docs/spec.md §8.4): all scene parameters, bytes / 2^20."""

from __future__ import annotations

from torch import nn


def param_count(field: nn.Module) -> int:
    """Number of scene parameters (encoder tables + decoders; fixed buffers such as the Fourier matrix excluded)."""
    return sum(p.numel() for p in field.parameters())


def model_size_mb(field: nn.Module, with_optimizer: bool = False) -> float:
    """Σ numel · bytes per element / 2^20 (MiB); with_optimizer adds Adam's two moments per parameter (×3)."""
    nbytes = sum(p.numel() * p.element_size() for p in field.parameters())
    return nbytes * (3 if with_optimizer else 1) / 2**20
