"""Multilinear table lookups (dense/hash grids, planes, lines): fused numba CPU kernels + PyTorch reference."""

from inrslam.fields.kernels.function import DENSE_GRAD_MAX_ROWS, MultilinearFn, multilinear, workspace
from inrslam.fields.kernels.layout import PRIMES, TableLayout
from inrslam.fields.kernels.torch_interp import interp_torch

__all__ = ["DENSE_GRAD_MAX_ROWS", "TableLayout", "MultilinearFn", "PRIMES", "interp_torch", "multilinear", "workspace"]
