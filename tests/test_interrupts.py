"""Ctrl-C (and SIGTERM / SIGHUP) deferred while numba / llvmlite are on the stack (a KeyboardInterrupt there can crash
the process)."""

from __future__ import annotations

import signal
import sys
import time

import pytest

from inrslam.interrupts import (TERMINATING, Terminated, _handler, _Retry, defer_interrupts_in_jit, hold_interrupts,
                                 in_jit)


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
        with defer_interrupts_in_jit() as installed:
            assert signal.SIGINT in installed and signal.getsignal(signal.SIGINT) is _handler
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with defer_interrupts_in_jit() as installed:
            assert signal.SIGINT not in installed and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
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
    with defer_interrupts_in_jit():
        pass
    assert 29.0 < signal.getitimer(signal.ITIMER_REAL)[0] <= 30.0  # a watchdog's timer keeps running
    with pytest.raises(KeyboardInterrupt):  # a Ctrl-C put off in the compiler borrows SIGALRM, then gives it back
        with defer_interrupts_in_jit():
            compiling_when_ctrl_c_arrives()()
            time.sleep(0.2)
    assert 28.0 < signal.getitimer(signal.ITIMER_REAL)[0] < 30.0
    signal.setitimer(signal.ITIMER_REAL, 0.01)
    time.sleep(0.1)
    assert fired == [signal.SIGALRM]  # the caller's own handler, not a KeyboardInterrupt


def test_a_ctrl_c_put_off_at_the_end_of_the_block_is_raised_when_it_ends(default_sigint):
    with pytest.raises(KeyboardInterrupt):
        with defer_interrupts_in_jit():
            compiling_when_ctrl_c_arrives()()  # the block ends before the 50 ms retry
    assert not _Retry.pending and signal.getitimer(signal.ITIMER_REAL)[0] == 0


@pytest.fixture
def default_terminating():
    """SIGTERM / SIGHUP at their defaults for the test (restored afterwards)."""
    inherited = {s: signal.getsignal(s) for s in TERMINATING}
    for s in TERMINATING:
        signal.signal(s, signal.SIG_DFL)
    yield
    for s, h in inherited.items():
        signal.signal(s, h)


@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP"])
def test_sigterm_and_sighup_raise_terminated_naming_the_signal(default_terminating, name):
    signum = getattr(signal, name, None)
    if signum is None:
        pytest.skip(f"{name} does not exist on this platform")
    with pytest.raises(Terminated) as caught:
        with defer_interrupts_in_jit() as installed:
            assert signum in installed and signal.getsignal(signum) is _handler
            signal.raise_signal(signum)
            time.sleep(1.0)  # the handler raises before this ends
    assert caught.value.signum == signum and str(caught.value) == name
    assert isinstance(caught.value, KeyboardInterrupt)  # every `except KeyboardInterrupt` unwinds it the same way
    assert signal.getsignal(signum) is signal.SIG_DFL  # given back


def test_an_ignored_or_callers_sigterm_is_left_alone(default_terminating):
    mine = lambda signum, frame: None  # noqa: E731
    signal.signal(signal.SIGTERM, mine)
    if hasattr(signal, "SIGHUP"):
        signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as under nohup
    with defer_interrupts_in_jit() as installed:
        assert signal.SIGTERM not in installed and signal.getsignal(signal.SIGTERM) is mine
        if hasattr(signal, "SIGHUP"):
            assert signal.SIGHUP not in installed and signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    assert signal.getsignal(signal.SIGTERM) is mine


def test_a_sigterm_inside_the_compiler_is_raised_as_terminated_once_it_returns(default_terminating, default_sigint):
    ns = {"__name__": "numba.core.fake", "signal": signal}
    exec("def compile_():\n    signal.raise_signal(signal.SIGTERM)\n", ns)
    with pytest.raises(Terminated) as caught:
        with defer_interrupts_in_jit():
            ns["compile_"]()  # put off: no exception inside the compiler ...
            assert _Retry.pending and _Retry.signum == signal.SIGTERM
            time.sleep(0.5)  # ... raised by the retry, still as SIGTERM
    assert caught.value.signum == signal.SIGTERM and not _Retry.pending


