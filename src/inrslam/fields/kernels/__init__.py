"""Multilinear table lookups (dense/hash grids, planes, lines): fused numba CPU kernels + PyTorch reference."""

from inrslam.fields.kernels.function import (
    DENSE_GRAD_MAX_ROWS,
    InputGradFn,
    MultilinearFn,
    MultilinearJacFn,
    input_grad_only,
    multilinear,
    row_slots,
    second_order,
)
from inrslam.fields.kernels.layout import PRIMES, TableLayout
from inrslam.fields.kernels.torch_interp import interp_torch
from inrslam.fields.kernels.workspace import KernelWorkspace

__all__ = ["DENSE_GRAD_MAX_ROWS", "InputGradFn", "KernelWorkspace", "MultilinearFn", "MultilinearJacFn", "PRIMES",
           "TableLayout", "input_grad_only", "interp_torch", "multilinear", "row_slots", "second_order"]
