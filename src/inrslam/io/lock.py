"""Folder locks: one process at a time writes a run folder or a sweep folder.

An exclusive, non-blocking `flock` on a small file in the folder, which names its holder ("pid N on HOST"). The
kernel releases it when the holding file is closed or its process ends, however it ends (a SIGKILL too), so a
lock file left behind never blocks anyone. Where `fcntl` is missing (Windows) or the file system has no locks (some
network mounts: ENOLCK; a warning says so) no lock is taken. Some cluster file systems take locks per node only
(Lustre mounted with `localflock`, NFS with `nolock`): there two nodes can both hold one.
"""

from __future__ import annotations

import errno
import os
import socket
import warnings
from pathlib import Path
from typing import TextIO

from inrslam.errors import InrslamWarning


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
        if _lock(f, path):
            f.seek(0)
            f.truncate()
            f.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
            f.flush()
    except BaseException:
        f.close()
        raise
    return f


def _lock(f: TextIO, path: Path) -> bool:
    """flock `f`; False where no lock can be taken (no fcntl, or a file system without locks: a warning)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        return False
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError as e:
        if e.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):  # e.g. ENOLCK: a file system without
            warnings.warn(f"{path.parent}: this file system takes no locks ({e.strerror}); going on without the "
                          "one-process-per-folder lock", InrslamWarning, stacklevel=3)
            return False
        f.seek(0)
        raise LockHeld(path, f.read().strip() or "another process") from None
