"""Tiny end-to-end SLAM runs on a built-in scene (quick preset): outputs, accuracy bound, determinism, resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from interrupted import run_interrupted
from polling import wait_for

from inrslam.config import load_config
from inrslam.io.trajectory import read_tum
from inrslam.runner import resume_slam, run_slam

FRAMES = 10
# 512 rays per initialisation step instead of 2048: 4-5 s less per run, ATE 1.4 instead of 1.1 cm (bound: 2 cm)
OVERRIDES = [f"data.max_frames={FRAMES}", "slam.checkpoint_every=2", "output.tensorboard=false", "seed=3",
             "slam.init_pixels=512"]


def quick_cfg(extra=()):
    return load_config(preset="quick", overrides=OVERRIDES + list(extra))


@pytest.fixture(scope="module")
def run_a(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "a"
    run_slam(quick_cfg(), out)
    return out


def test_outputs_parse_and_trajectory_is_accurate(run_a):
    ts, est = read_tum(run_a / "trajectory.txt")
    ts_gt, gt = read_tum(run_a / "trajectory_gt.txt")
    assert len(ts) == FRAMES and len(ts_gt) == FRAMES  # one pose per processed frame
    assert np.allclose(ts, ts_gt)
    metrics = json.loads((run_a / "metrics.json").read_text())
    for key in ("ate_rmse_m", "track_ms_per_frame", "map_ms_per_call", "model_size_mb", "psnr_process_db",
                "depth_l1_process_m", "frames", "peak_memory_mb"):
        assert metrics.get(key) is not None, key
    assert metrics["frames"] == FRAMES
    # Bound: the camera moves ~1 cm/frame, so over 10 frames a tracker that ignored the images (constant pose)
    # would be off by ~5 cm RMSE; at the quick preset (96x72 px, 8 x 256 rays) the tracker must do clearly better.
    gt_motion = np.linalg.norm(gt[:, :3, 3] - gt[0, :3, 3], axis=1)
    assert metrics["ate_rmse_m"] < 0.02
    assert metrics["ate_rmse_m"] < 0.5 * np.sqrt(np.mean(gt_motion**2))
    # frame 0 is initialised at its ground-truth pose
    assert np.allclose(est[0], gt[0], atol=1e-5)
    info = json.loads((run_a / "run_info.json").read_text())
    assert info["status"] == "complete"
    assert (run_a / "mesh.ply").stat().st_size > 0
    assert (run_a / "config.yaml").exists()
    log = [json.loads(line) for line in (run_a / "log.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in log if r["type"] == "track"] == list(range(1, FRAMES))
    assert [r["frame"] for r in log if r["type"] == "map"] == list(range(5, FRAMES, 5))
    # the relative trajectory (spec §7.6): same timestamps, keyframes identical, evaluated as well
    ts_rel, rel = read_tum(run_a / "trajectory_relative.txt")
    kfs = json.loads((run_a / "keyframes.json").read_text())["keyframes"]
    assert np.allclose(ts_rel, ts) and np.allclose(rel[kfs], est[kfs], atol=1e-6)
    assert metrics["ate_relative_rmse_m"] is not None and metrics["ate_relative_rmse_m"] < 0.02


def test_resolved_config_reproduces_run(run_a):
    import dataclasses

    from inrslam.fields.kernels.threads import resolve_threads

    cfg = load_config(run_a / "config.yaml", preset=None)
    assert cfg.threads == resolve_threads(0)  # the count used, not 0 ("every core"): --config sums in that order
    assert cfg == dataclasses.replace(quick_cfg(), threads=cfg.threads)


def test_determinism_same_seed(run_a, tmp_path):
    run_slam(quick_cfg(), tmp_path / "b")
    assert (tmp_path / "b" / "trajectory.txt").read_text() == (run_a / "trajectory.txt").read_text()


def test_run_holds_its_own_thread_count_whatever_the_process_left_set(run_a, tmp_path):
    """A caller that left torch / numba at 1 thread (as a sweep worker did) must not change a run's result: the run
    resolves `threads: 0` to every core, records it, and gives the caller its counts back."""
    import numba
    import torch

    from inrslam.fields.kernels.threads import resolve_threads, thread_scope

    with thread_scope(1):
        run_slam(quick_cfg(), tmp_path / "b")
        assert (torch.get_num_threads(), numba.get_num_threads()) == (1, 1)
    assert (tmp_path / "b" / "trajectory.txt").read_text() == (run_a / "trajectory.txt").read_text()
    info = json.loads((tmp_path / "b" / "run_info.json").read_text())
    assert info["threads"] == resolve_threads(0)
    assert info["machine"]["cores"] == os.cpu_count() and info["machine"]["cpu"]  # the machine it ran on


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the OpenMP ballast acts on Linux's libgomp")
def test_a_run_throttled_throughout_by_the_load_guard_is_byte_identical(run_a, tmp_path):
    """The adaptive wait policy's ballast changes when OpenMP threads sleep, never how work is split."""
    import torch

    from inrslam import omp_env

    torch.ones(1 << 20).sum()  # torch's OpenMP runtime has its pool
    libs = omp_env.loaded_libgomp()
    if not libs:
        pytest.skip("no GNU libgomp loaded in this process")
    ballast = omp_env.Ballast(libs, len(os.sched_getaffinity(0)) + 1).start()  # as the guard holds it
    assert ballast.held == libs
    try:
        run_slam(quick_cfg(), tmp_path / "b")
    finally:
        ballast.stop()
    for name in ("trajectory.txt", "mesh.ply"):
        assert (tmp_path / "b" / name).read_bytes() == (run_a / name).read_bytes(), name
    info = json.loads((tmp_path / "b" / "run_info.json").read_text())["omp_wait_policy"]
    assert set(info) == {"policy", "set_by", "adaptive", "guard"}


