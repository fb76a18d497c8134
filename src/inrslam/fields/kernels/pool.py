"""Reusable numpy buffers for arrays that the fused kernels hand to torch without a copy (sparse gradients).

A fresh multi-MB array per backward pays its page faults on first write (glibc gives large blocks back to the
OS when they are freed), which can cost more than the kernel that fills it. A ``BufferPool`` keeps a few base
arrays and hands out views of them; a base is reused only once the view it last handed out has been freed. A
tensor made by ``torch.from_numpy(view)`` keeps ``view`` alive for as long as any tensor shares its memory, so a
base is never written while torch can still read it.
"""

from __future__ import annotations

import math
import weakref

import numpy as np


class BufferPool:
    """At most ``max_buffers`` kept base arrays; ``take`` returns a view of a free one (the smallest that fits, else
    the largest grown), or a plain new array when all are in use. Not thread-safe: like the rest of the
    ``KernelWorkspace`` that holds it (one per table layout), one pool serves one thread at a time."""

    def __init__(self, max_buffers: int = 8):
        self.max_buffers = max_buffers
        self._bases: list[np.ndarray] = []  # (bytes,) uint8
        self._users: list[weakref.ref | None] = []  # the view handed out last, per base

    def take(self, shape: tuple[int, ...], dtype) -> np.ndarray:
        """An uninitialised C-contiguous array of ``shape`` and ``dtype`` that nothing else uses. Hand exactly this
        array to ``torch.from_numpy`` (not a numpy view of it, whose base would skip it): the pool tracks it."""
        dtype = np.dtype(dtype)
        need = max(1, math.prod(shape)) * dtype.itemsize
        free = [i for i, user in enumerate(self._users) if user is None or user() is None]
        if free:
            fits = [k for k in free if self._bases[k].nbytes >= need]
            if fits:  # the smallest free buffer that fits
                i = min(fits, key=lambda k: self._bases[k].nbytes)
            else:  # grow the largest free one, with headroom: sizes vary a little from call to call
                i = max(free, key=lambda k: self._bases[k].nbytes)
                self._bases[i] = np.empty(need + need // 4, np.uint8)
        elif len(self._bases) < self.max_buffers:
            i = len(self._bases)
            self._bases.append(np.empty(need + need // 4, np.uint8))
            self._users.append(None)
        else:
            return np.empty(shape, dtype)
        view = self._bases[i][:need].view(dtype)[: math.prod(shape)].reshape(shape)
        self._users[i] = weakref.ref(view)
        return view

    @property
    def nbytes(self) -> int:
        """Bytes held by the kept base arrays."""
        return sum(b.nbytes for b in self._bases)
