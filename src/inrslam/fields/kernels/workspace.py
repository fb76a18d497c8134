"""Everything the fused kernels keep between calls for one ``TableLayout``: scratch arrays, the gradient buffer pool
and caches, as declared fields of one ``KernelWorkspace``.

A layout holds exactly one workspace (``TableLayout.workspace``), empty when the layout is built and filled on first
use by ``function.py``; copies and pickles of a layout start with an empty one, so they never share or carry scratch.
Scratch arrays are kept large (grown, never shrunk) so that a steady stream of calls allocates nothing and pays no
page faults. Not thread-safe: one layout serves one thread at a time.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field

import numpy as np
import torch

from inrslam.fields.kernels.pool import BufferPool


@dataclass(eq=False, slots=True)
class KernelWorkspace:
    """Scratch of the fused kernels for one layout of E entries over an (M, F) table (None = not created yet)."""

    #: (M,) row → slot map of the row-compaction kernels (slot-based sparse backward, the optimizer's
    #: ``unique_rows_sum``), all −1 between uses; int32, or int64 for tables of 2^31 rows or more
    #: (``function.row_index_dtype``).
    slots: np.ndarray | None = None
    #: (acc (M,F), mark_off (E,) int64, mark (Σ⌈rows/8⌉,) uint8) of the accumulator table backward: a dense gradient
    #: and a touched-row bitmap (entry e's bits from byte mark_off[e]), all zero between uses.
    accumulator: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    #: (rows (C,), values (C,F)) per-item output blocks of the slot-based sparse backward (rows of the slots' dtype),
    #: never zeroed.
    sparse_out: tuple[np.ndarray, np.ndarray] | None = None
    #: Flat buffer of the (E,N,F) level-major copy of the output gradient (accumulator backward).
    level_major: np.ndarray | None = None
    #: Buffers of the (rows, values) arrays of the sparse gradients handed to torch.
    grad_pool: BufferPool = field(default_factory=BufferPool)
    #: Weak references to the (rows, values) arrays of the last fused sparse gradient, whose rows are unique.
    last_grad: tuple[weakref.ref, weakref.ref] | None = None
    #: str(device) → the layout's metadata as tensors on that device (reference path).
    torch_arrays: dict[str, dict[str, torch.Tensor]] = field(default_factory=dict)
