"""Atomic writers (`inrslam.io.atomic`), folder locks (`inrslam.io.lock`) and TUM trajectory files
(`inrslam.io.trajectory`)."""

from __future__ import annotations

import json
import math
import os
import socket
import stat
import subprocess
import sys
import threading

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import inrslam.io.atomic as atomic
from inrslam.errors import DataError, InrslamWarning, RunError
from inrslam.io.atomic import append_jsonl, atomic_path, write_json, write_text
from inrslam.io.lock import LockHeld, acquire
from inrslam.io.rundir import RunDir
from inrslam.io.trajectory import quat_rotation, read_tum, write_tum


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    try:
        yield 0o022
    finally:
        os.umask(old)


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
@pytest.mark.parametrize("mask", [0o022, 0o002, 0o077], ids=oct)
def test_atomic_files_get_the_umask_permissions(tmp_path, mask):
    old = os.umask(mask)
    try:
        write_text(tmp_path / "a.txt", "hello")
        write_json(tmp_path / "b.json", {"x": 1})
        (tmp_path / "c.txt").write_text("plain open()")  # what a non-atomic writer would give
        assert _current_umask() == mask  # reading the umask restores it
    finally:
        os.umask(old)
    for name in ("a.txt", "b.json", "c.txt"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o666 & ~mask, name


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
def test_overwrite_gets_umask_permissions(tmp_path, umask_022):
    p = tmp_path / "a.txt"
    write_text(p, "one")
    write_text(p, "two")
    assert p.read_text() == "two" and stat.S_IMODE(p.stat().st_mode) == 0o644


def test_failure_inside_atomic_path_keeps_the_old_file(tmp_path):
    p = tmp_path / "metrics.json"
    write_text(p, "old")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_path(p) as tmp:
            assert tmp.parent == p.parent and tmp.name.endswith(".json") and tmp != p
            tmp.write_text("half-written")
            raise RuntimeError("boom")
    assert p.read_text() == "old"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["metrics.json"]  # no temporary file left behind


def test_atomic_path_creates_parent_folders(tmp_path):
    p = tmp_path / "a" / "b" / "c.txt"
    write_text(p, "x")
    assert p.read_text() == "x" and sorted(x.name for x in p.parent.iterdir()) == ["c.txt"]


def test_json_writers_turn_non_finite_into_null(tmp_path):
    p = tmp_path / "m.json"
    write_json(p, {"a": float("nan"), "b": [1.5, float("inf"), (float("-inf"), 2)], "c": {"d": math.nan}, "e": "s"})
    assert json.loads(p.read_text()) == {"a": None, "b": [1.5, None, [None, 2]], "c": {"d": None}, "e": "s"}
    assert "NaN" not in p.read_text() and "Infinity" not in p.read_text()
    log = tmp_path / "log.jsonl"
    append_jsonl(log, {"frame": 0, "loss": float("nan")})
    append_jsonl(log, {"frame": 1, "loss": 0.25, "v": [float("inf")]})
    lines = log.read_text().splitlines()
    assert [json.loads(x) for x in lines] == [{"frame": 0, "loss": None}, {"frame": 1, "loss": 0.25, "v": [None]}]


def test_a_refused_log_append_is_cut_back_to_whole_lines(tmp_path):
    """A line the file-size limit refuses half-way (as a full disk would) leaves the log as it was, whole lines only.
    In a child process: the limit applies to every write of the process."""
    log = tmp_path / "log.jsonl"
    append_jsonl(log, {"frame": 0})
    before = log.read_bytes()
    child = f"""
import errno, resource, signal, sys
from inrslam.io.atomic import append_jsonl
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of the signal's default, ending the process
resource.setrlimit(resource.RLIMIT_FSIZE, ({len(before) + 10}, resource.RLIM_INFINITY))
try:
    append_jsonl({str(log)!r}, {{"frame": 1, "note": "x" * 100}})
except OSError as e:
    sys.exit(0 if e.errno == errno.EFBIG else 3)
sys.exit(4)
"""
    done = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert log.read_bytes() == before  # 10 bytes of the line had gone in before the refusal: cut back
    append_jsonl(log, {"frame": 2})
    assert [json.loads(x)["frame"] for x in log.read_text().splitlines()] == [0, 2]


def test_atomic_writes_flush_the_folder_after_the_rename(tmp_path, monkeypatch):
    synced = []
    real = atomic.os.fsync

    def fsync(fd):
        synced.append(stat.S_ISDIR(os.fstat(fd).st_mode))
        real(fd)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    write_text(tmp_path / "a.txt", "x")
    assert synced == [False, True]  # the file's data, then the folder's entry
    synced.clear()
    with atomic.atomic_folder(tmp_path / "scene") as tmp:
        (tmp / "f").write_text("y")
    assert synced == [True] and (tmp_path / "scene" / "f").read_text() == "y"


def test_a_folder_lock_names_its_holder_and_frees_when_closed(tmp_path):
    path = tmp_path / ".run.lock"
    held = acquire(path)
    try:
        with pytest.raises(LockHeld) as caught:  # another open file: as another process would
            acquire(path)
        assert caught.value.holder == f"pid {os.getpid()} on {socket.gethostname()}"
    finally:
        held.close()
    acquire(path).close()  # the file left behind does not block anyone


def test_a_file_system_without_locks_goes_on_unlocked(tmp_path, monkeypatch):
    import errno
    import fcntl

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with pytest.warns(InrslamWarning, match=r"this file system takes no locks \(No locks available\); going on"):
        first, second = acquire(tmp_path / ".lock"), acquire(tmp_path / ".lock")  # neither refused
    first.close()
    second.close()


def test_a_run_folder_is_held_by_one_process_at_a_time(tmp_path):
    rd = RunDir(tmp_path / "run")
    with rd.lock():
        assert (rd.root / RunDir.LOCK_FILE).is_file()
        with pytest.raises(LockHeld):  # what another process meets: the kernel's lock is taken
            acquire(rd.root / RunDir.LOCK_FILE)
        with RunDir(rd.root).lock():  # the thread holding it may enter again (a sweep worker, then the runner)
            pass
        errors = []

        def other_thread():
            try:
                with rd.lock():
                    pass
            except RunError as e:
                errors.append(str(e))

        t = threading.Thread(target=other_thread)
        t.start()
        t.join()
        assert len(errors) == 1
        assert errors[0].startswith(f"{rd.root}: another inrslam process is running in this run folder (pid ")
    held = acquire(rd.root / RunDir.LOCK_FILE)  # as another process would hold it
    try:
        with pytest.raises(RunError, match=r"another inrslam process is running in this run folder"):
            with rd.lock():
                pass
    finally:
        held.close()
    with rd.lock():  # free again
        pass
    assert not rd.holds_run() and not RunDir(rd.root).remove_stale_temporaries()  # the lock is not a run's file


def _poses(n: int = 6) -> np.ndarray:
    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 1.0, (n, 3))).as_matrix()
    T[:, :3, 3] = rng.normal(0, 2.0, (n, 3))
    return T


