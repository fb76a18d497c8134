"""Ctrl-C (and SIGTERM / SIGHUP) that never lands inside the JIT compiler.

A SIGINT whose KeyboardInterrupt is raised while numba / llvmlite is compiling or loading a cached kernel (their
Python callbacks run under ctypes) cannot unwind: the exception is swallowed there and the process can crash
(seen: a segmentation fault instead of the clean "interrupted; resume with ..." exit). `defer_interrupts_in_jit`
installs a handler that raises KeyboardInterrupt at once anywhere else, and inside those frames retries every 50 ms
until the compiler has returned. SIGTERM (`kill`, a batch system's time limit) and SIGHUP (a closed terminal) get
the same handler where they would otherwise end the process on the spot: they raise `Terminated`, a
KeyboardInterrupt, so a run or a sweep unwinds as on Ctrl-C (a sweep cancels its jobs, files are written whole).
"""

from __future__ import annotations

import os
import signal
import threading
import time
import types
from contextlib import contextmanager
from typing import Iterator

RETRY_S = 0.05
_JIT_MODULES = ("numba", "llvmlite")
#: signals that end a process by default and are turned into `Terminated` (SIGHUP is missing on Windows)
TERMINATING = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised where Ctrl-C would be; `signum` is the signal's number, `str()` its name."""

    def __init__(self, signum: int):
        super().__init__(int(signum))  # args = (signum,): pickled and copied as it was made
        self.signum = int(signum)

    def __str__(self) -> str:
        return signal.Signals(self.signum).name


def interrupt(signum: int) -> KeyboardInterrupt:
    """The exception a signal raises: KeyboardInterrupt for SIGINT, `Terminated` for the others."""
    return Terminated(signum) if signum in TERMINATING else KeyboardInterrupt()


def in_jit(frame: types.FrameType | None) -> bool:
    """Whether any frame of the stack from `frame` outwards belongs to numba or llvmlite."""
    while frame is not None:
        if str(frame.f_globals.get("__name__", "")).startswith(_JIT_MODULES):
            return True
        frame = frame.f_back
    return False


class _Retry:
    """The SIGALRM retry of a signal put off inside the compiler, and what it borrowed: the caller's SIGALRM handler
    and interval timer, given back (the timer less the time elapsed) once the interrupt is raised or the block ends.
    `signum` is the signal put off (the first one, if several arrive)."""

    pending = False
    signum = int(signal.SIGINT)
    handler: object = signal.SIG_DFL
    timer: tuple[float, float] = (0.0, 0.0)
    since = 0.0

    @classmethod
    def arm(cls, signum: int) -> None:
        if not cls.pending:
            cls.pending, cls.signum, cls.handler = True, int(signum), signal.getsignal(signal.SIGALRM)
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


class Held:
    """A `hold_interrupts` block's state: `signum` of the first signal put off (else None); `note`, printed on stderr
    when one is (what the wait is for); `active`, False to let signals through at once for a while (work that cannot
    be saved part-way)."""

    def __init__(self, note: str | None = None) -> None:
        self.signum: int | None = None
        self.note = note
        self.active = True


_HOLD: list[Held] = []  # the main thread's hold_interrupts blocks, innermost last


@contextmanager
def hold_interrupts(note: str | None = None) -> Iterator[Held]:
    """Put off a signal that `defer_interrupts_in_jit`'s handler receives until the caller is ready, so that a unit
    of work (a SLAM frame) completes and can be saved: the caller checks `Held.signum` between units and raises
    `interrupt(signum)` itself. A second Ctrl-C is raised at once (a user who presses it twice does not wait); a
    repeated SIGTERM or SIGHUP (a scheduler and `kill` both sending one) is not. Where that handler is not installed
    (a script, a notebook) or outside the main thread, the block changes nothing."""
    held = Held(note)
    if threading.current_thread() is not threading.main_thread():
        yield held
        return
    _HOLD.append(held)
    try:
        yield held
    finally:
        _HOLD.remove(held)


def _handler(signum: int, frame: types.FrameType | None) -> None:
    if signum == getattr(signal, "SIGALRM", None):  # the retry of a signal put off: raise that one ...
        signum = _Retry.signum
        if _HOLD and _HOLD[-1].active and _HOLD[-1].signum is None:  # ... or hand it to a hold begun since
            _Retry.disarm()
            _HOLD[-1].signum = signum
            _say(_HOLD[-1].note)
            return
    elif _HOLD and _HOLD[-1].active:
        held = _HOLD[-1]
        if held.signum is None:  # the first signal in a hold: noted, raised by its caller
            held.signum = int(signum)
            _say(held.note)
            return
        if signum != signal.SIGINT:  # a repeated SIGTERM / SIGHUP: the unit still ends and is saved
            return
    if in_jit(frame) and hasattr(signal, "SIGALRM"):
        _Retry.arm(signum)
        return
    _Retry.disarm()
    raise interrupt(signum)


def _say(note: str | None) -> None:
    """`note` on stderr (file descriptor 2, unbuffered: the handler may interrupt a write to `sys.stderr`), if
    there is one and stderr can take it (a closed terminal cannot)."""
    if note:
        try:
            os.write(2, f"inrslam: {note}\n".encode())
        except OSError:
            pass


@contextmanager
def signals_blocked() -> Iterator[None]:
    """Block SIGINT, SIGTERM and SIGHUP for a short block (main thread, POSIX), and so for the processes it starts
    (they inherit the mask): a terminal's Ctrl-C reaches the whole process group, and a child that must not be cut
    short (`sbatch`) is not. Signals that arrive meanwhile are delivered when the block ends."""
    mask = getattr(signal, "pthread_sigmask", None)
    if mask is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = mask(signal.SIG_BLOCK, {int(signal.SIGINT), *TERMINATING})
    try:
        yield
    finally:
        mask(signal.SIG_SETMASK, previous)


def _ours(signum: int) -> bool:
    """Whether `signum` still has the default behaviour we replace (an ignored or caller-set handler is kept)."""
    current = signal.getsignal(signum)
    return current is signal.default_int_handler if signum == signal.SIGINT else current is signal.SIG_DFL


@contextmanager
def defer_interrupts_in_jit() -> Iterator[tuple[int, ...]]:
    """Hold the handler for a block (main thread only) on SIGINT, SIGTERM and SIGHUP, each only where it has its
    default behaviour (an ignored one, as SIGINT in a shell's background job or SIGHUP under `nohup`, and a caller's
    own handler are left alone); the previous handlers are back afterwards, and so are the caller's SIGALRM handler
    and timer, which only a signal put off inside the compiler borrows. A signal still put off when the block ends
    is raised then. Yields the signals the handler was installed for."""
    if threading.current_thread() is not threading.main_thread():
        yield ()
        return
    installed = tuple(s for s in (int(signal.SIGINT), *TERMINATING) if _ours(s))
    previous = {s: signal.getsignal(s) for s in installed}
    for s in installed:
        signal.signal(s, _handler)
    failed = False
    try:
        yield installed
    except BaseException:
        failed = True
        raise
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        pending, signum = _Retry.pending, _Retry.signum
        _Retry.disarm()
        if pending and not failed:
            raise interrupt(signum)  # the signal put off in the compiler's last moments is not lost
