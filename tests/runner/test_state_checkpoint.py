"""The SLAM loop's state, the loop without I/O, and verified checkpoints (runner/checkpoint.py)."""

from __future__ import annotations

import json
import os
import signal
import struct

import numpy as np
import pytest
import torch

from inrslam.config import load_config
from inrslam.datasets import open_dataset
from inrslam.errors import InrslamError, RunError
from inrslam.interrupts import Terminated, defer_interrupts_in_jit
from inrslam.io.rundir import RunDir
from inrslam.runner import resume_slam, run_slam
from inrslam.runner.checkpoint import load_checkpoint, save_checkpoint
from inrslam.slam.system import SlamSystem

TINY = ["data.max_frames=4", "slam.init_iters=10", "slam.track_iters=3", "slam.map_iters=2", "slam.map_every=2",
        "slam.checkpoint_every=2", "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false"]


def tiny_cfg(extra=()):
    return load_config(preset="quick", overrides=TINY + list(extra))


def test_the_loop_writes_nothing_and_returns_its_records(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = tiny_cfg()
    system = SlamSystem(cfg, open_dataset(cfg.data))
    kinds = [[r["type"] for r in system.process(i)] for i in range(len(system.dataset))]
    assert kinds == [["init"], ["track"], ["track", "map"], ["track"]]
    assert list(tmp_path.iterdir()) == []  # nothing written anywhere the loop could reach relative to the cwd
    res = system.result()
    assert res.est.shape == (4, 4, 4) and np.isfinite(res.est).all()
    assert res.keyframes == [0, 2] and res.metrics["frames"] == 4
    with pytest.raises(ValueError, match="out of order"):
        system.process(1)


def test_state_round_trip_restores_every_field():
    cfg = tiny_cfg()
    a = SlamSystem(cfg, open_dataset(cfg.data))
    for i in range(3):
        a.process(i)
    saved = a.state.state_dict()
    b = SlamSystem(cfg, open_dataset(cfg.data))
    b.state.load_state_dict(saved)
    assert b.state.next_frame == 3 and b.state.store.frame_ids == [0, 2]
    assert torch.equal(torch.nan_to_num(a.est), torch.nan_to_num(b.est))
    for (ka, va), (kb, vb) in zip(a.model.state_dict().items(), b.model.state_dict().items()):
        assert ka == kb and torch.equal(va, vb)
    assert torch.equal(a.generator.get_state(), b.generator.get_state())
    # loop-closure bookkeeping (plain lists / dicts) comes back as equal copies, not shared objects
    a.state.loops.append({"candidate": 0, "frame": 2, "T": np.eye(4).tolist()})
    a.state.loop_stats["candidates"] = 3
    a.state.kf_odometry[2] = np.eye(4).tolist()
    c = SlamSystem(cfg, open_dataset(cfg.data))
    c.state.load_state_dict(a.state.state_dict())
    assert c.state.loops == a.state.loops and c.state.loop_stats == {"candidates": 3}
    assert c.state.loop_stats is not a.state.loop_stats and c.state.loops is not a.state.loops
    assert c.state.kf_odometry == {2: np.eye(4).tolist()} and c.state.kf_odometry is not a.state.kf_odometry
    # both continue identically from there
    assert [r["loss"] for r in a.process(3)] == [r["loss"] for r in b.process(3)]
    with pytest.raises(KeyError, match="lacks est"):
        b.state.load_state_dict({k: v for k, v in saved.items() if k != "est"})


def _state():
    return {"next_frame": 3, "est": torch.full((5, 4, 4), 1.2345), "gt": np.eye(4)[None].repeat(5, 0),
            "model": {"w": torch.arange(8, dtype=torch.float64)}, "events": [{"frame": 1, "event": "x"}]}


def test_checkpoint_round_trip_and_bit_flip_is_caught(tmp_path):
    path = tmp_path / "checkpoints" / "latest.pt"
    save_checkpoint(path, _state())
    st = load_checkpoint(path)
    assert st["next_frame"] == 3 and torch.equal(st["est"], _state()["est"])
    raw = bytearray(path.read_bytes())
    at = raw.find(struct.pack("<f", 1.2345))
    assert at > 0
    raw[at] ^= 0x10  # one flipped bit inside the stored tensor
    path.write_bytes(bytes(raw))
    with pytest.raises(RunError, match=r"corrupt checkpoint \(checksum mismatch in est\)"):
        load_checkpoint(path)


@pytest.mark.parametrize("damage,message", [
    (lambda p: p.write_bytes(b""), "empty"),
    (lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]), "truncated or corrupt"),
    (lambda p: torch.save({"a": 1}, p), "not an inrslam checkpoint"),
    (lambda p: p.unlink(), "no checkpoint to resume from"),
])
def test_unusable_checkpoints_are_one_line_errors(tmp_path, damage, message):
    path = tmp_path / "latest.pt"
    save_checkpoint(path, _state())
    damage(path)
    with pytest.raises(RunError, match=message) as e:
        load_checkpoint(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value) and "--overwrite" in str(e.value)


