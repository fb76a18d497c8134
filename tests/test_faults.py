"""Fault injection: what the CLI does with relative paths, damaged or half-done run directories, failed sweep runs,
Ctrl-C and unusable arguments. User-visible behaviour is checked on a real `python -m inrslam.cli` subprocess: one
line on stderr (no traceback), the exit code, and that nothing already finished is lost (docs/reliability.md).

Runs are tiny: a 6-frame, 96 x 72 built-in room exported to the Replica layout, quick preset, one thread.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml
from polling import wait_for

import inrslam
from inrslam.bench.sweep import run_sweep
from inrslam.bench.testing import write_fake_run
from inrslam.cli import main
from inrslam.data.config import DataConfig
from inrslam.datasets import open_dataset
from inrslam.eval import eval_mesh_files, evaluate_run
from inrslam.eval.run import TRAJECTORY_KEYS
from inrslam.geometry.intrinsics import Intrinsics
from inrslam.io.atomic import write_json
from inrslam.io.rundir import RunDir
from inrslam.io.trajectory import write_tum
from inrslam.runner.checkpoint import load_checkpoint
from inrslam.scenes import SceneConfig, load_scene

SRC = Path(inrslam.__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent
FRAMES, WIDTH, HEIGHT = 6, 96, 72
RUN_ARGS = ["--preset", "quick", "--quiet", "threads=1", "seed=3", "slam.init_iters=30", "slam.init_pixels=512",
            "slam.checkpoint_every=1", "output.tensorboard=false", "eval.heldout_every=0", "eval.n_samples=2000"]
EXIT_ERROR, EXIT_FAILED_RUNS, EXIT_INTERRUPTED = 2, 1, 130


def cli(*args: str, cwd: Path, env: dict | None = None, timeout: float = 240) -> subprocess.CompletedProcess:
    """`python -m inrslam.cli ARGS` in `cwd` with this tree on the path; output captured as text."""
    return subprocess.run([sys.executable, "-m", "inrslam.cli", *args], cwd=cwd, env=_env(env), capture_output=True,
                          text=True, timeout=timeout)


def _default_sigint() -> None:
    """In the child before exec: SIGINT back to its default, so the child's Python raises KeyboardInterrupt on it
    even when the test run itself was started in the background with SIGINT ignored (a shell's `cmd &`), which
    a child would inherit."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _alive(pid: int) -> bool:
    """Whether process `pid` exists (and is not a zombie awaiting its parent)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True
    return state != "Z"


def _env(extra: dict | None = None) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(SRC), str(TESTS)])
    env.update(extra or {})
    return env


def assert_one_line_error(proc, code: int, *needles: str) -> str:
    """The process exited with `code`, printed exactly one stderr line containing every needle, and no traceback."""
    err = proc.stderr.strip()
    assert proc.returncode == code, (proc.returncode, proc.stderr[-3000:])
    assert "Traceback" not in proc.stderr and len(err.splitlines()) == 1, proc.stderr[-3000:]
    for n in needles:
        assert n in err, (n, err)
    return err


def assert_stopped(proc, code: int, *needles: str, held: bool = True) -> str:
    """`assert_one_line_error` for an interrupted `run`: before its line, the one note that the frame in progress
    is being finished and saved (`held`; the signal may also land where nothing is held: frame 0, the end)."""
    lines = proc.stderr.strip().splitlines()
    notes = [x for x in lines if x.startswith("inrslam: finishing frame ")]
    assert len(notes) <= 1 and (notes or not held or len(lines) == 1), proc.stderr[-3000:]
    if notes:
        assert re.fullmatch(r"inrslam: finishing frame \d+ and saving it, then stopping \(Ctrl-C again stops at "
                            r"once\)", notes[0]) and lines[0] == notes[0], proc.stderr[-3000:]
    rest = "\n".join(x for x in lines if x not in notes)
    return assert_one_line_error(subprocess.CompletedProcess(proc.args, proc.returncode, proc.stdout, rest), code,
                                 *needles)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A folder holding `data/room_rep`: the built-in room exported to the Replica layout (with its GT mesh)."""
    w = tmp_path_factory.mktemp("faults")
    assert main(["export", "room", "--layout", "replica", "--out", str(w / "data" / "room_rep"),
                 "--frames", str(FRAMES), "--width", str(WIDTH), "--height", str(HEIGHT)]) == 0
    (w / "elsewhere").mkdir()
    return w


@pytest.fixture(scope="module")
def relative_run(work) -> Path:
    """A finished run started from `work` with relative --data and --out paths."""
    proc = cli("run", "--data", "data/room_rep", "--out", "o", *RUN_ARGS, cwd=work)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return work / "o"


# -- a. relative paths ---------------------------------------------------------------------------------------------


def test_relative_data_path_is_recorded_absolute_and_mesh_is_evaluated(work, relative_run):
    data = work / "data" / "room_rep"
    cfg = yaml.safe_load((relative_run / "config.yaml").read_text())
    info = json.loads((relative_run / "run_info.json").read_text())
    assert cfg["data"]["path"] == str(data)
    assert info["dataset"]["root"] == str(data) and info["gt_mesh"] == str(data / "mesh.ply")
    metrics = json.loads((relative_run / "metrics.json").read_text())
    assert metrics["acc_m"] is not None and metrics["comp_m"] is not None, metrics["eval_notes"]


def test_old_run_with_relative_gt_mesh_evaluates_from_another_directory(work, relative_run, tmp_path, monkeypatch,
                                                                        capsys):
    """A run made before paths were recorded absolute: config.yaml, run_info.json root and gt_mesh relative to the
    directory it was started from. `eval` from elsewhere finds the mesh through the data root."""
    (tmp_path / "data").mkdir()
    os.symlink(work / "data" / "room_rep", tmp_path / "data" / "room_rep")
    old = tmp_path / "o"
    shutil.copytree(relative_run, old)
    cfg = yaml.safe_load((old / "config.yaml").read_text())
    cfg["data"]["path"] = "data/room_rep"
    (old / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    info = json.loads((old / "run_info.json").read_text())
    info["dataset"]["root"], info["gt_mesh"] = "data/room_rep", "data/room_rep/mesh.ply"
    write_json(old / "run_info.json", info)
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert main(["eval", str(old), "--json"]) == 0
    metrics = json.loads((old / "metrics.json").read_text())
    ref = json.loads((relative_run / "metrics.json").read_text())
    assert metrics["acc_m"] == ref["acc_m"] and metrics["comp_m"] == ref["comp_m"]
    assert metrics["mesh_eval"]["gt_mesh"] == str(tmp_path / "data" / "room_rep" / "mesh.ply")


def test_resume_of_old_run_with_missing_relative_data_is_one_line(work, relative_run, tmp_path):
    old = tmp_path / "o"
    shutil.copytree(relative_run, old)
    cfg = yaml.safe_load((old / "config.yaml").read_text())
    cfg["data"]["path"] = "data/room_rep"
    (old / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    before = (old / "metrics.json").read_bytes()
    proc = cli("run", "--resume", str(old), "--quiet", cwd=work / "elsewhere")
    assert_one_line_error(proc, EXIT_ERROR, "data.path 'data/room_rep' is relative", "config.yaml")
    assert (old / "metrics.json").read_bytes() == before


# -- g. Ctrl-C ---------------------------------------------------------------------------------------------------


def test_ctrl_c_in_run_says_how_to_resume_and_resume_completes(work, relative_run, monkeypatch):
    """SIGINT after the first checkpoint: exit 130 with the resume command; resuming from another directory (the
    data path is absolute in config.yaml) ends with the trajectory and Acc of the uninterrupted run."""
    out = work / "g"
    proc = subprocess.Popen([sys.executable, "-m", "inrslam.cli", "run", "--data", "data/room_rep", "--out", "g",
                             *RUN_ARGS], cwd=work, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, preexec_fn=_default_sigint)
    wait_for(lambda: proc.poll() is not None or RunDir(out).has_checkpoint(), 240, 0.02)
    assert proc.poll() is None, f"run ended before it could be interrupted: {proc.stderr.read()[-2000:]}"
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does: the whole foreground group
    stdout, stderr = proc.communicate(timeout=120)
    done = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    assert_stopped(done, EXIT_INTERRUPTED, "interrupted", "inrslam run --resume g", held=False)
    assert RunDir(out).has_checkpoint() and not (out / "metrics.json").exists()
    monkeypatch.chdir(work / "elsewhere")
    assert main(["run", "--resume", str(out), "--quiet"]) == 0
    assert (out / "trajectory.txt").read_text() == (relative_run / "trajectory.txt").read_text()
    m, ref = (json.loads((d / "metrics.json").read_text()) for d in (out, relative_run))
    assert m["acc_m"] == ref["acc_m"] and json.loads((out / "run_info.json").read_text())["status"] == "complete"


def test_sigterm_unwinds_like_ctrl_c_and_a_second_process_is_refused_meanwhile(work):
    """While a run works in its folder, a second `inrslam run` into it (--resume or --overwrite) is one line naming
    the holder, and changes nothing; SIGTERM (a batch system's time limit, `kill`) then exits 143 with the resume
    command and its checkpoint, and the folder is free again. (Long tracking keeps the first run busy; the Ctrl-C
    test above resumes a run to the end.)"""
    out = work / "t"
    slow = [*RUN_ARGS, "slam.track_iters=2500"]
    proc = subprocess.Popen([sys.executable, "-m", "inrslam.cli", "run", "--data", "data/room_rep", "--out", "t",
                             *slow], cwd=work, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    wait_for(lambda: proc.poll() is not None or RunDir(out).has_checkpoint(), 240, 0.02)
    assert proc.poll() is None, f"run ended before it could be interrupted: {proc.stderr.read()[-2000:]}"
    config = (out / "config.yaml").read_bytes()
    for argv in (["run", "--resume", "t", "--quiet"], ["run", "--data", "data/room_rep", "--out", "t", "--overwrite",
                                                        *slow]):
        second = cli(*argv, cwd=work)
        assert_one_line_error(second, EXIT_ERROR, "another inrslam process is running in this run folder",
                              f"pid {proc.pid} on ")
        assert (out / "config.yaml").read_bytes() == config and RunDir(out).has_checkpoint()  # not cleared
    proc.send_signal(signal.SIGTERM)  # the process alone, as `kill` or SLURM's time limit
    stdout, stderr = proc.communicate(timeout=120)
    done = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    assert_stopped(done, 128 + signal.SIGTERM, "terminated by SIGTERM; the run can be resumed",
                          "inrslam run --resume t")
    assert RunDir(out).has_checkpoint() and not (out / "metrics.json").exists()
    with RunDir(out).lock():  # the lock went with its process
        assert (out / ".run.lock").is_file()


def test_an_interrupt_mid_run_ends_the_frame_and_saves_it(work, monkeypatch):
    """With no periodic checkpoint due, SIGTERM after frame 1 still leaves a checkpoint: the frame being processed
    ends, is saved, and the run stops; the resumed run equals an uninterrupted one."""
    args = [a for a in RUN_ARGS if not a.startswith("slam.checkpoint_every")]
    args += ["slam.checkpoint_every=100", "slam.track_iters=150"]  # no periodic checkpoint; frames of ~0.5 s
    out = work / "h"
    proc = subprocess.Popen([sys.executable, "-m", "inrslam.cli", "run", "--data", "data/room_rep", "--out", "h",
                             *args], cwd=work, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    log = out / "log.jsonl"
    wait_for(lambda: proc.poll() is not None or (log.is_file() and '"frame": 1' in log.read_text()), 240, 0.01)
    assert proc.poll() is None, f"run ended before it could be interrupted: {proc.stderr.read()[-2000:]}"
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    done = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    assert_stopped(done, 128 + signal.SIGTERM, "the run can be resumed from its last checkpoint")
    saved = load_checkpoint(RunDir(out).checkpoint)["next_frame"]
    assert 2 <= saved < FRAMES, saved  # frame 1 or a later one, whole; not the end of SLAM
    frames = [json.loads(x)["frame"] for x in log.read_text().splitlines()]
    assert max(frames) == saved - 1  # the log holds exactly the saved frames
    monkeypatch.chdir(work)
    assert main(["run", "--resume", "h", "--quiet"]) == 0
    assert main(["run", "--data", "data/room_rep", "--out", "h_ref", *args]) == 0
    assert (out / "trajectory.txt").read_text() == (work / "h_ref" / "trajectory.txt").read_text()


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_in_bench_keeps_finished_runs_and_says_how_to_resume(tmp_path, signum):
    spec = _spec(tmp_path)
    out = tmp_path / "sweep"
    proc = subprocess.Popen([sys.executable, "-m", "inrslam.cli", "bench", str(spec), "--out", str(out)],
                            cwd=tmp_path, env=_env({"INRSLAM_BENCH_RUN_FN": "fault_runs:hang_other_seeds"}),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=_default_sigint)
    hanging = out / "room__dense__direct__quick__s1" / "started"
    wait_for(lambda: proc.poll() is not None or hanging.exists(), 120, 0.02)
    assert proc.poll() is None, proc.stderr.read()[-2000:]
    time.sleep(0.2)
    if signum == signal.SIGINT:
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C: the whole foreground group
        code, said = EXIT_INTERRUPTED, "interrupted; finished runs are kept"
    else:
        proc.send_signal(signum)  # the driver alone (`kill`, a closed session): it stops its workers itself
        code, said = 128 + signum, "terminated by SIGTERM; finished runs are kept"
    stdout, stderr = proc.communicate(timeout=60)
    done = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    assert_one_line_error(done, code, said, f"inrslam bench {spec} --out {out}")
    worker = int(hanging.read_text())
    assert wait_for(lambda: not _alive(worker), 10, 0.05), "the sweep left its hanging worker running"
    assert RunDir(out / "room__dense__direct__quick__s0").is_complete()
    assert json.loads((out / "sweep_status.json").read_text())["state"] == "interrupted"
    res = run_sweep(spec, out, run_fn="inrslam.bench.testing:fake_run", quiet=True, report=False)
    assert res.count("skipped") == 1 and res.count("complete") == 1 and not res.failed


def test_sigterm_to_a_sweep_lets_its_workers_save_the_frame_in_progress(work):
    """`kill` of an `inrslam bench` driver: the executor stops its workers, each ends its frame and saves it (no
    periodic checkpoint was due), and the same command resumes the run from there."""
    spec = work / "held.yaml"
    spec.write_text(yaml.safe_dump({
        "encodings": ["dense"], "renders": ["direct"], "presets": ["quick"],
        "scenes": [{"name": "rr", "path": str(work / "data" / "room_rep")}],
        "overrides": ["threads=1", "slam.init_iters=30", "slam.init_pixels=512", "slam.checkpoint_every=100",
                      "slam.track_iters=150", "output.tensorboard=false", "eval.heldout_every=0",
                      "eval.n_samples=2000"]}))
    out = work / "held_sweep"
    proc = subprocess.Popen([sys.executable, "-m", "inrslam.cli", "bench", str(spec), "--out", str(out)], cwd=work,
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    logs = lambda: list(out.glob("*/log.jsonl"))  # noqa: E731
    wait_for(lambda: proc.poll() is not None or any('"frame": 1' in p.read_text() for p in logs()), 240, 0.01)
    assert proc.poll() is None, f"sweep ended before it could be stopped: {proc.stderr.read()[-2000:]}"
    proc.send_signal(signal.SIGTERM)  # the driver alone
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, stderr[-3000:]
    assert "terminated by SIGTERM; finished runs are kept" in stderr
    (run,) = [p.parent for p in logs()]
    saved = load_checkpoint(RunDir(run).checkpoint)["next_frame"]
    assert 2 <= saved < FRAMES, saved  # frame 1 or a later one, saved by the worker as it stopped
    res = run_sweep(spec, out, quiet=True, report=False)
    (result,) = res.results.values()
    assert result["status"] == "complete" and result["resumed"], result


# -- e. failed sweep runs ------------------------------------------------------------------------------------------


def _spec(tmp_path: Path) -> Path:
    spec = tmp_path / "two.yaml"
    spec.write_text("encodings: [dense]\nrenders: [direct]\nscenes: [builtin:room]\npresets: [quick]\n"
                    "seeds: [0, 1]\n")
    return spec


def test_bench_with_a_failed_run_goes_on_and_exits_nonzero(tmp_path):
    out = tmp_path / "sweep"
    proc = cli("bench", str(_spec(tmp_path)), "--out", str(out), cwd=tmp_path,
               env={"INRSLAM_BENCH_RUN_FN": "fault_runs:fail_other_seeds"})
    assert_one_line_error(proc, EXIT_FAILED_RUNS, "1 of 2 runs failed", "error.txt")
    assert RunDir(out / "room__dense__direct__quick__s0").is_complete()
    assert "injected failure" in (out / "room__dense__direct__quick__s1" / "error.txt").read_text()
    assert (out / "report" / "index.html").is_file()


# -- c. eval: stale families, incomplete runs --------------------------------------------------------------------


def test_eval_without_gt_trajectory_leaves_no_stale_trajectory_metric(tmp_path):
    rd = write_fake_run(tmp_path / "run", "hash", "direct", frames=12)
    first = evaluate_run(rd)
    assert first["ate_n_used"] == 12 and first["ate_std_m"] is not None and first["rpe_n_pairs"] == 11
    (rd / "trajectory_gt.txt").unlink()
    second = evaluate_run(rd)
    on_disk = json.loads((rd / "metrics.json").read_text())
    for key in TRAJECTORY_KEYS:
        assert second[key] is None and on_disk[key] is None, key
    assert on_disk["frames"] == 12 and on_disk["track_ms_per_frame"] == first["track_ms_per_frame"]
    assert any("trajectory_gt.txt" in n for n in on_disk["eval_notes"])


@pytest.mark.parametrize("damage", ["running", "no_trajectory"])
def test_eval_of_an_incomplete_run_is_one_line_and_writes_nothing(tmp_path, damage):
    rd = write_fake_run(tmp_path / "run", "hash", "direct", status="running" if damage == "running" else "complete")
    (rd / "checkpoints").mkdir()
    (rd / "checkpoints" / "latest.pt").write_bytes(b"checkpoint")
    if damage == "no_trajectory":
        (rd / "trajectory.txt").unlink()
    before = (rd / "metrics.json").read_bytes()
    proc = cli("eval", str(rd), cwd=tmp_path)
    want = "status running" if damage == "running" else "no trajectory.txt"
    assert_one_line_error(proc, EXIT_ERROR, f"{rd}: the run is incomplete (", want,
                          f"resume it with inrslam run --resume {rd}")
    assert (rd / "metrics.json").read_bytes() == before


# -- d. report ---------------------------------------------------------------------------------------------------


def test_report_shows_corrupt_json_files_and_does_not_count_them(tmp_path, capsys):
    runs = tmp_path / "runs"
    good = write_fake_run(runs / "good", "dense", "direct")
    bad_metrics = write_fake_run(runs / "bad_metrics", "hash", "direct")
    bad_info = write_fake_run(runs / "bad_info", "hash", "density")
    for path in (bad_metrics / "metrics.json", bad_info / "run_info.json"):
        text = path.read_text()
        path.write_text(text[: len(text) // 2])  # truncated: invalid JSON
    assert main(["report", str(runs)]) == 0
    printed = capsys.readouterr().out
    assert "3 runs: " in printed and "1 complete" in printed and "1 corrupt: metrics.json" in printed
    status = {line.split(",")[0]: line.split(",")[6]
              for line in (runs / "report" / "runs.csv").read_text().splitlines()[1:]}
    assert status == {"good": "complete", "bad_metrics": "corrupt: metrics.json",
                      "bad_info": "corrupt: run_info.json"}
    board = (runs / "report" / "leaderboard.md").read_text()
    assert "(1 runs," in board and board.count("| SDF(direct) |") == 1
    html = (runs / "report" / "index.html").read_text()
    assert "corrupt: metrics.json" in html and "corrupt: run_info.json" in html
    assert good.name in (runs / "report" / "runs.csv").read_text()


def test_report_on_a_missing_folder_fails_and_creates_nothing(tmp_path):
    proc = cli("report", str(tmp_path / "nope"), cwd=tmp_path)
    assert_one_line_error(proc, EXIT_ERROR, str(tmp_path / "nope"), "does not exist")
    assert not (tmp_path / "nope").exists()


# -- b. --cull-gt with large GT triangles ------------------------------------------------------------------------


def _grid_wall(size: float, n: int, z: float) -> trimesh.Trimesh:
    """size x size m square at height z, centred on the z axis, as n x n cells of two triangles."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return trimesh.Trimesh(np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1), faces, process=False)


def test_cull_gt_keeps_the_seen_part_of_a_two_triangle_wall(tmp_path):
    """A 4 m x 4 m wall at z = 2 as two triangles; the camera at the origin sees its central 2.56 m x 2.56 m and
    none of its corners. The reconstruction is that seen part, finely meshed: with --cull-gt the GT must keep the
    seen part (Acc / Comp ~ 0), not lose the whole wall."""
    intr = Intrinsics(fx=50.0, fy=50.0, cx=31.5, cy=31.5, width=64, height=64)
    half = 2.0 * 31.5 / 50.0  # half-width of the view at z = 2
    wall = trimesh.Trimesh([[-2, -2, 2], [2, -2, 2], [2, 2, 2], [-2, 2, 2]], [[0, 1, 2], [0, 2, 3]], process=False)
    wall.export(tmp_path / "gt.ply")
    _grid_wall(2 * half, 40, z=2.0).export(tmp_path / "rec.ply")
    write_tum(tmp_path / "cams.txt", np.zeros(1), np.eye(4)[None])
    kw = dict(cameras_path=tmp_path / "cams.txt", intrinsics=intr, every=1, n_samples=20_000)
    culled = eval_mesh_files(tmp_path / "rec.ply", tmp_path / "gt.ply", cull_gt=True, **kw)
    assert culled["comp_m"] < 0.01 and culled["acc_m"] < 0.01 and culled["comp_ratio"] > 0.95
    assert culled["mesh_eval"]["gt_split_faces"] > culled["mesh_eval"]["gt_faces"] > 2
    plain = eval_mesh_files(tmp_path / "rec.ply", tmp_path / "gt.ply", **kw)
    assert plain["comp_ratio"] < 0.5  # unculled, the unseen 60 % of the wall counts as missed


# -- f. export ---------------------------------------------------------------------------------------------------


def test_export_writes_a_readable_tum_folder(tmp_path):
    out = tmp_path / "room_tum"
    proc = cli("export", "room", "--layout", "tum", "--out", str(out), "--frames", "3", "--width", "48",
               "--height", "36", cwd=tmp_path)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    ds = open_dataset(DataConfig(path=str(out)))
    scene = load_scene("room", SceneConfig(frames=3, width=48, height=36))
    assert ds.name == "tum" and len(ds) == 3 and (out / "mesh.ply").is_file()
    for i in range(3):
        a, b = ds[i], scene[i]
        assert np.allclose(a.rgb, b.rgb, atol=1 / 255 + 1e-6) and np.allclose(a.depth, b.depth, atol=2e-4)
        assert np.allclose(a.c2w, b.c2w, atol=1e-6)
    again = cli("export", "room", "--layout", "tum", "--out", str(out), cwd=tmp_path)
    assert_one_line_error(again, EXIT_ERROR, str(out), "not empty")


# -- h. unusable arguments ---------------------------------------------------------------------------------------


def _read_only_dir(tmp_path: Path) -> Path:
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o555)
    try:
        (d / "probe").write_text("")
    except OSError:
        return d
    (d / "probe").unlink()  # running as root: permission bits do not stop writes
    if _unwritable(Path("/sys")):  # read-only to root too in most containers
        return Path("/sys")
    pytest.skip("no read-only directory available to this user")


def _unwritable(d: Path) -> bool:
    try:
        (d / ".inrslam-probe").write_text("")
    except OSError:
        return True
    (d / ".inrslam-probe").unlink()
    return False


@pytest.mark.parametrize("case", ["out_is_file", "out_read_only", "device_tpu"])
def test_unusable_run_arguments_are_one_line_errors(tmp_path, case):
    args = ["run", "--preset", "quick", "--quiet"]
    if case == "out_is_file":
        (tmp_path / "f").write_text("x")
        args += ["--out", str(tmp_path / "f")]
        needles = [str(tmp_path / "f"), "not a directory"]
    elif case == "out_read_only":
        ro = _read_only_dir(tmp_path)
        args += ["--out", str(ro / "run")]
        needles = [str(ro / "run"), "cannot write"]
    else:
        args += ["--out", str(tmp_path / "run"), "--device", "tpu"]
        needles = ["'device'", "'tpu'", "cuda:N"]
    proc = cli(*args, cwd=tmp_path)
    assert_one_line_error(proc, EXIT_ERROR, *needles)
    assert not (tmp_path / "run").exists()
    if case == "out_is_file":
        assert (tmp_path / "f").read_text() == "x"


# -- numeric keys, intrinsics, timestamps, frame size: refused before any work -------------------------------------


@pytest.mark.parametrize("override,needle", [
    ("mesh.resolution=0", "'mesh.resolution' in command-line overrides: expected a number >= 0.001"),
    ("slam.map_every=0", "'slam.map_every' in command-line overrides: expected an integer >= 1"),
    ("slam.track_pixels=0", "'slam.track_pixels'"),
    ("slam.track_iters=-1", "'slam.track_iters'"),
    ("slam.map_lr=-0.01", "'slam.map_lr'"),
    ("sampling.n_free=-1", "'sampling.n_free'"),
    ("sampling.n_free=1 sampling.n_surface=0", "n_free + n_surface >= 2"),
    ("sampling.n_uniform=1", "'sampling.n_uniform'"),
    ("render.density.beta=.nan", "expected a finite number"),
    ("data.builtin.width=1", "'data.builtin.width'"),
])
def test_bad_numeric_keys_fail_at_load_time(tmp_path, override, needle):
    proc = cli("run", "--out", str(tmp_path / "o"), *override.split(), "--quiet", cwd=tmp_path)
    assert_one_line_error(proc, EXIT_ERROR, needle)
    assert not (tmp_path / "o").exists()  # refused at load: no run folder was ever made


@pytest.mark.parametrize("intrinsics,needle", [
    ("[0,500,48,36]", "fx=0.0"), ("[-300,300,48,36]", "fx=-300.0"), ("[.nan,300,48,36]", "finite number")])
def test_bad_intrinsics_are_one_line_errors(work, tmp_path, intrinsics, needle):
    proc = cli("run", "--data", str(work / "data" / "room_rep"), "--out", str(tmp_path / "o"), *RUN_ARGS,
               f"data.intrinsics={intrinsics}", cwd=tmp_path)
    assert_one_line_error(proc, EXIT_ERROR, needle)


def test_nan_in_cam_params_names_the_file(work, tmp_path):
    data = tmp_path / "room_rep"
    shutil.copytree(work / "data" / "room_rep", data, symlinks=True)
    cam = data / "cam_params.json"
    params = json.loads(cam.read_text())
    params["camera"]["fx"] = float("nan")
    cam.write_text(json.dumps(params))  # json writes NaN, which Python's reader accepts
    proc = cli("run", "--data", str(data), "--out", str(tmp_path / "o"), *RUN_ARGS, cwd=tmp_path)
    assert_one_line_error(proc, EXIT_ERROR, str(cam), "fx not a finite number")


def test_nan_timestamp_in_tum_rgb_list_names_file_and_line(tmp_path):
    from inrslam.errors import DataError

    out = tmp_path / "tum"
    assert main(["export", "room", "--layout", "tum", "--out", str(out), "--frames", "3", "--width", "32",
                 "--height", "24"]) == 0
    lines = (out / "rgb.txt").read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))
    lines[k + 1] = "nan " + lines[k + 1].split()[1]
    (out / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=rf"rgb.txt:{k + 2}: timestamp 'nan' is not a finite number"):
        open_dataset(DataConfig(path=str(out)))


def test_tiny_images_are_refused_before_slam(tmp_path):
    from inrslam.errors import DataError

    out = tmp_path / "tiny"
    assert main(["export", "room", "--layout", "replica", "--out", str(out), "--frames", "2", "--width", "8",
                 "--height", "6"]) == 0
    from inrslam.config import load_config
    from inrslam.slam.system import SlamSystem

    cfg = load_config(preset="quick", overrides=[f"data.path={out}"])
    with pytest.raises(DataError, match="frames are 8x6 px; the SLAM loop needs at least 16x16"):
        SlamSystem(cfg, open_dataset(cfg.data))


# -- checkpoints and post-SLAM steps ---------------------------------------------------------------------------------


@pytest.mark.parametrize("damage,needle", [
    ("empty", "the checkpoint is empty"), ("truncate", "truncated or corrupt"), ("flip", "corrupt")])
def test_resume_from_a_damaged_checkpoint_is_one_line(work, relative_run, tmp_path, damage, needle):
    run = tmp_path / "o"
    shutil.copytree(relative_run, run)
    info = json.loads((run / "run_info.json").read_text())
    (run / "run_info.json").write_text(json.dumps({**info, "status": "running"}))  # interrupted (a complete run
    ck = RunDir(run).checkpoint  # has nothing to resume)
    raw = bytearray(ck.read_bytes())
    if damage == "empty":
        raw = bytearray()
    elif damage == "truncate":
        raw = raw[: len(raw) // 3]
    else:  # flip a bit in the middle of the file: inside the stored tensors, which most of it holds
        raw[len(raw) // 2] ^= 0x01
    ck.write_bytes(bytes(raw))
    before = (run / "trajectory.txt").read_bytes()
    proc = cli("run", "--resume", str(run), "--quiet", cwd=tmp_path)
    assert_one_line_error(proc, EXIT_ERROR, str(ck), needle, "--overwrite")
    assert (run / "trajectory.txt").read_bytes() == before


def test_a_failing_post_slam_step_still_writes_the_rest(work, tmp_path, monkeypatch):
    """Evaluation raises: trajectories, mesh and process metrics are written, the error is one RunError naming the
    step, the traceback is in log.jsonl, and `inrslam eval` afterwards completes the metrics."""
    import inrslam.eval.run as ev_run
    from inrslam.config import load_config
    from inrslam.errors import RunError
    from inrslam.runner import run_slam

    def broken(*a, **k):
        raise MemoryError("simulated")

    monkeypatch.setattr(ev_run, "evaluate_run", broken)
    cfg = load_config(preset="quick", overrides=[f"data.path={work / 'data' / 'room_rep'}", "data.max_frames=3",
                                                 "slam.init_iters=30", "output.tensorboard=false",
                                                 "eval.heldout_every=0", "eval.n_samples=2000", "threads=1"])
    out = tmp_path / "o"
    with pytest.raises(RunError, match=r"SLAM finished .* evaluation failed \(MemoryError: simulated\).*inrslam eval"):
        run_slam(cfg, out)
    rd = RunDir(out)
    assert rd.trajectory.is_file() and rd.mesh.is_file() and rd.read_metrics()["frames"] == 3
    assert rd.read_run_info()["status"] == "slam_done"
    errors = [json.loads(ln) for ln in rd.log.read_text().splitlines() if '"type": "error"' in ln]
    assert errors[0]["step"] == "evaluation" and "MemoryError" in errors[0]["traceback"]
    monkeypatch.undo()
    assert main(["eval", str(out), "--json"]) == 0
    assert rd.read_metrics()["ate_rmse_m"] is not None
