"""Command-line interface. Thin: every command calls a plain Python function.

    inrslam run --data builtin:room --out runs/room
    inrslam scenes
    inrslam eval RUN_DIR | --traj EST --gt GT | --mesh REC.ply --gt-mesh GT.ply [--cameras GT_TRAJ]
    inrslam bench SPEC.yaml --out DIR [--jobs N] [--executor local|ray|slurm]
    inrslam report RUNS_DIR
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from inrslam.errors import InrslamError

TRAJ_MAX_DIFF = 0.02  # s, default `--max-diff` of `inrslam eval --traj/--gt`


def _registry_help() -> tuple[str, str]:
    from inrslam.fields.registry import ENCODINGS
    from inrslam.rendering import RENDERERS

    return ENCODINGS.describe(), RENDERERS.describe()


def build_parser() -> argparse.ArgumentParser:
    from inrslam.config.loader import preset_names

    enc_help, ren_help = _registry_help()
    p = argparse.ArgumentParser(prog="inrslam", description="Neural implicit RGB-D SLAM: run, evaluate, benchmark.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    r = sub.add_parser("run", help="run SLAM on a dataset or built-in scene",
                       description="Run SLAM and write a run directory (trajectory, mesh, metrics, logs, checkpoints).",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="Overrides: any config key as KEY=VALUE, e.g. slam.track_iters=10 field.levels=16 "
                              "data.builtin.frames=50. Print every key with `inrslam config`; see docs/config.md.")
    r.add_argument("--data", help="dataset folder (Replica, NeuralRGBD, ScanNet, TUM, 7-Scenes layouts) or "
                                  "builtin:NAME (see `inrslam scenes`); default builtin:room")
    r.add_argument("--out", help="output run directory (required unless --resume)")
    r.add_argument("--encoding", help=f"scene representation F: {enc_help}")
    r.add_argument("--render", help=f"rendering function G: {ren_help}")
    r.add_argument("--max-frames", type=int, help="process at most N frames (0 = all)")
    r.add_argument("--preset", default="paper", help=f"settings preset: {', '.join(preset_names())} (default paper)")
    r.add_argument("--config", help="YAML config file (may `inherit_from` another file or preset:NAME); "
                                    "a run's config.yaml reproduces that run")
    r.add_argument("--dataset", help="force the dataset layout instead of detecting it "
                                     "(replica, neuralrgbd, scannet, tum, 7scenes)")
    r.add_argument("--device", help="auto (default), cpu, cuda, cuda:N")
    r.add_argument("--seed", type=int, help="random seed")
    r.add_argument("--resume", metavar="DIR", help="continue an interrupted run directory from its last checkpoint")
    r.add_argument("--overwrite", action="store_true", help="replace an existing run in --out")
    r.add_argument("--quiet", action="store_true", help="no progress bar or table")
    r.add_argument("overrides", nargs="*", help="config overrides KEY=VALUE")

    sub.add_parser("scenes", help="list the built-in scenes")

    c = sub.add_parser("config", help="print a resolved config as YAML (preset + file + overrides)")
    c.add_argument("--preset", default="paper", help=f"preset: {', '.join(preset_names())} (default paper)")
    c.add_argument("--config", help="YAML config file")
    c.add_argument("overrides", nargs="*", help="config overrides KEY=VALUE")

    e = sub.add_parser("eval", help="evaluate a run directory, or outside trajectories / meshes")
    e.add_argument("run_dir", nargs="?", help="run directory to (re)evaluate")
    e.add_argument("--traj", help="estimated trajectory (TUM format)")
    e.add_argument("--gt", help="ground-truth trajectory (TUM format)")
    e.add_argument("--align", default=None, choices=["se3", "sim3", "none"],
                   help="ATE alignment (default: the run's eval.align for RUN_DIR, se3 for --traj)")
    e.add_argument("--max-diff", type=float, default=None,
                   help="timestamp association tolerance in seconds (default: the run's eval.max_time_diff for "
                        f"RUN_DIR, {TRAJ_MAX_DIFF} for --traj)")
    e.add_argument("--mesh", help="reconstructed mesh (PLY/OBJ)")
    e.add_argument("--gt-mesh", help="ground-truth mesh")
    e.add_argument("--cameras", help="GT camera poses (TUM file) for frustum + occlusion culling")
    e.add_argument("--intrinsics", help="fx,fy,cx,cy,width,height of the culling cameras")
    e.add_argument("--virtual-cameras", help="extra (virtual) camera poses for culling, TUM file (Co-SLAM variant)")
    e.add_argument("--cull-gt", action="store_true", help="also cull the GT mesh with the same cameras")
    e.add_argument("--icp", action="store_true", default=None,
                   help="ICP-align the reconstruction first (default: the run's eval.icp for RUN_DIR, off for --mesh)")
    e.add_argument("--json", action="store_true", help="print JSON instead of a table")

    b = sub.add_parser("bench", help="run a sweep of F x G x scenes and build the leaderboard")
    b.add_argument("spec", help="sweep spec YAML (see src/inrslam/bench/specs/)")
    b.add_argument("--out", required=True, help="folder holding one run directory per combination")
    b.add_argument("--jobs", type=int, default=1, help="parallel local processes")
    b.add_argument("--executor", default="local", help="local (default), ray, slurm")
    b.add_argument("--address", help="Ray cluster address (executor ray)")
    b.add_argument("--partition", help="SLURM partition (executor slurm)")
    b.add_argument("--time", type=int, default=60, help="SLURM time limit per run in minutes")
    b.add_argument("--dry-run", action="store_true", help="list the runs without running them")

    rep = sub.add_parser("report", help="aggregate run directories into leaderboards, plots and an HTML report")
    rep.add_argument("runs_dir", help="folder containing run directories")
    rep.add_argument("--out", help="report folder (default RUNS_DIR/report)")
    return p


def _run_command(args) -> int:
    from rich.console import Console

    from inrslam.config.loader import load_config
    from inrslam.runner import resume_slam, run_slam

    console = Console(stderr=False)
    progress_cb, finish = _progress(console, quiet=args.quiet)
    if args.resume:
        given = [f"--{k.replace('_', '-')}" for k in ("data", "out", "encoding", "render", "max_frames", "config",
                                                      "dataset", "device", "seed") if getattr(args, k) is not None]
        if given or args.overrides:
            raise InrslamError(f"inrslam run --resume continues a run with its own config.yaml; do not combine it "
                               f"with {', '.join(given + list(args.overrides))}")
        run_dir = resume_slam(args.resume, progress=progress_cb)
    else:
        if not args.out:
            raise InrslamError("inrslam run: --out DIR is required (or --resume DIR)")
        ov = list(args.overrides)
        for flag, key in (("data", "data.path"), ("encoding", "field.encoding"), ("render", "render.name"),
                          ("max_frames", "data.max_frames"), ("dataset", "data.dataset"), ("device", "device"),
                          ("seed", "seed")):
            val = getattr(args, flag)
            if val is not None:
                ov.append(f"{key}={val}")
        cfg = load_config(args.config, preset=args.preset, overrides=ov)
        _check_registry_names(cfg)
        run_dir = run_slam(cfg, args.out, progress=progress_cb, overwrite=args.overwrite)
    finish()
    if not args.quiet:
        _print_metrics(console, run_dir)
    return 0


def _check_registry_names(cfg) -> None:
    from inrslam.errors import ConfigError
    from inrslam.fields.registry import ENCODINGS
    from inrslam.rendering import RENDERERS

    if cfg.field.encoding not in ENCODINGS:
        raise ConfigError(f"config key 'field.encoding': {ENCODINGS.unknown_message(cfg.field.encoding)}")
    if cfg.render.name not in RENDERERS:
        raise ConfigError(f"config key 'render.name': {RENDERERS.unknown_message(cfg.render.name)}")


def _progress(console, quiet: bool):
    if quiet:
        return None, lambda: None
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    prog = Progress(TextColumn("[bold]SLAM"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[info]}"),
                    TimeElapsedColumn(), console=console, transient=False)
    state = {"task": None, "t0": None, "ate": None}

    def cb(i: int, n: int, info: dict) -> None:
        if state["task"] is None:
            prog.start()
            state["task"] = prog.add_task("slam", total=n, info="")
            state["t0"] = time.perf_counter()
            state["start"] = i
        if "gt" in info and (i % 10 == 0 or i == n - 1):
            state["ate"] = _current_ate(info["est"], info["gt"]) or state["ate"]
        done = i + 1 - state["start"]
        fps = done / max(time.perf_counter() - state["t0"], 1e-9)
        text = f"frame {i}  {fps:.2f} fps"
        if state["ate"] is not None:
            text += f"  ATE {state['ate'] * 100:.2f} cm"
        prog.update(state["task"], completed=i + 1, info=text)

    def finish() -> None:
        if state["task"] is not None:
            prog.stop()

    return cb, finish


def _current_ate(est, gt) -> float | None:
    """ATE RMSE (m) of the trajectory so far, or None with fewer than 3 frames with ground truth."""
    import numpy as np

    from inrslam.eval.trajectory import ate

    est = est.double().cpu().numpy()
    if np.isfinite(gt).all(axis=(1, 2)).sum() < 3:
        return None
    return float(ate(est, gt)["rmse"])


def _print_metrics(console, run_dir: Path) -> None:
    from inrslam.eval.run import format_table
    from inrslam.io.rundir import RunDir

    metrics = RunDir(run_dir).read_metrics() or {}
    console.print(format_table(metrics))
    console.print(f"Outputs in [bold]{run_dir}[/bold]: trajectory.txt, mesh.ply, metrics.json, log.jsonl, config.yaml")


def _scenes_command(args) -> int:
    from rich.console import Console
    from rich.table import Table

    from inrslam.scenes import list_scenes

    t = Table(title="Built-in scenes (use --data builtin:NAME)")
    t.add_column("name")
    t.add_column("description")
    for name, desc in list_scenes():
        t.add_row(name, desc)
    Console().print(t)
    return 0


def _config_command(args) -> int:
    from inrslam.config.loader import dump_config, load_config

    cfg = load_config(args.config, preset=args.preset, overrides=list(args.overrides))
    _check_registry_names(cfg)
    print(dump_config(cfg), end="")
    return 0


def _eval_command(args) -> int:
    import json

    from rich.console import Console

    from inrslam.eval import run as ev

    console = Console()
    if args.run_dir:
        metrics = ev.evaluate_run(args.run_dir, _run_eval_config(args))
    elif args.traj or args.gt:
        if not (args.traj and args.gt):
            raise InrslamError("inrslam eval: --traj and --gt go together")
        metrics = ev.eval_trajectory_files(args.traj, args.gt, align=args.align or "se3",
                                           max_diff=TRAJ_MAX_DIFF if args.max_diff is None else args.max_diff)
    elif args.mesh or args.gt_mesh:
        if not (args.mesh and args.gt_mesh):
            raise InrslamError("inrslam eval: --mesh and --gt-mesh go together")
        intr = None
        if args.intrinsics:
            vals = [float(x) for x in args.intrinsics.split(",")]
            if len(vals) != 6:
                raise InrslamError("--intrinsics expects fx,fy,cx,cy,width,height")
            from inrslam.geometry.intrinsics import Intrinsics

            intr = Intrinsics(vals[0], vals[1], vals[2], vals[3], int(vals[4]), int(vals[5]))
        metrics = ev.eval_mesh_files(args.mesh, args.gt_mesh, cameras_path=args.cameras, intrinsics=intr,
                                     icp=bool(args.icp), virtual_cameras=args.virtual_cameras, cull_gt=args.cull_gt)
    else:
        raise InrslamError("inrslam eval: give a RUN_DIR, or --traj/--gt, or --mesh/--gt-mesh")
    if args.json:
        print(json.dumps(metrics, indent=2, default=str))
    else:
        console.print(ev.format_table(metrics))
    return 0


def _run_eval_config(args):
    """Evaluation protocol of `inrslam eval RUN_DIR`: the run's own `eval` section (RUN_DIR/config.yaml, resolved
    without a preset, as it was written), or the default protocol when the run has no config.yaml; then the flags
    the user gave explicitly (--align, --max-diff, --icp, --virtual-cameras, --cull-gt) on top."""
    from dataclasses import replace

    import yaml

    from inrslam.config.loader import build_config
    from inrslam.eval.config import Alignment, EvalConfig

    from inrslam.io.rundir import RunDir

    cfg_path = RunDir(args.run_dir).config
    cfg = EvalConfig()
    if cfg_path.is_file():  # only the `eval:` section matters here (other sections may come from older versions)
        section = (yaml.safe_load(cfg_path.read_text()) or {}).get("eval") or {}
        cfg = build_config(EvalConfig, [(section, f"{cfg_path} (eval section)")])
    if args.align is not None:
        cfg = replace(cfg, align=Alignment(args.align))
    if args.max_diff is not None:
        cfg = replace(cfg, max_time_diff=float(args.max_diff))
    if args.icp is not None:
        cfg = replace(cfg, icp=bool(args.icp))
    if args.virtual_cameras:
        cfg = replace(cfg, virtual_cameras=str(args.virtual_cameras))
    if args.cull_gt:
        cfg = replace(cfg, cull_gt=True)
    return cfg


def _bench_command(args) -> int:
    from inrslam.bench.sweep import run_sweep

    run_sweep(args.spec, args.out, jobs=args.jobs, executor=args.executor, address=args.address,
              partition=args.partition, time_min=args.time, dry_run=args.dry_run)
    return 0


def _report_command(args) -> int:
    from inrslam.bench.report import build_report

    out = build_report(args.runs_dir, args.out)
    print(f"report written to {out}")
    return 0


COMMANDS = {"run": _run_command, "scenes": _scenes_command, "config": _config_command, "eval": _eval_command,
            "bench": _bench_command, "report": _report_command}


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except InrslamError as e:
        print(f"inrslam {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