def test_a_full_disk_keeps_the_previous_checkpoint_and_says_so(tmp_path, monkeypatch):
    path = tmp_path / "checkpoints" / "latest.pt"
    save_checkpoint(path, _state())
    before = path.read_bytes()

    def full(obj, f):
        open(f, "wb").write(b"partial")
        raise RuntimeError("[enforce fail at inline_container.cc:664] . unexpected pos 64 vs 0")

    monkeypatch.setattr(torch, "save", full)
    import inrslam.runner.checkpoint as checkpoint

    monkeypatch.setattr(checkpoint, "_free_mb", lambda folder: 0)  # the disk is full
    with pytest.raises(RunError, match="no space left on device") as e:
        save_checkpoint(path, _state())
    assert "previous checkpoint is kept" in str(e.value) and "MB" in str(e.value)
    assert path.read_bytes() == before
    assert [p.name for p in path.parent.iterdir()] == ["latest.pt"]  # no temporary file left behind
    # the same torch error with room on the disk (a file-size limit, a quota): not called a full disk
    monkeypatch.setattr(checkpoint, "_free_mb", lambda folder: 10**6)
    with pytest.raises(RunError, match=r"writing the checkpoint failed .*1000000 MB free: a file-size limit") as e:
        save_checkpoint(path, _state())
    assert "previous checkpoint is kept" in str(e.value) and path.read_bytes() == before


def test_resume_rejects_another_runs_checkpoint_and_removes_stale_temporaries(tmp_path, monkeypatch):
    a, b = tmp_path / "a", tmp_path / "b"
    run_slam(tiny_cfg(), a)
    run_slam(tiny_cfg(["field.encoding=hash"]), b)
    stale = RunDir(a).checkpoints / ".latest.pt.k1ll3d.tmp.pt"
    stale.write_bytes(os.urandom(1024))  # what kill -9 during a checkpoint write leaves
    with monkeypatch.context() as m:  # not even the folder's lock: a finished run may be in a read-only folder
        m.setattr(RunDir, "lock", lambda self: pytest.fail("a complete run's folder was locked for writing"))
        resume_slam(a)  # a complete run: nothing to resume, nothing touched
    assert stale.exists() and json.loads(RunDir(a).run_info.read_text())["status"] == "complete"
    info = json.loads(RunDir(a).run_info.read_text())
    RunDir(a).run_info.write_text(json.dumps({**info, "status": "running"}))  # as if killed before it finished
    resume_slam(a)
    assert not stale.exists() and json.loads(RunDir(a).run_info.read_text())["status"] == "complete"
    os.replace(RunDir(b).checkpoint, RunDir(a).checkpoint)
    RunDir(a).run_info.write_text(json.dumps({**info, "status": "running"}))
    with pytest.raises(RunError, match="belongs to another run .*encoding 'hash' in the checkpoint, 'dense'"):
        resume_slam(a)


def test_the_loops_config_protocol_names_runconfigs_sections():
    import typing

    from inrslam.config.schema import RunConfig
    from inrslam.slam.system import SlamRunConfig

    wanted, run = typing.get_type_hints(SlamRunConfig), typing.get_type_hints(RunConfig)
    assert set(wanted) >= {"field", "render", "slam", "mesh", "seed", "device"}
    assert all(run[k] == tp for k, tp in wanted.items())


def test_config_yaml_records_the_thread_count_used(tmp_path):
    import yaml

    from inrslam.fields.kernels.threads import resolve_threads

    run_slam(tiny_cfg(["data.max_frames=2"]), tmp_path / "r")
    assert yaml.safe_load(RunDir(tmp_path / "r").config.read_text())["threads"] == resolve_threads(0) >= 1


