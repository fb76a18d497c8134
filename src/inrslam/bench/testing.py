"""Cheap stand-ins for a SLAM run, to test sweeps and reports without running SLAM.

`fake_run` is a run function (see `inrslam.bench.worker`): it writes a complete, self-describing fake run directory
with deterministic metrics. An encoding name containing "fail" raises; one containing "crash" kills the process.
Every call appends a line to `<out>/fake_executions.log`, so tests can count how many runs executed.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np
import yaml

from inrslam.io.atomic import append_jsonl, write_json, write_text

METRIC_KEYS = ("ate_rmse_m", "ate_mean_m", "rpe_trans_m", "rpe_rot_deg", "psnr_db", "ssim", "depth_l1_m",
               "psnr_process_db", "depth_l1_process_m", "acc_m", "comp_m", "comp_ratio", "track_ms_per_frame",
               "map_ms_per_call", "model_size_mb", "peak_memory_mb", "frames", "wall_time_s")


def fake_metrics(encoding: str, render: str, scene: str, seed: int, frames: int = 10) -> dict:
    """Deterministic plausible metrics for one combination (same inputs -> same numbers)."""
    rng = np.random.default_rng(zlib.crc32(f"{scene}|{encoding}|{render}|{seed}".encode()))
    return {
        "ate_rmse_m": float(rng.uniform(0.01, 0.05)), "ate_mean_m": float(rng.uniform(0.01, 0.04)),
        "rpe_trans_m": float(rng.uniform(0.001, 0.01)), "rpe_rot_deg": float(rng.uniform(0.1, 1.0)),
        "psnr_db": float(rng.uniform(20, 30)), "ssim": float(rng.uniform(0.6, 0.9)),
        "depth_l1_m": float(rng.uniform(0.01, 0.05)), "psnr_process_db": float(rng.uniform(20, 30)),
        "depth_l1_process_m": float(rng.uniform(0.01, 0.05)), "acc_m": float(rng.uniform(0.01, 0.05)),
        "comp_m": float(rng.uniform(0.02, 0.08)), "comp_ratio": float(rng.uniform(0.6, 0.9)),
        "track_ms_per_frame": float(rng.uniform(100, 400)), "map_ms_per_call": float(rng.uniform(200, 900)),
        "model_size_mb": float(10 ** rng.uniform(-1, 3)), "peak_memory_mb": float(rng.uniform(500, 2000)),
        "frames": frames, "wall_time_s": float(rng.uniform(1, 10)), "encoding": encoding, "render": render,
    }


def _tum(path: Path, ts: np.ndarray, pos: np.ndarray) -> None:
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    lines += [f"{t:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} 0 0 0 1" for t, p in zip(ts, pos)]
    write_text(path, "\n".join(lines) + "\n")


def write_fake_run(run_dir: str | os.PathLike, encoding: str, render: str, scene: str = "room", seed: int = 0,
                   metrics: dict | None = None, frames: int = 10, status: str = "complete",
                   preset: str | None = None, noise: float = 0.01, machine: dict | None = None,
                   threads: int | None = None) -> Path:
    """Write a run directory as `inrslam run` would (config.yaml, run_info.json, metrics.json, trajectories, log);
    run_info.json holds `machine` and `threads` when given."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = scene if (":" in scene or "/" in scene) else f"builtin:{scene}"
    cfg = {"data": {"path": path, "max_frames": frames}, "field": {"encoding": encoding}, "render": {"name": render},
           "eval": {"align": "se3"}, "seed": seed}
    write_text(run_dir / "config.yaml", yaml.safe_dump(cfg, sort_keys=False))
    if preset is not None:
        write_json(run_dir / "bench.json", {"preset": preset, "scene": scene, "encoding": encoding, "render": render,
                                            "seed": seed})
    rng = np.random.default_rng(zlib.crc32(f"traj|{scene}|{encoding}|{render}|{seed}".encode()))
    ts = np.arange(frames) / 30.0
    gt = np.stack([np.cos(ts), np.sin(ts), 0.1 * ts], axis=1)
    est = gt + rng.normal(0.0, noise, gt.shape)
    _tum(run_dir / "trajectory.txt", ts, est)
    _tum(run_dir / "trajectory_gt.txt", ts, gt)
    (run_dir / "log.jsonl").write_text("")
    for i in range(frames):
        append_jsonl(run_dir / "log.jsonl", {"type": "track", "frame": i, "loss": float(rng.uniform())})
    m = fake_metrics(encoding, render, scene, seed, frames) if metrics is None else dict(metrics)
    m.setdefault("encoding", encoding)
    m.setdefault("render", render)
    write_json(run_dir / "metrics.json", m)
    info: dict = {"status": status, "encoding": encoding, "render": render,
                  "dataset": {"kind": "builtin", "root": path, "frames": frames}}
    if machine is not None:
        info["machine"] = machine
    if threads is not None:
        info["threads"] = threads
    write_json(run_dir / "run_info.json", info)
    return run_dir


def fake_run(run: dict, run_dir: Path) -> dict:
    """Run function writing a fake complete run for `run` (a `RunSpec.to_dict()`); see the module docstring."""
    run_dir = Path(run_dir)
    with open(run_dir.parent / "fake_executions.log", "a") as f:
        f.write(run["name"] + "\n")
    if "crash" in run["encoding"]:
        os._exit(3)
    if "fail" in run["encoding"]:
        raise RuntimeError(f"fake failure of {run['name']}")
    write_fake_run(run_dir, run["encoding"], run["render"], run["scene"], run["seed"])  # bench.json: worker
    return {"fake": True}


def executed_runs(out_dir: str | os.PathLike) -> list[str]:
    """Names of the runs `fake_run` executed in `out_dir`, in order (one per call)."""
    log = Path(out_dir) / "fake_executions.log"
    return log.read_text().split() if log.is_file() else []
