"""Text formats of ground-truth poses and calibration (parsing only; no conventions applied here).

Non-finite values (nan, inf) are allowed in poses: `check_pose` turns such a pose into (all-NaN, invalid).
Malformed files (wrong number of lines or values, non-numeric text) raise `DataError` naming file and line.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from inrslam.data.frame import NAN_POSE
from inrslam.errors import DataError


def read_lines(path: Path, what: str) -> list[tuple[int, str]]:
    """Non-blank, non-comment lines as (1-based line number, text)."""
    if not path.is_file():
        raise DataError(f"{path}: {what} not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read {what} ({e})") from None
    out = []
    for n, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append((n, s))
    return out


def parse_floats(path: Path, lineno: int, text: str, expected: int, what: str) -> np.ndarray:
    parts = text.replace(",", " ").split()
    if len(parts) != expected:
        raise DataError(f"{path}:{lineno}: expected {expected} values ({what}), got {len(parts)}: {text[:80]!r}")
    try:
        return np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise DataError(f"{path}:{lineno}: non-numeric value in {text[:80]!r} (expected {what})") from None


def read_matrix(path: str | os.PathLike, rows: int, cols: int, what: str = "matrix") -> np.ndarray:
    """Read a whitespace-separated `rows` x `cols` matrix file (one row per line) as float64."""
    path = Path(path)
    lines = read_lines(path, what)
    if len(lines) != rows:
        raise DataError(f"{path}: expected {rows} lines of {cols} values ({what}), got {len(lines)} lines")
    return np.stack([parse_floats(path, n, s, cols, what) for n, s in lines])


def read_pose_matrix(path: str | os.PathLike) -> np.ndarray:
    """One 4x4 pose written as 4 lines of 4 values (7-Scenes, ScanNet). Non-finite entries are kept."""
    return read_matrix(path, 4, 4, "4x4 camera-to-world pose, 4 lines of 4 values")


def read_pose_rows(path: str | os.PathLike) -> tuple[np.ndarray, list[int]]:
    """One pose per line, 16 values row-major (Replica `traj.txt`) -> (N, 4, 4) poses and each one's line number."""
    path = Path(path)
    lines = read_lines(path, "trajectory file")
    if not lines:
        raise DataError(f"{path}: no poses found (expected one line of 16 values per frame)")
    poses = np.stack([parse_floats(path, n, s, 16, "16 values of a row-major 4x4 pose").reshape(4, 4)
                      for n, s in lines])
    return poses, [n for n, _ in lines]


def read_pose_blocks(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """4 lines of 4 values per pose (NeuralRGBD `poses.txt`).

    Returns (N, 4, 4) poses, (N,) bool "a line contained 'nan'", and the first line number of each pose."""
    path = Path(path)
    lines = read_lines(path, "pose file")
    if not lines or len(lines) % 4:
        raise DataError(f"{path}: expected 4 lines of 4 values per pose, got {len(lines)} lines (not a multiple of 4)")
    poses, nan, first = [], [], []
    for k in range(0, len(lines), 4):
        block = lines[k : k + 4]
        poses.append(np.stack([parse_floats(path, n, s, 4, "one row of a 4x4 pose") for n, s in block]))
        nan.append(any("nan" in s.lower() for _, s in block))
        first.append(block[0][0])
    return np.stack(poses), np.array(nan), first


def check_pose(T: np.ndarray, where: str) -> tuple[np.ndarray, bool]:
    """Validate a 4x4 pose: non-finite -> (NaN pose, False); finite must have bottom row [0, 0, 0, 1].

    Args:
        T: (4, 4) candidate camera-to-world.
        where: file (and line) for the error message.
    """
    T = np.asarray(T, dtype=np.float64)
    if not np.all(np.isfinite(T)):
        return NAN_POSE.copy(), False
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-4):
        raise DataError(f"{where}: pose bottom row is {T[3].tolist()}, expected [0, 0, 0, 1] (a rigid 4x4 transform)")
    return T, True
