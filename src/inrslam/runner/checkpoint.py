"""Checkpoint files: a `SlamState` plus the writer's process bookkeeping, with checksums of every array.

A checkpoint is written atomically (the previous one survives a crash or a full disk) and verified when loaded:
a truncated, zero-byte or foreign checkpoint, or one with a bit flipped in any array, is a one-line `RunError`,
never a traceback or a run that silently carries NaNs on (the few Python scalars and lists beside the arrays, loss
histories and event records, carry no checksum). A checkpoint is a pickle (`torch.load(weights_only=False)`): load
only run directories you trust, as with any pickle.
"""

from __future__ import annotations

import errno
import shutil
import zlib
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch

from inrslam.errors import RunError
from inrslam.io.atomic import atomic_path

CHECKSUMS = "checksums"  # key of the {array path: crc32} table inside a checkpoint
IDENTITY = "run"  # key of what identifies the run that wrote it


def _arrays(obj: Any, prefix: str = "") -> Iterator[tuple[str, np.ndarray]]:
    """(path, raw bytes as a uint8 array) of every tensor / numpy array nested in dicts, lists and tuples."""
    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous().reshape(-1)
        yield prefix, (t.view(torch.uint8).numpy() if t.numel() else np.zeros(0, np.uint8))
    elif isinstance(obj, np.ndarray):
        yield prefix, np.ascontiguousarray(obj).reshape(-1).view(np.uint8)
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _arrays(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _arrays(v, f"{prefix}[{i}]")


def checksums(state: dict) -> dict[str, int]:
    """{path: crc32} of every array in `state` (the checksum table itself excluded)."""
    return {p: zlib.crc32(a) for p, a in _arrays({k: v for k, v in state.items() if k != CHECKSUMS})}


def save_checkpoint(path: Path, state: dict) -> None:
    """Write `state` (with its checksum table added) atomically to `path`.

    Raises RunError on a full disk or an unwritable folder, naming the path, the checkpoint's size and the space
    left; the previous checkpoint at `path` is kept.
    """
    state = {**state, CHECKSUMS: checksums(state)}
    try:
        with atomic_path(path) as tmp:
            torch.save(state, tmp)
    except (OSError, RuntimeError) as e:
        size_mb = sum(a.nbytes for _, a in _arrays(state)) / 2**20
        free_mb = _free_mb(path.parent)
        full = (isinstance(e, OSError) and e.errno == errno.ENOSPC) or (free_mb is not None and free_mb < size_mb)
        if not full and ("unexpected pos" in str(e) or "file write failed" in str(e)):  # torch's words for any
            raise RunError(f"{path}: writing the checkpoint failed (~{size_mb:.0f} MB to write, "  # failed write
                           f"{free_mb if free_mb is not None else '?'} MB free: a file-size limit or quota?); the "
                           f"previous checkpoint is kept: continue with --resume {path.parent.parent}") from None
        if full:
            raise RunError(f"{path}: no space left on device (a checkpoint needs ~{size_mb:.0f} MB, "
                           f"{free_mb if free_mb is not None else '?'} MB free); the previous checkpoint is kept: "
                           f"free space, then continue with --resume {path.parent.parent}") from None
        if isinstance(e, OSError):
            raise RunError(f"{path}: cannot write the checkpoint ({e.strerror or e})") from None
        raise


def _free_mb(folder: Path) -> int | None:
    try:
        return int(shutil.disk_usage(folder).free / 2**20)
    except OSError:
        return None


def load_checkpoint(path: Path, identity: dict | None = None) -> dict:
    """Read and verify a checkpoint written by `save_checkpoint`.

    Args:
        identity: what the resuming run is (frames, encoding, ...); a checkpoint written by a different run fails.
    Raises:
        RunError naming the file and what to do when it is missing, unreadable, corrupt or another run's.
    """
    restart = "start the run again with --overwrite"
    if not path.is_file():
        raise RunError(f"{path}: no checkpoint to resume from (the run stopped before its first checkpoint): {restart}")
    if path.stat().st_size == 0:
        raise RunError(f"{path}: the checkpoint is empty (0 bytes): {restart}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # truncated zip, bad pickle, ...: all mean "unreadable"
        reason = str(e).splitlines()[0][:120] if str(e) else type(e).__name__
        raise RunError(f"{path}: unreadable checkpoint, truncated or corrupt ({reason}): {restart}") from None
    if not isinstance(state, dict) or "next_frame" not in state:
        raise RunError(f"{path}: not an inrslam checkpoint: {restart}")
    saved = state.get(CHECKSUMS)
    if saved is not None:  # checkpoints from before checksums were added have none
        now = checksums(state)
        bad = sorted(k for k in set(saved) | set(now) if saved.get(k) != now.get(k))
        if bad:
            raise RunError(f"{path}: corrupt checkpoint (checksum mismatch in {bad[0]}"
                           f"{f' and {len(bad) - 1} more' if len(bad) > 1 else ''}): {restart}")
    mine = state.get(IDENTITY)
    if identity is not None and mine is not None:
        diff = [f"{k} {mine.get(k)!r} in the checkpoint, {v!r} in config.yaml"
                for k, v in identity.items() if mine.get(k) != v]
        if diff:
            raise RunError(f"{path}: the checkpoint belongs to another run ({'; '.join(diff)}): resume the run "
                           f"directory it came from, or {restart}")
    return state