def test_tum_round_trip_skips_non_finite_poses(tmp_path):
    ts = np.arange(6) * 0.033 + 1305031102.175304
    T = _poses()
    T[2, 0, 3] = np.nan  # lost frame: not written
    p = tmp_path / "traj.txt"
    write_tum(p, ts, T, header="estimated c2w")
    text = p.read_text().splitlines()
    assert text[0] == "# estimated c2w" and text[1].startswith("# timestamp")
    ts2, T2 = read_tum(p)
    keep = np.array([0, 1, 3, 4, 5])
    np.testing.assert_allclose(ts2, ts[keep], atol=1e-6)
    np.testing.assert_allclose(T2, T[keep], atol=1e-8)
    np.testing.assert_array_equal(T2[:, 3], np.tile([0, 0, 0, 1.0], (5, 1)))


@pytest.mark.parametrize("body, match", [
    ("0 1 2 3 0 0 0 1\n1 1 2 3 0 0 1\n", r"bad\.txt:3: expected 8 values .* got 7"),
    ("0 1 2 3 0 0 0 1 9\n", r"bad\.txt:2: expected 8 values .* got 9"),
    ("0 1 2 x 0 0 0 1\n", r"bad\.txt:2: non-numeric"),
    ("0 1 2 nan 0 0 0 1\n", r"bad\.txt:2: non-finite"),
    ("0 1 2 3 0 0 0 0\n", r"bad\.txt:2: zero quaternion"),
    ("\n", r"bad\.txt: no poses"),
])
def test_read_tum_errors_name_file_and_line(tmp_path, body, match):
    p = tmp_path / "bad.txt"
    p.write_text("# timestamp tx ty tz qx qy qz qw\n" + body)
    with pytest.raises(DataError, match=match):
        read_tum(p)


