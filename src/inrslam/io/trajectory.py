"""TUM trajectory files: one line per pose, `timestamp tx ty tz qx qy qz qw` (scalar-last quaternion).

Poses are camera-to-world. Lines starting with '#' and blank lines are ignored.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from inrslam.errors import DataError
from inrslam.io.atomic import write_text


def quat_rotation(q: np.ndarray, where: str) -> np.ndarray:
    """(3, 3) rotation of a finite quaternion (qx, qy, qz, qw) of any length, or a `DataError` at `where` for a zero
    one (length below 1e-9). q / |q| as always where |q| is finite; components so large (1e300) that |q| overflows are
    scaled by the largest first. Example: (0, 0, 0, 2) -> identity."""
    q = np.asarray(q, dtype=np.float64)
    with np.errstate(over="ignore"):
        n = float(np.linalg.norm(q))
    if not np.isfinite(n):
        u = q / float(np.abs(q).max())
        q, n = u, float(np.linalg.norm(u))
    if not n >= 1e-9:
        raise DataError(f"{where}: zero quaternion (expected qx qy qz qw of a rotation)")
    return Rotation.from_quat(q / n).as_matrix()  # scipy: scalar-last (x, y, z, w)


def poses_to_tum_lines(timestamps: np.ndarray, c2w: np.ndarray) -> list[str]:
    """(N,) seconds and (N, 4, 4) c2w -> TUM lines; non-finite poses are skipped."""
    lines = []
    for ts, T in zip(timestamps, c2w):
        if not np.all(np.isfinite(T)):
            continue
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
        t = T[:3, 3]
        lines.append(f"{ts:.6f} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    return lines


def write_tum(path: str | os.PathLike, timestamps: np.ndarray, c2w: np.ndarray, header: str | None = None) -> None:
    """Atomically write a TUM trajectory file."""
    lines = ([f"# {header}"] if header else []) + ["# timestamp tx ty tz qx qy qz qw"]
    lines += poses_to_tum_lines(np.asarray(timestamps, dtype=np.float64), np.asarray(c2w, dtype=np.float64))
    write_text(path, "\n".join(lines) + "\n")


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory. Returns (N,) timestamps and (N, 4, 4) c2w (float64).

    Raises DataError naming the file and line for malformed lines.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: trajectory file not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read the trajectory file ({e})") from None
    ts, poses = [], []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise DataError(f"{path}:{lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            vals = np.array([float(p) for p in parts])
        except ValueError:
            raise DataError(f"{path}:{lineno}: non-numeric value in {s!r}") from None
        if not np.all(np.isfinite(vals)):
            raise DataError(f"{path}:{lineno}: non-finite value in {s!r}")
        T = np.eye(4)
        T[:3, :3] = quat_rotation(vals[4:8], f"{path}:{lineno}")
        T[:3, 3] = vals[1:4]
        ts.append(vals[0])
        poses.append(T)
    if not poses:
        raise DataError(f"{path}: no poses found")
    return np.array(ts), np.stack(poses)