def test_a_run_with_glibcs_own_malloc_settings_is_byte_identical(run_a, tmp_path):
    """inrslam.malloc_env decides where tensors' memory comes from, never what is computed: a run in a process that
    keeps glibc's settings (`INRSLAM_MALLOC=default`) equals `run_a`, run in this process with the run's settings."""
    from inrslam import malloc_env

    out = tmp_path / "b"
    cmd = [sys.executable, "-m", "inrslam.cli", "run", "--preset", "quick", "--out", str(out), "--quiet", *OVERRIDES]
    res = subprocess.run(cmd, env={**os.environ, "INRSLAM_MALLOC": "default"}, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    for name in ("trajectory.txt", "mesh.ply"):
        assert (out / name).read_bytes() == (run_a / name).read_bytes(), name
    untuned = json.loads((out / "run_info.json").read_text())["malloc"]
    tuned = json.loads((run_a / "run_info.json").read_text())["malloc"]
    assert untuned == {"tuned": False, "reason": "INRSLAM_MALLOC=default"}
    assert tuned["tuned"] is (malloc_env._glibc() is not None and os.environ.get(malloc_env.ENV) != "default")


FUSED = ["field.decoder_kernel=auto", "loss.kernel=auto", "render.kernel=auto"]  # what `paper_fused` adds to `paper`


@pytest.fixture(scope="module")
def run_fused(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "fused"
    run_slam(quick_cfg(FUSED), out)
    return out


def test_the_paper_loop_with_every_fused_kernel_tracks_as_the_paper_loop(run_a, run_fused):
    """`paper_fused`'s three kernel switches (on `quick`'s sizes here) compute the same maths as `paper`'s autograd,
    rounded otherwise: the two trajectories part only by rounding that the optimisation then carries along, a small
    fraction of the loop's own drift (on these tiny images ~5 cm over the run)."""
    (_, a), (_, b), (_, gt) = (read_tum(d / name) for d, name in ((run_a, "trajectory.txt"),
                                                                   (run_fused, "trajectory.txt"),
                                                                   (run_a, "trajectory_gt.txt")))
    apart = np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)  # metres, per frame
    drift = np.linalg.norm(a[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert apart[:4].max() < 1e-4  # the first frames agree to 0.1 mm
    assert (apart <= 0.25 * drift + 1e-3).all(), (apart, drift)
    m_f, m_a = (json.loads((d / "metrics.json").read_text()) for d in (run_fused, run_a))
    assert m_f["ate_rmse_m"] < 0.02 and m_f["ate_rmse_m"] < 1.5 * m_a["ate_rmse_m"] + 0.002


def test_interrupted_run_with_every_fused_kernel_resumes_to_the_uninterrupted_result(run_fused, tmp_path):
    """`paper_fused` is deterministic per seed and resumable exactly, as `paper` is."""
    out = tmp_path / "interrupted"

    run_interrupted(quick_cfg(FUSED), out, 5)
    assert (out / "checkpoints" / "latest.pt").is_file() and not (out / "trajectory.txt").exists()
    resume_slam(out)
    for name in ("trajectory.txt", "trajectory_relative.txt", "mesh.ply"):
        assert (out / name).read_bytes() == (run_fused / name).read_bytes(), name


def test_killed_run_resumes_to_identical_result(run_a, tmp_path):
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "inrslam.cli", "run", "--preset", "quick", "--out", str(out), "--quiet", *OVERRIDES,
           "output.tensorboard=true"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    ckpt = out / "checkpoints" / "latest.pt"
    # wait until at least the checkpoint after frame 4 exists, then kill the process hard
    wait_for(lambda: proc.poll() is not None or (ckpt.exists() and _logged_frames(out) >= 5), 300, 0.05)
    assert proc.poll() is None, f"run finished before it could be killed: {proc.stderr.read().decode()[-2000:]}"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (out / "metrics.json").exists()
    resume_slam(out)
    assert (out / "trajectory.txt").read_text() == (run_a / "trajectory.txt").read_text()
    assert (out / "trajectory_relative.txt").read_text() == (run_a / "trajectory_relative.txt").read_text()
    log_a = (run_a / "log.jsonl").read_text().splitlines()
    log_b = (out / "log.jsonl").read_text().splitlines()
    strip = lambda lines: [{k: v for k, v in json.loads(l).items() if not k.endswith("_ms")} for l in lines]
    assert strip(log_b) == strip(log_a)
    _assert_tensorboard_steps_once(out / "tensorboard", "track/loss", list(range(1, FRAMES)))


def _assert_tensorboard_steps_once(logdir: Path, tag: str, steps: list[int]) -> None:
    """TensorBoard shows each step of `tag` once: the resumed writer's event file starts with an explicit purge
    (SessionLog START at the checkpointed frame) of what the killed run logged after its checkpoint."""
    try:
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
        from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
        from tensorboard.compat.proto.event_pb2 import SessionLog
    except ImportError:
        return  # tensorboard is optional; the trajectory/log checks above still ran
    files = sorted(logdir.glob("events.out.tfevents.*"), key=lambda p: p.stat().st_mtime)
    assert len(files) == 2  # the killed segment and the resumed one
    resumed = [e for e in EventFileLoader(str(files[1])).Load()]
    first_step = min(e.step for e in resumed if e.HasField("summary"))
    starts = [e.step for e in resumed if e.HasField("session_log") and e.session_log.status == SessionLog.START]
    assert starts == [first_step]  # purge from the first frame processed after the checkpoint on
    acc = EventAccumulator(str(logdir), purge_orphaned_data=True)
    acc.Reload()
    assert [e.step for e in acc.Scalars(tag)] == steps


def _logged_frames(out: Path) -> int:
    p = out / "log.jsonl"
    if not p.exists():
        return 0
    return sum(1 for line in p.read_text().splitlines() if line.strip())


def test_initialisation_ends_on_a_plateau_only_when_asked():
    from inrslam.datasets import open_dataset
    from inrslam.slam.system import SlamSystem

    def init_record(extra):
        cfg = quick_cfg(["data.max_frames=1", "slam.init_iters=100", "slam.init_pixels=256"] + extra)
        return SlamSystem(cfg, open_dataset(cfg.data)).process(0)[0]

    plain = init_record([])
    early = init_record(["slam.init_stop_window=10", "slam.init_stop_tol=0.5"])  # stop once a window falls < 50 %
    assert plain["type"] == early["type"] == "init" and plain["iters"] == 100
    assert 20 <= early["iters"] < 100 and early["iters"] % 10 == 0