def test_quat_rotation_is_q_over_its_norm_bit_for_bit_and_survives_overflow():
    """Ordinary quaternions give exactly scipy's rotation of q / |q| (the metrics of earlier runs stay the same bits);
    only a norm that overflows is scaled first."""
    rng = np.random.default_rng()
    for q in np.round(rng.normal(size=(500, 4)), 4):
        assert np.array_equal(quat_rotation(q, "f"), Rotation.from_quat(q / np.linalg.norm(q)).as_matrix())
    half = np.sqrt(0.5)
    np.testing.assert_allclose(quat_rotation(np.array([0.0, 0.0, 1e300, 1e300]), "f"),
                               Rotation.from_quat([0, 0, half, half]).as_matrix(), atol=1e-15)
    with pytest.raises(DataError, match=r"^f:3: zero quaternion"):
        quat_rotation(np.array([1e-10, 0.0, 0.0, 0.0]), "f:3")


def test_read_tum_missing_file_and_commas(tmp_path):
    with pytest.raises(DataError, match="not found"):
        read_tum(tmp_path / "nope.txt")
    p = tmp_path / "commas.txt"
    p.write_text("0.5,1,2,3,0,0,0,2\n")  # comma separated, unnormalised quaternion
    ts, T = read_tum(p)
    assert ts.tolist() == [0.5] and np.allclose(T[0], np.array([[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3],
                                                                [0, 0, 0, 1.0]]))


def test_run_dir_names_every_path_and_clears_only_its_own_files(tmp_path):
    from inrslam.io.rundir import RunDir

    rd = RunDir(tmp_path / "run")
    assert rd.checkpoint == tmp_path / "run" / "checkpoints" / "latest.pt"
    assert rd.mesh_at(7) == tmp_path / "run" / "meshes" / "mesh_000007.ply"
    with pytest.raises(KeyError, match="no run-directory entry 'metric'"):
        rd.path("metric")
    assert not rd.holds_run() and not rd.is_complete() and not rd.has_checkpoint()
    for key in RunDir.FILES:
        p = rd.path(key)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("{}")
    rd.meshes.mkdir()
    rd.mesh_at(3).write_text("ply")
    rd.bench.write_text("{}")  # the sweep's own file survives a clear
    (rd.root / "notes.txt").write_text("mine")
    assert rd.holds_run() and rd.has_checkpoint() and not rd.is_complete()  # run_info has no status
    rd.clear()
    assert sorted(p.name for p in rd.root.iterdir()) == ["bench.json", "notes.txt"]


def test_run_dir_complete_needs_a_readable_metrics_file(tmp_path):
    from inrslam.io.rundir import RunDir

    rd = RunDir(tmp_path)
    rd.run_info.write_text('{"status": "complete"}')
    rd.metrics.write_text('{"ate_rmse_m": 0.0')  # truncated
    assert not rd.is_complete() and rd.read_metrics() is None
    rd.write_metrics({"ate_rmse_m": 0.01})
    assert rd.is_complete()
    assert rd.update_metrics({"psnr_db": 30.0}) == {"ate_rmse_m": 0.01, "psnr_db": 30.0}
    assert rd.read_metrics() == {"ate_rmse_m": 0.01, "psnr_db": 30.0}
