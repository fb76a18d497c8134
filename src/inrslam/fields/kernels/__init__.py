"""Multilinear table lookups (dense/hash grids, planes, lines): fused numba CPU kernels + PyTorch reference."""

from inrslam.fields.kernels.function import DENSE_GRAD_MAX_ROWS, MultilinearFn, multilinear, row_slots
from inrslam.fields.kernels.layout import PRIMES, TableLayout
from inrslam.fields.kernels.torch_interp import interp_torch
from inrslam.fields.kernels.workspace import KernelWorkspace

__all__ = ["DENSE_GRAD_MAX_ROWS", "KernelWorkspace", "MultilinearFn", "PRIMES", "TableLayout", "interp_torch",
           "multilinear", "row_slots"]