def test_run_info_records_the_openblas_kernels_and_a_resume_on_others_warns(tmp_path):
    """The fused decoders round by the OpenBLAS kernel set: run_info.json records it, and resuming on another one
    (OPENBLAS_CORETYPE changed in between) warns that the result will not be an uninterrupted run's bit for bit."""
    from inrslam.errors import InrslamWarning
    from inrslam.machine import openblas_core
    from inrslam.runner import _warn_other_blas

    run_slam(tiny_cfg(["data.max_frames=2"]), tmp_path / "r")
    info = json.loads(RunDir(tmp_path / "r").run_info.read_text())
    started = info["machine"]["openblas_core"]
    assert started == openblas_core()
    if started is None:
        pytest.skip("no OpenBLAS whose kernel name can be read (SciPy's wheels bring one)")
    assert _warn_other_blas(tmp_path / "r", info, current=started) is None  # the same kernels: silent
    other = "Sandybridge" if started != "Sandybridge" else "Haswell"
    with pytest.warns(InrslamWarning, match=f"started on OpenBLAS kernels {started} and resumes on {other}"):
        assert "bit for bit" in _warn_other_blas(tmp_path / "r", info, current=other)


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MiB tmpfs (needs the right to mount: root in a container), unmounted afterwards."""
    import subprocess

    mnt = tmp_path / "disk"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here (needs root): the full-disk case is covered by the simulated test")
    yield mnt
    proc = subprocess.run(["umount", str(mnt)], capture_output=True, text=True)
    if proc.returncode:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_a_really_full_disk_keeps_the_previous_checkpoint(small_disk):
    path = small_disk / "checkpoints" / "latest.pt"
    save_checkpoint(path, _state())
    before = path.read_bytes()
    with pytest.raises(RunError, match="no space left on device") as e:
        save_checkpoint(path, {**_state(), "model": {"w": torch.zeros(1_000_000, dtype=torch.float64)}})  # 8 MB
    assert "\n" not in str(e.value) and "--resume" in str(e.value)
    assert path.read_bytes() == before and [p.name for p in path.parent.iterdir()] == ["latest.pt"]


@pytest.mark.parametrize("bad", ["data.path=/nonexistent/typo", "field.encoding=nope"])
def test_an_overwrite_that_cannot_start_keeps_the_finished_run(tmp_path, bad):
    out = tmp_path / "run"
    out.mkdir()
    kept = {"config.yaml": "seed: 0\n", "metrics.json": '{"ate_rmse_m": 0.01}', "trajectory.txt": "0 0 0 0 0 0 0 1\n"}
    for name, text in kept.items():
        (out / name).write_text(text)
    assert RunDir(out).holds_run()
    with pytest.raises(InrslamError):
        run_slam(load_config(preset="quick", overrides=[bad]), out, overwrite=True)
    assert {p.name: p.read_text() for p in out.iterdir()} == kept


@pytest.fixture
def our_signal_handlers():
    """SIGINT / SIGTERM at their defaults, so that `defer_interrupts_in_jit` installs its handler (as `inrslam run`)."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    with defer_interrupts_in_jit():
        yield
    for s, h in saved.items():
        signal.signal(s, h)


@pytest.mark.parametrize("callback_fails", [False, True])
def test_a_signal_during_a_frame_saves_it_even_if_the_progress_callback_fails(tmp_path, our_signal_handlers,
                                                                              callback_fails):
    """A SIGTERM in frame 1's progress report (no periodic checkpoint due) lets the frame end, saves it and stops the
    run; so it does when the callback (a live viewer) then fails. Frame 2 is never started."""
    seen = []

    def progress(i, n, info):
        seen.append(i)
        if i == 1:
            signal.raise_signal(signal.SIGTERM)  # held
            if callback_fails:
                raise RuntimeError("the viewer broke")

    out = tmp_path / "r"
    with pytest.raises(Terminated):
        run_slam(tiny_cfg(["slam.checkpoint_every=100"]), out, progress=progress)
    assert load_checkpoint(RunDir(out).checkpoint)["next_frame"] == 2 and seen == [0, 1]
    resume_slam(out)
    assert RunDir(out).is_complete()
