"""Ctrl-C that never lands inside the JIT compiler.

A SIGINT whose KeyboardInterrupt is raised while numba / llvmlite is compiling or loading a cached kernel (their
Python callbacks run under ctypes) cannot unwind: the exception is swallowed there and the process can crash
(seen: a segmentation fault instead of the clean "interrupted; resume with ..." exit). `defer_sigint_in_jit`
installs a SIGINT handler that raises KeyboardInterrupt at once anywhere else, and inside those frames retries
every 50 ms until the compiler has returned.
"""

from __future__ import annotations

import signal
import threading
import types
from contextlib import contextmanager
from typing import Iterator

RETRY_S = 0.05
_JIT_MODULES = ("numba", "llvmlite")


def in_jit(frame: types.FrameType | None) -> bool:
    """Whether any frame of the stack from `frame` outwards belongs to numba or llvmlite."""
    while frame is not None:
        if str(frame.f_globals.get("__name__", "")).startswith(_JIT_MODULES):
            return True
        frame = frame.f_back
    return False


def _handler(signum: int, frame: types.FrameType | None) -> None:
    if in_jit(frame):
        signal.signal(signal.SIGALRM, _handler)
        signal.setitimer(signal.ITIMER_REAL, RETRY_S)  # try again once the compiler has returned
        return
    raise KeyboardInterrupt


@contextmanager
def defer_sigint_in_jit() -> Iterator[bool]:
    """Hold the handler for a block (main thread only), unless SIGINT is not Python's default handler (ignored, as
    in a shell's background job, or the caller's own); the previous handler is back afterwards. Yields whether it
    was installed."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield False
        return
    signal.signal(signal.SIGINT, _handler)
    try:
        yield True
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.setitimer(signal.ITIMER_REAL, 0)
