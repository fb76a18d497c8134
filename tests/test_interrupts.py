"""Ctrl-C deferred while numba / llvmlite are on the stack (a KeyboardInterrupt there can crash the process)."""

from __future__ import annotations

import signal
import sys
import time

import pytest

from inrslam.interrupts import _handler, _Retry, defer_sigint_in_jit, in_jit


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
        _Retry.disarm()
    assert signal.getsignal(signal.SIGALRM) is previous and signal.getitimer(signal.ITIMER_REAL)[0] == 0


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


@pytest.fixture
def default_sigint():
    inherited, alarm = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGALRM)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.setitimer(signal.ITIMER_REAL, 0)
    signal.signal(signal.SIGINT, inherited)
    signal.signal(signal.SIGALRM, alarm)


def compiling_when_ctrl_c_arrives():
    """A function of a numba-named module that receives a Ctrl-C while it runs."""
    ns = {"__name__": "numba.core.fake", "signal": signal}
    exec("def compile_():\n    signal.raise_signal(signal.SIGINT)\n", ns)
    return ns["compile_"]


def test_the_callers_alarm_handler_and_timer_are_left_alone(default_sigint):
    fired = []
    signal.signal(signal.SIGALRM, lambda signum, frame: fired.append(signum))
    signal.setitimer(signal.ITIMER_REAL, 30.0)
    with defer_sigint_in_jit():
        pass
    assert 29.0 < signal.getitimer(signal.ITIMER_REAL)[0] <= 30.0  # a watchdog's timer keeps running
    with pytest.raises(KeyboardInterrupt):  # a Ctrl-C put off in the compiler borrows SIGALRM, then gives it back
        with defer_sigint_in_jit():
            compiling_when_ctrl_c_arrives()()
            time.sleep(0.2)
    assert 28.0 < signal.getitimer(signal.ITIMER_REAL)[0] < 30.0
    signal.setitimer(signal.ITIMER_REAL, 0.01)
    time.sleep(0.1)
    assert fired == [signal.SIGALRM]  # the caller's own handler, not a KeyboardInterrupt


def test_a_ctrl_c_put_off_at_the_end_of_the_block_is_raised_when_it_ends(default_sigint):
    with pytest.raises(KeyboardInterrupt):
        with defer_sigint_in_jit():
            compiling_when_ctrl_c_arrives()()  # the block ends before the 50 ms retry
    assert not _Retry.pending and signal.getitimer(signal.ITIMER_REAL)[0] == 0