def test_a_hold_puts_off_the_first_signal_and_raises_a_second_at_once(default_terminating, default_sigint):
    with defer_interrupts_in_jit():
        with hold_interrupts() as held:
            signal.raise_signal(signal.SIGTERM)  # noted, not raised: the unit of work goes on
            time.sleep(0.1)
        assert held.signum == signal.SIGTERM
        with pytest.raises(KeyboardInterrupt):
            with hold_interrupts() as held:
                signal.raise_signal(signal.SIGTERM)
                signal.raise_signal(signal.SIGINT)  # a second one: at once
                time.sleep(1.0)
        assert held.signum == signal.SIGTERM


def test_a_hold_without_our_handler_changes_nothing(default_sigint):
    with pytest.raises(KeyboardInterrupt):  # a script's or notebook's Ctrl-C stops it where it is
        with hold_interrupts() as held:
            signal.raise_signal(signal.SIGINT)
            time.sleep(1.0)
    assert held.signum is None


def test_a_repeated_sigterm_does_not_cut_the_held_work_short_and_the_note_is_printed(default_terminating,
                                                                                      default_sigint, capfd):
    with defer_interrupts_in_jit():
        with hold_interrupts("finishing frame 7 and saving it") as held:
            signal.raise_signal(signal.SIGTERM)
            signal.raise_signal(signal.SIGTERM)  # a scheduler and `kill` both: still held
            time.sleep(0.1)
        assert held.signum == signal.SIGTERM
    assert capfd.readouterr().err == "inrslam: finishing frame 7 and saving it\n"  # once, for the first


def test_a_hold_outside_the_main_thread_changes_nothing(default_sigint):
    import threading

    entered = threading.Event()
    release = threading.Event()

    def worker():
        with hold_interrupts():
            entered.set()
            release.wait(5)

    t = threading.Thread(target=worker)
    t.start()
    try:
        entered.wait(5)
        with defer_interrupts_in_jit():
            with pytest.raises(KeyboardInterrupt):  # the worker's hold does not swallow the main thread's Ctrl-C
                signal.raise_signal(signal.SIGINT)
                time.sleep(1.0)
    finally:
        release.set()
        t.join()


def test_terminated_pickles_and_names_its_signal():
    import pickle

    e = pickle.loads(pickle.dumps(Terminated(signal.SIGTERM)))
    assert isinstance(e, Terminated) and e.signum == signal.SIGTERM and str(e) == "SIGTERM"


def test_an_inactive_hold_lets_signals_through_at_once(default_terminating, default_sigint):
    """Work that cannot be saved part-way (the map's initialisation) sets `active` False for a while."""
    with defer_interrupts_in_jit():
        with hold_interrupts() as held:
            held.active = False
            with pytest.raises(Terminated):
                signal.raise_signal(signal.SIGTERM)
                time.sleep(1.0)
            held.active = True
            signal.raise_signal(signal.SIGTERM)
            time.sleep(0.1)
        assert held.signum == signal.SIGTERM


def test_a_signal_put_off_in_the_compiler_goes_to_a_hold_begun_since(default_sigint):
    """A Ctrl-C during frame 0's compilation waits for the compiler; if a hold has begun by the retry, it is held
    (the frame then ends and is saved) rather than raised inside it."""
    with defer_interrupts_in_jit():
        compiling_when_ctrl_c_arrives()()  # put off: the 50 ms retry is armed
        assert _Retry.pending
        with hold_interrupts() as held:
            time.sleep(0.3)  # the retry fires inside the hold
        assert held.signum == signal.SIGINT and not _Retry.pending
