"""Waiting in tests for something another thread or process does (no sleeps of a guessed length)."""

from __future__ import annotations

import time
from typing import Callable


def wait_for(check: Callable[[], object], timeout: float = 5.0, interval: float = 0.01) -> bool:
    """Poll `check()` every `interval` seconds until it is true or `timeout` seconds have passed; its last value's
    truth (a check that turns true at the deadline still counts)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if check():
            return True
        time.sleep(interval)
    return bool(check())
