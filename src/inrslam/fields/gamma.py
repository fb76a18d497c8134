"""Positional encodings γ(p̂) of normalised coordinates p̂ (docs/spec.md §3.2)."""

from __future__ import annotations

import torch
from torch import nn

from inrslam.errors import ConfigError

GAMMAS = ("identity", "blob", "freq")


class Identity(nn.Module):
    """γ(p̂) = p̂ (3-d)."""

    out_dim = 3

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        return p


def _quartic_cdf(u: torch.Tensor, bins: int) -> torch.Tensor:
    """C₀(u) = clamp(15/16·v(1 − 2/3·v² + 1/5·v⁴) + 1/2, 0, 1), v = bins·u: CDF of the quartic kernel 15/16(1−v²)²."""
    v = u * bins
    return torch.clamp(15.0 / 16.0 * v * (1.0 - 2.0 / 3.0 * v * v + 0.2 * v ** 4) + 0.5, 0.0, 1.0)


class OneBlob(nn.Module):
    """One-blob encoding with tiny-cuda-nn's quartic kernel: 16 bins per axis (48-d), periodic images x, x±1.

    value_k(x) = Σ_{m∈{−1,0,1}} C₀(r_k − x − m) − C₀(l_k − x − m), l_k = k/16, r_k = (k+1)/16 (Müller et al. 2019).
    """

    def __init__(self, bins: int = 16):
        super().__init__()
        self.bins = bins
        self.out_dim = 3 * bins

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        k = torch.arange(self.bins, device=p.device, dtype=p.dtype)
        lo, hi = k / self.bins, (k + 1) / self.bins
        x = p.unsqueeze(-1)  # (N,3,1)
        val = torch.zeros(p.shape[0], 3, self.bins, device=p.device, dtype=p.dtype)
        for m in (-1.0, 0.0, 1.0):
            val = val + _quartic_cdf(hi - x - m, self.bins) - _quartic_cdf(lo - x - m, self.bins)
        return val.reshape(p.shape[0], -1)


class FourierFeatures(nn.Module):
    """Gaussian Fourier features γ(p̂) = sin(p̂ᵀB), B (3, 93) ~ N(0, 25²), fixed (buffer, not optimised; iMAP)."""

    B: torch.Tensor  # (3, out_dim) buffer

    def __init__(self, out_dim: int = 93, sigma: float = 25.0):
        super().__init__()
        self.out_dim = out_dim
        self.register_buffer("B", torch.randn(3, out_dim) * sigma)

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        return torch.sin(p @ self.B.to(p.dtype))


def make_gamma(name: str) -> Identity | OneBlob | FourierFeatures:
    """The positional encoding called ``name`` (identity | blob | freq)."""
    if name == "identity":
        return Identity()
    if name == "blob":
        return OneBlob()
    if name == "freq":
        return FourierFeatures()
    raise ConfigError(f"field.gamma: unknown positional encoding {name!r} (choices: {', '.join(GAMMAS)})")
