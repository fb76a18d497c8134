"""The run-directory contract: every file and folder a run writes, in one place (layout in docs/design.md).

Writers and readers (the SLAM system, the runner, evaluation, the sweep worker, the leaderboard, the plots, the CLI)
name paths only through `RunDir`, so the layout is defined once. Writes are atomic (`inrslam.io.atomic`).
"""

from __future__ import annotations

import json
import os
import shutil
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from inrslam.errors import RunError
from inrslam.io.atomic import temporary_files, write_json
from inrslam.io.lock import LockHeld, acquire

_HELD: dict[str, int] = {}  # run folders this process holds (`RunDir.lock`): resolved path -> holding thread


def read_json(path: str | os.PathLike) -> Any:
    """Parsed JSON of the file at `path`, or None when it is missing or unreadable (runs and sweeps alike)."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


class RunDir:
    """A run directory at `root`.

    Files: config.yaml, run_info.json, log.jsonl, trajectory.txt, trajectory_gt.txt, trajectory_relative.txt,
    keyframes.json, trajectory.png, mesh.ply, mesh.png, metrics.json, checkpoints/latest.pt; sweep runs add
    bench.json and error.txt. Folders: meshes/ (intermediate meshes), renders/ (held-out frames), tensorboard/.
    `.run.lock` names the process running in the folder (`lock`).
    """

    LOCK_FILE = ".run.lock"

    FILES = {
        "config": "config.yaml",
        "run_info": "run_info.json",
        "log": "log.jsonl",
        "trajectory": "trajectory.txt",
        "trajectory_gt": "trajectory_gt.txt",
        "trajectory_relative": "trajectory_relative.txt",
        "keyframes": "keyframes.json",
        "trajectory_plot": "trajectory.png",
        "mesh": "mesh.ply",
        "mesh_thumbnail": "mesh.png",
        "metrics": "metrics.json",
        "checkpoint": "checkpoints/latest.pt",
    }
    SWEEP_FILES = {"bench": "bench.json", "error": "error.txt"}  # written by the sweep worker around a run
    DIRS = {"meshes": "meshes", "tensorboard": "tensorboard", "checkpoints": "checkpoints", "renders": "renders"}

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"RunDir({str(self.root)!r})"

    def __fspath__(self) -> str:
        return str(self.root)

    # -- paths ---------------------------------------------------------------------------------------------------
    def path(self, key: str) -> Path:
        """Path of a file (`FILES` key) or folder (`DIRS` key)."""
        for table in (self.FILES, self.SWEEP_FILES, self.DIRS):
            if key in table:
                return self.root / table[key]
        files = ", ".join([*self.FILES, *self.SWEEP_FILES])
        raise KeyError(f"no run-directory entry {key!r} (files: {files}; folders: {', '.join(self.DIRS)})")

    config = property(lambda self: self.path("config"))
    run_info = property(lambda self: self.path("run_info"))
    log = property(lambda self: self.path("log"))
    trajectory = property(lambda self: self.path("trajectory"))
    trajectory_gt = property(lambda self: self.path("trajectory_gt"))
    trajectory_relative = property(lambda self: self.path("trajectory_relative"))
    keyframes = property(lambda self: self.path("keyframes"))
    trajectory_plot = property(lambda self: self.path("trajectory_plot"))
    mesh = property(lambda self: self.path("mesh"))
    mesh_thumbnail = property(lambda self: self.path("mesh_thumbnail"))
    metrics = property(lambda self: self.path("metrics"))
    checkpoint = property(lambda self: self.path("checkpoint"))
    bench = property(lambda self: self.path("bench"))
    error = property(lambda self: self.path("error"))
    meshes = property(lambda self: self.path("meshes"))
    checkpoints = property(lambda self: self.path("checkpoints"))
    tensorboard = property(lambda self: self.path("tensorboard"))

    renders = property(lambda self: self.path("renders"))

    def render_at(self, frame: int) -> Path:
        """renders/frame_NNNNNN.png: held-out frame `frame`, observed | rendered colour | depth | depth error."""
        return self.renders / f"frame_{frame:06d}.png"

    def mesh_at(self, frame: int) -> Path:
        """Intermediate mesh after `frame` (slam.mesh_every)."""
        return self.meshes / f"mesh_{frame:06d}.ply"

    # -- state -----------------------------------------------------------------------------------------------------
    def holds_run(self) -> bool:
        """A run was started here (its resolved config.yaml exists)."""
        return self.config.is_file()

    def is_complete(self) -> bool:
        """run_info.json says status complete and metrics.json is a readable JSON object."""
        info = self.read_run_info()
        return info is not None and info.get("status") == "complete" and self.read_metrics() is not None

    def has_checkpoint(self) -> bool:
        """A partial run can be resumed: config.yaml and checkpoints/latest.pt exist."""
        return self.checkpoint.is_file() and self.config.is_file()

    def remove_checkpoints(self) -> int:
        """Delete checkpoints/ (a finished run that need not be resumed or re-rendered); returns the bytes freed."""
        folder = self.checkpoints
        if not folder.is_dir():
            return 0
        size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
        shutil.rmtree(folder)
        return size

    def clear(self) -> None:
        """Remove every file and folder a SLAM run writes (the sweep's bench.json / error.txt and any other file in
        the folder are left alone)."""
        for name in self.FILES.values():
            (self.root / name).unlink(missing_ok=True)
        for name in self.DIRS.values():
            shutil.rmtree(self.root / name, ignore_errors=True)

    @contextmanager
    def lock(self) -> Iterator[None]:
        """Hold the folder's lock for a block: one process at a time runs, resumes or overwrites this run (two would
        write the same files, and each would delete the other's half-written ones). RunError naming the holder when
        another process (or another thread of this one) has it; the thread holding it may enter again (a sweep
        worker, then the runner inside it). The kernel frees it when its holder ends, however it ends."""
        self.root.mkdir(parents=True, exist_ok=True)
        key = str(self.root.resolve())
        if _HELD.get(key) == threading.get_ident():
            yield
            return
        try:
            held = acquire(self.root / self.LOCK_FILE)
        except LockHeld as e:
            raise RunError(f"{self.root}: another inrslam process is running in this run folder ({e.holder}); wait "
                           "for it to end, or stop it and continue with --resume") from None
        _HELD[key] = threading.get_ident()
        try:
            yield
        finally:
            _HELD.pop(key, None)
            held.close()

    # -- JSON files --------------------------------------------------------------------------------------------------
    def read_json(self, key: str) -> Any:
        """Parsed JSON of a file, or None when missing or unreadable."""
        return read_json(self.path(key))

    def corrupt_files(self, keys: tuple[str, ...] = ("run_info", "metrics")) -> list[str]:
        """File names among `keys` that exist but do not hold a JSON object (truncated, edited, not JSON)."""
        bad = []
        for key in keys:
            path = self.path(key)
            if path.is_file() and not isinstance(self.read_json(key), dict):
                bad.append(path.name)
        return bad

    def read_metrics(self) -> dict | None:
        m = self.read_json("metrics")
        return m if isinstance(m, dict) else None

    def read_run_info(self) -> dict | None:
        info = self.read_json("run_info")
        return info if isinstance(info, dict) else None

    def write_metrics(self, metrics: dict) -> None:
        """Replace metrics.json (atomically)."""
        write_json(self.metrics, metrics)

    def update_metrics(self, new: dict) -> dict:
        """Merge `new` into metrics.json (created if missing) and return the merged dict."""
        merged = {**(self.read_metrics() or {}), **new}
        self.write_metrics(merged)
        return merged

    def remove_stale_temporaries(self) -> list[Path]:
        """Delete the temporary files of atomic writes a killed process left in the run folder, checkpoints/,
        meshes/ and renders/ (`inrslam.io.atomic.temporary_files`); returns what was removed."""
        folders = (self.root, self.checkpoints, self.meshes, self.renders)
        gone = [p for folder in folders for p in temporary_files(folder)]
        for p in gone:
            p.unlink(missing_ok=True)
        return gone
