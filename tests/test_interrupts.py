"""Ctrl-C deferred while numba / llvmlite are on the stack (a KeyboardInterrupt there can crash the process)."""

from __future__ import annotations

import signal
import sys

import pytest

from inrslam.interrupts import _handler, defer_sigint_in_jit, in_jit


def frame_in(module: str):
    """A live frame whose function belongs to `module` (as numba's own functions do)."""
    ns = {"__name__": module, "sys": sys}
    exec("def grab():\n    return sys._getframe()\n", ns)
    return ns["grab"]()


def test_in_jit_looks_at_every_frame_outwards():
    assert in_jit(frame_in("numba.core.compiler"))
    assert in_jit(frame_in("llvmlite.binding.executionengine"))
    assert not in_jit(frame_in("inrslam.slam.mapping"))
    assert not in_jit(sys._getframe())


def test_handler_raises_outside_and_retries_inside_the_compiler():
    with pytest.raises(KeyboardInterrupt):
        _handler(signal.SIGINT, frame_in("inrslam.slam.mapping"))
    previous = signal.getsignal(signal.SIGALRM)
    try:
        _handler(signal.SIGINT, frame_in("numba.core.dispatcher"))  # no exception now ...
        assert signal.getitimer(signal.ITIMER_REAL)[0] > 0  # ... a retry is armed
        assert signal.getsignal(signal.SIGALRM) is _handler
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def test_the_block_restores_the_default_and_leaves_an_ignored_sigint_alone():
    inherited = signal.getsignal(signal.SIGINT)  # SIG_IGN when the test process was started with nohup / `&`
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with defer_sigint_in_jit() as installed:
            assert installed and signal.getsignal(signal.SIGINT) is _handler
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with defer_sigint_in_jit() as installed:
            assert not installed and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, inherited)
