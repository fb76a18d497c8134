"""glibc malloc settings for runs: large tensors reuse freed heap memory instead of taking fresh pages from the OS.

torch allocates CPU tensors with `malloc`. glibc serves a request above its mmap threshold (128 KiB at first,
raised as such chunks are freed, at most 32 MiB) with a fresh `mmap`, and gives the top of its heap back to the OS
once more than the trim threshold is free there. An iteration allocates and frees dozens of (samples, features)
tensors of 1-30 MiB, so by default the kernel maps, faults in and zeroes fresh pages for them at every iteration:
one minor page fault per 4 KiB, 2.1 million in an 8-frame `paper` run of the built-in `room`. `tune_malloc()`
(called by `run_slam` / `resume_slam` and `inrslam eval RUN`) sets the mmap threshold to glibc's maximum
(`MMAP_THRESHOLD`, 32 MiB), the trim threshold to `TRIM_THRESHOLD` (1 GiB) and the top pad to `TOP_PAD` (64 MiB),
so that freed blocks stay in the heap for the next iteration: the same run then takes 0.24 million faults
(docs/speed.md "Memory", `benchmarks/bench_malloc.py`). The price: up to `TRIM_THRESHOLD` of freed memory stays
with the process until it exits.

`INRSLAM_MALLOC=default` leaves glibc's settings as they are; another value than `default` / `tuned` warns and
means `tuned`. Where the C library is not glibc (macOS, musl, Windows) nothing is changed. The settings decide
where memory comes from, never what is computed: results are byte-identical either way (tested).
"""

from __future__ import annotations

import ctypes
import os
import warnings

ENV = "INRSLAM_MALLOC"
MMAP_THRESHOLD = 32 * 1024 * 1024  # bytes; glibc refuses more on 64-bit (half its 64 MiB heap size)
TRIM_THRESHOLD = 1024 * 1024 * 1024  # bytes of free heap top kept before giving memory back to the OS
TOP_PAD = 64 * 1024 * 1024  # bytes added to every heap extension
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3  # mallopt parameters (glibc malloc.h)

_state: dict | None = None


def _glibc() -> ctypes.CDLL | None:
    """The process's C library if it is glibc (it exports `gnu_get_libc_version` and `mallopt`), else None."""
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version.restype = ctypes.c_char_p
        libc.gnu_get_libc_version()
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.mallopt.restype = ctypes.c_int
        return libc
    except (OSError, AttributeError, TypeError):  # not glibc; TypeError: no process namespace (Windows)
        return None


def tune_malloc() -> dict:
    """Apply the settings once per process (later calls return the first call's record): {'tuned': bool, 'reason':
    why not (or None), and the values set in bytes}. `INRSLAM_MALLOC=default` or a C library other than glibc ->
    not tuned."""
    global _state
    if _state is not None:
        return _state
    choice = os.environ.get(ENV, "tuned").strip().lower()
    if choice not in ("default", "tuned"):
        warnings.warn(f"{ENV}={os.environ[ENV]!r} is not one of 'default', 'tuned'; using 'tuned'", stacklevel=2)
        choice = "tuned"
    libc = _glibc() if choice == "tuned" else None
    if choice == "default":
        _state = {"tuned": False, "reason": f"{ENV}=default"}
    elif libc is None:
        _state = {"tuned": False, "reason": "the C library is not glibc"}
    else:
        settings = {"mmap_threshold": (_M_MMAP_THRESHOLD, MMAP_THRESHOLD), "trim_threshold":
                    (_M_TRIM_THRESHOLD, TRIM_THRESHOLD), "top_pad": (_M_TOP_PAD, TOP_PAD)}
        applied = {name: value for name, (param, value) in settings.items() if libc.mallopt(param, value) == 1}
        _state = {"tuned": bool(applied), "reason": None if applied else "mallopt refused every setting", **applied}
    return _state


def malloc_state() -> dict:
    """The record of `tune_malloc` if it ran in this process, else {'tuned': False, 'reason': 'not applied'}."""
    return _state if _state is not None else {"tuned": False, "reason": "not applied"}
