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
import time
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


class _Retry:
    """The SIGALRM retry of a Ctrl-C put off inside the compiler, and what it borrowed: the caller's SIGALRM handler
    and interval timer, given back (the timer less the time elapsed) once the Ctrl-C is raised or the block ends."""

    pending = False
    handler: object = signal.SIG_DFL
    timer: tuple[float, float] = (0.0, 0.0)
    since = 0.0

    @classmethod
    def arm(cls) -> None:
        if not cls.pending:
            cls.pending, cls.handler = True, signal.getsignal(signal.SIGALRM)
            cls.timer, cls.since = signal.getitimer(signal.ITIMER_REAL), time.monotonic()
            signal.signal(signal.SIGALRM, _handler)
        signal.setitimer(signal.ITIMER_REAL, RETRY_S)  # try again once the compiler has returned

    @classmethod
    def disarm(cls) -> None:
        if not cls.pending:
            return
        cls.pending = False
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, cls.handler if cls.handler is not None else signal.SIG_DFL)
        left, interval = cls.timer
        if left > 0:
            signal.setitimer(signal.ITIMER_REAL, max(left - (time.monotonic() - cls.since), 1e-3), interval)


def _handler(signum: int, frame: types.FrameType | None) -> None:
    if in_jit(frame):
        _Retry.arm()
        return
    _Retry.disarm()
    raise KeyboardInterrupt


@contextmanager
def defer_sigint_in_jit() -> Iterator[bool]:
    """Hold the handler for a block (main thread only), unless SIGINT is not Python's default handler (ignored, as
    in a shell's background job, or the caller's own); the previous handler is back afterwards, and so are the
    caller's SIGALRM handler and timer, which only a Ctrl-C put off inside the compiler borrows. A Ctrl-C still put
    off when the block ends is raised then. Yields whether it was installed."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield False
        return
    signal.signal(signal.SIGINT, _handler)
    failed = False
    try:
        yield True
    except BaseException:
        failed = True
        raise
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        pending = _Retry.pending
        _Retry.disarm()
        if pending and not failed:
            raise KeyboardInterrupt  # the Ctrl-C put off in the compiler's last moments is not lost
