"""Software prefetch for the numba kernels: ``prefetch_row(a, r)`` (read) and ``prefetch_row_w(a, r)`` (write)
hint the CPU to bring the cache line of ``a[r, 0]`` (2-D C-contiguous array) or ``a[r]`` (1-D) into cache.

The trilinear kernels compute the 8 corner rows of a block of points first and prefetch them, then gather or
scatter, so that hundreds of cache misses on a large (hash or fine dense) table overlap with the arithmetic
instead of stalling it. A prefetch never faults and has no visible effect besides timing. If this LLVM cannot
compile the intrinsic, both names fall back to a no-op (same results, only slower).
"""

from __future__ import annotations

import llvmlite.binding as llvm
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

#: The overloaded intrinsic's name: opaque pointers (LLVM >= 15) mangle as p0, typed pointers as p0i8.
_NAME = "llvm.prefetch.p0" if llvm.llvm_version_info >= (15,) else "llvm.prefetch.p0i8"


def _make(write: int):
    @intrinsic
    def _prefetch(typingctx, arr, r):
        if not isinstance(arr, types.Array) or arr.ndim not in (1, 2) or not isinstance(r, types.Integer):
            return None
        sig = types.void(arr, r)

        def codegen(context, builder, signature, args):
            aryty, idxty = signature.args
            ary = context.make_array(aryty)(context, builder, args[0])
            idx = [context.cast(builder, args[1], idxty, types.intp)]
            if aryty.ndim == 2:
                idx.append(context.get_constant(types.intp, 0))
            ptr = cgutils.get_item_pointer2(context, builder, ary.data, cgutils.unpack_tuple(builder, ary.shape),
                                            cgutils.unpack_tuple(builder, ary.strides), aryty.layout, idx,
                                            wraparound=False, boundscheck=False)
            i8p = ir.IntType(8).as_pointer()
            i32 = ir.IntType(32)
            fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                                _NAME)
            # (address, rw: 0 read / 1 write, locality 3 = keep in all cache levels, 1 = data cache)
            builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, write), ir.Constant(i32, 3),
                              ir.Constant(i32, 1)])
            return context.get_dummy_value()

        return sig, codegen

    return _prefetch


prefetch_row = _make(0)
prefetch_row_w = _make(1)


@njit(cache=True)
def _probe(a):
    prefetch_row(a, 0)
    prefetch_row_w(a, 0)


try:  # compile once here rather than fail inside every kernel
    import numpy as np

    _probe(np.zeros((1, 1)))
    AVAILABLE = True
except Exception:  # pragma: no cover - depends on the LLVM build
    AVAILABLE = False

    @njit(inline="always", cache=True)
    def prefetch_row(a, r):  # noqa: F811 - no-op fallback
        return None

    @njit(inline="always", cache=True)
    def prefetch_row_w(a, r):  # noqa: F811 - no-op fallback
        return None
