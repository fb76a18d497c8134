"""Folder locks: one process at a time writes a run folder or a sweep folder.

An exclusive, non-blocking `flock` on a small file in the folder, which names its holder ("pid N on HOST"). The
kernel releases it when the holding file is closed or its process ends, however it ends (a SIGKILL too), so a
lock file left behind never blocks anyone. Where `fcntl` is missing (Windows) no lock is taken.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import TextIO


class LockHeld(Exception):
    """Another open file (another process) holds the lock; `holder` is what it wrote ("pid N on HOST")."""

    def __init__(self, path: Path, holder: str):
        super().__init__(f"{path} is held by {holder}")
        self.path, self.holder = path, holder


def acquire(path: str | os.PathLike) -> TextIO:
    """Take the lock on `path` (created if missing) and write this process into it; the lock lasts until the
    returned file is closed. Raises `LockHeld` when another open file holds it."""
    path = Path(path)
    f = open(path, "a+", encoding="utf-8")
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        return f
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.seek(0)
        holder = f.read().strip() or "another process"
        f.close()
        raise LockHeld(path, holder) from None
    f.seek(0)
    f.truncate()
    f.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
    f.flush()
    return f
