"""Command-line interface. Thin: every command calls a plain Python function.

    inrslam run --data builtin:room --out runs/room-paper
    inrslam scenes
    inrslam eval RUN_DIR | --traj EST --gt GT | --mesh REC.ply --gt-mesh GT.ply [--cameras GT_TRAJ]
    inrslam bench SPEC.yaml --out DIR [--jobs N] [--executor local|ray|slurm]
    inrslam report RUNS_DIR
    inrslam export SCENE --layout replica|tum --out DIR
    inrslam view RUN_DIR [RUN_DIR ...] [--port P]

Errors a user can fix print one line `inrslam COMMAND: error: ...` and exit 2; Ctrl-C prints how to resume and exits
130; `bench` exits 1 when some runs failed (docs/reliability.md).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import re
import shlex
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from inrslam.errors import InrslamError

TRAJ_MAX_DIFF = 0.02  # s, default `--max-diff` of `inrslam eval --traj/--gt`
EXIT_ERROR = 2  # a user-fixable error (one line on stderr)
EXIT_RUNS_FAILED = 1  # `bench`: the sweep went through but some runs failed
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT), as shells report it
DEVICE_RE = re.compile(r"auto|cpu|cuda(:\d+)?")
VIEWER_PORT = 8080
VIEWER_HOST = "127.0.0.1"
OVERRIDE_RE = re.compile(r"[A-Za-z_][\w.]*=.*", re.S)  # a config override KEY=VALUE
_T0 = time.perf_counter()  # the status lines count seconds from here (the command's start)


def _registry_help() -> tuple[str, str]:
    from inrslam.fields.registry import ENCODINGS
    from inrslam.rendering import RENDERERS

    return ENCODINGS.describe(), RENDERERS.describe()


def _shipped_presets() -> list[str]:
    """`inrslam.config.loader.preset_names` without importing the loader (it imports the whole config schema, with
    torch): the names of the shipped preset files."""
    return sorted(p.stem for p in (Path(__file__).parent / "configs").glob("*.yaml"))


def build_parser(registry_help: bool = True) -> argparse.ArgumentParser:
    """The argument parser. `registry_help=False` skips importing the encodings / renderers (torch) for the
    `run --encoding / --render` help text: `main` does so for every command but `run`, which keeps them quick."""
    if registry_help:
        from inrslam.config.loader import preset_names
    else:
        preset_names = _shipped_presets

    enc_help, ren_help = _registry_help() if registry_help else ("see `inrslam run --help`",) * 2
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
    r.add_argument("--preset", default=None, help=f"settings preset: {', '.join(preset_names())} (default paper)")
    r.add_argument("--config", help="YAML config file (may `inherit_from` another file or preset:NAME); "
                                    "a run's config.yaml reproduces that run")
    r.add_argument("--dataset", help="force the dataset layout instead of detecting it "
                                     "(replica, neuralrgbd, scannet, tum, 7scenes)")
    r.add_argument("--device", help="auto (default), cpu, cuda, cuda:N")
    r.add_argument("--seed", type=int, help="random seed")
    r.add_argument("--poses", help="map with given poses instead of tracking: 'gt' (the dataset's ground truth) or "
                   "a TUM trajectory file (associated by timestamp); sets slam.poses")
    r.add_argument("--resume", metavar="DIR", help="continue an interrupted run directory from its last checkpoint")
    r.add_argument("--overwrite", action="store_true", help="replace an existing run in --out")
    r.add_argument("--quiet", action="store_true", help="no progress bar or table")
    r.add_argument("--viewer", action="store_true", help="live view in the browser while the run goes (needs the "
                   "extra inrslam[viewer]; docs/viewer.md); in a terminal the finished run stays on view until Ctrl-C")
    r.add_argument("--viewer-port", type=int, default=VIEWER_PORT, help=f"port of --viewer (default {VIEWER_PORT})")
    r.add_argument("--viewer-host", default=VIEWER_HOST, help=f"address --viewer listens on (default {VIEWER_HOST})")
    r.add_argument("--viewer-mesh-every", type=int, default=20,
                   help="frames between two meshes of the live map (0 = none; default 20)")
    r.add_argument("overrides", nargs="*", help="config overrides KEY=VALUE")

    sub.add_parser("scenes", help="list the built-in scenes")

    c = sub.add_parser("config", help="print a resolved config as YAML (preset + file + overrides)")
    c.add_argument("--preset", default="paper", help=f"preset: {', '.join(preset_names())} (default paper)")
    c.add_argument("--config", help="YAML config file")
    c.add_argument("--plain", action="store_true", help="YAML without each key's help as a comment")
    c.add_argument("overrides", nargs="*", help="config overrides KEY=VALUE")

    e = sub.add_parser("eval", help="evaluate a run directory, or outside trajectories / meshes")
    e.add_argument("run_dir", nargs="?", help="run directory to (re)evaluate")
    e.add_argument("--traj", help="estimated trajectory (TUM format)")
    e.add_argument("--gt", help="ground-truth trajectory (TUM format)")
    e.add_argument("--align", default=None, choices=["se3", "sim3", "none"],
                   help="ATE alignment (default: the run's eval.align for RUN_DIR, se3 for --traj)")
    e.add_argument("--max-diff", type=_seconds, default=None,
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

    v = sub.add_parser("view", help="show run directories in the browser (mesh, trajectories, renders, metrics)",
                       description="Serve a browser viewer (viser) of one or more run directories: mesh (with the "
                                   "intermediate meshes as a timeline), estimated and ground-truth trajectories, "
                                   "keyframe frusta, the held-out renders and the metrics; several runs side by side "
                                   "with a comparison table. Needs the extra inrslam[viewer]; see docs/viewer.md.")
    v.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="run directories (inrslam run --out)")
    v.add_argument("--port", type=int, default=VIEWER_PORT, help=f"port (default {VIEWER_PORT}; the next free one "
                                                                   "if taken)")
    v.add_argument("--host", default=VIEWER_HOST, help=f"address to listen on (default {VIEWER_HOST}: this machine "
                                                        "only, reach it through an SSH tunnel; 0.0.0.0: every "
                                                        "interface)")

    x = sub.add_parser("export", help="write a built-in scene in the Replica or TUM RGB-D folder layout",
                       description="Render a built-in scene (`inrslam scenes`) and write it as a dataset folder that "
                                   "`inrslam run --data DIR` (and other tools) read: Replica (NICE-SLAM release) or "
                                   "TUM RGB-D layout, with the ground-truth mesh.")
    x.add_argument("scene", help="built-in scene name (or builtin:NAME)")
    x.add_argument("--layout", required=True, choices=["replica", "tum"], help="folder layout to write")
    x.add_argument("--out", required=True, help="new (or empty) folder to write")
    x.add_argument("--frames", type=int, default=0, help="number of frames (default: the scene's own length)")
    x.add_argument("--width", type=int, default=0, help="image width in pixels (default: the scene's)")
    x.add_argument("--height", type=int, default=0, help="image height in pixels (default: the scene's)")
    x.add_argument("--seed", type=int, default=0, help="seed of layout, camera path and sensor noise (default 0)")
    return p


def _check_out_dir(path: str | os.PathLike, flag: str = "--out") -> None:
    """InrslamError unless `path` is, or can be created as, a folder this process can write in. Creates nothing
    (a probe file in the nearest existing folder is made and removed)."""
    from inrslam.errors import ConfigError

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{flag} {p}: exists and is not a directory")
    base = p.absolute()
    while not base.exists():
        base = base.parent
    if not base.is_dir():
        raise ConfigError(f"{flag} {p}: {base} is a file, not a directory")
    try:
        fd, probe = tempfile.mkstemp(prefix=".inrslam-write-check-", dir=base)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ConfigError(f"{flag} {p}: cannot write in {base} ({e.strerror or e})") from None


def _check_device(cfg) -> None:
    """ConfigError for a device name other than auto, cpu, cuda, cuda:N, CUDA asked for but not available, or a
    CPU-only kernel (`numba`) asked for on another device."""
    from inrslam.errors import ConfigError
    from inrslam.slam.system import resolve_device

    if not DEVICE_RE.fullmatch(str(cfg.device)):
        raise ConfigError(f"config key 'device' (--device): expected auto, cpu, cuda or cuda:N, got {cfg.device!r}")
    device = resolve_device(cfg.device)
    if device.type != "cpu":
        for key, value in (("field.kernel", cfg.field.kernel), ("field.decoder_kernel", cfg.field.decoder_kernel),
                           ("loss.kernel", cfg.loss.kernel), ("render.kernel", cfg.render.kernel)):
            if value == "numba":  # str enums (KernelChoice) compare equal to their value
                raise ConfigError(f"config key '{key}': 'numba' runs on CPU tensors only and the run's device is "
                                  f"{device}; use auto (numba on CPU, torch elsewhere) or torch")


def _check_resumable_data(run_dir: str) -> None:
    """ConfigError when the run's config.yaml names its dataset folder by a relative path that does not exist from
    here (runs made before paths were recorded absolute)."""
    from inrslam.errors import ConfigError
    from inrslam.io.rundir import RunDir
    from inrslam.io.yamlfile import load_yaml

    cfg_path = RunDir(run_dir).config
    try:
        path = str(((load_yaml(cfg_path) or {}).get("data") or {}).get("path") or "")
    except (ConfigError, AttributeError):
        return  # resume_slam reports a missing / unreadable config.yaml itself
    if path and not path.startswith("builtin:") and not Path(path).expanduser().is_absolute() \
            and not Path(path).expanduser().is_dir():
        raise ConfigError(f"{cfg_path}: data.path {path!r} is relative and not found from {Path.cwd()}; resume from "
                          "the directory the run was started in, or set data.path in that file to the absolute folder")


def _run_command(args) -> int:
    from rich.console import Console

    console = Console(stderr=False)
    with _status_display(console, quiet=args.quiet) as display:
        return _run_with_display(args, console, display)


def _run_with_display(args, console, display: "_StatusDisplay | None") -> int:
    if display is not None:
        display.line("loading torch and the SLAM code")
    from inrslam.api import absolute_paths
    from inrslam.config.loader import load_config
    from inrslam.runner import resume_slam, run_slam

    live = None
    progress_cb = _frame_progress(display)
    if args.resume:
        given = [f"--{k.replace('_', '-')}" for k in ("data", "out", "encoding", "render", "max_frames", "config",
                                                      "dataset", "device", "seed", "poses", "preset")
                 if getattr(args, k) is not None] + (["--overwrite"] if args.overwrite else [])
        if given or args.overrides:
            raise InrslamError(f"inrslam run --resume continues a run with its own config.yaml; do not combine it "
                               f"with {', '.join(given + list(args.overrides))}")
        _check_resumable_data(args.resume)
        live = _start_live_viewer(args, console) if args.viewer else None
        run_dir = resume_slam(args.resume, progress=_chain(progress_cb, live))
    else:
        if not args.out:
            raise InrslamError("inrslam run: --out DIR is required (or --resume DIR)")
        _check_out_dir(args.out)
        ov = list(args.overrides)
        for flag, key in (("data", "data.path"), ("encoding", "field.encoding"), ("render", "render.name"),
                          ("max_frames", "data.max_frames"), ("dataset", "data.dataset"), ("device", "device"),
                          ("seed", "seed"), ("poses", "slam.poses")):
            val = getattr(args, flag)
            if val is not None:
                ov.append(f"{key}={val}")
        cfg = absolute_paths(load_config(args.config, preset=args.preset or "paper", overrides=ov))
        _check_registry_names(cfg)
        _check_device(cfg)
        live = _start_live_viewer(args, console) if args.viewer else None
        run_dir = run_slam(cfg, args.out, progress=_chain(progress_cb, live), overwrite=args.overwrite)
    if display is not None:
        display.close()
    if not args.quiet:
        _print_metrics(console, run_dir)
    if live is not None:
        _keep_viewing(live.server, run_dir, console)
    return 0


def _chain(*callbacks):
    """One progress callback calling each of `callbacks` that is not None (None if there is none)."""
    cbs = [cb for cb in callbacks if cb is not None]
    if not cbs:
        return None

    def cb(i: int, n: int, info: dict) -> None:
        for f in cbs:
            f(i, n, info)

    return cb


def _start_live_viewer(args, console):
    """`inrslam run --viewer`: a server and the `LiveViewer` progress callback drawing on it."""
    from inrslam.viewer.live import LiveViewer
    from inrslam.viewer.server import start_server, url_lines

    server = start_server(args.viewer_host, args.viewer_port)
    for line in url_lines(args.viewer_host, server.get_port()):
        console.print(line, highlight=False)
    return LiveViewer(server, mesh_every=args.viewer_mesh_every)


def _keep_viewing(server, run_dir: Path, console) -> None:
    """After `run --viewer`: the finished run replaces the live view, served until Ctrl-C when the command runs in
    a terminal (a script or background job just ends, as it would without --viewer)."""
    from inrslam.runner.loaded import load_run
    from inrslam.viewer.server import show_runs, stop_server

    if sys.stdin is None or not sys.stdin.isatty():
        stop_server(server)
        return
    viewer = show_runs(server, [load_run(run_dir)])
    console.print(f"viewer: showing the finished run at http://localhost:{viewer.port}; Ctrl-C to exit",
                  highlight=False)
    viewer.wait()


def _view_command(args) -> int:
    from inrslam.runner.loaded import load_run
    from inrslam.viewer.server import require_viser, serve, url_lines

    runs = [load_run(d) for d in args.run_dirs]
    require_viser()
    viewer = serve(runs, host=args.host, port=args.port)
    for line in url_lines(args.host, viewer.port):
        print(line)
    for k, c in enumerate(viewer.contents):
        print(f"  /run{k}: {c.root}" + (f" ({'; '.join(c.notes)})" if c.notes else ""))
    print("Ctrl-C to stop", flush=True)
    viewer.wait()
    return 0


def _check_registry_names(cfg) -> None:
    from inrslam.errors import ConfigError
    from inrslam.fields.registry import ENCODINGS
    from inrslam.rendering import RENDERERS

    if cfg.field.encoding not in ENCODINGS:
        raise ConfigError(f"config key 'field.encoding': {ENCODINGS.unknown_message(cfg.field.encoding)}")
    if cfg.render.name not in RENDERERS:
        raise ConfigError(f"config key 'render.name': {RENDERERS.unknown_message(cfg.render.name)}")


class _StatusDisplay:
    """What `inrslam run` / `inrslam eval` show while they work: one line per step, prefixed by the seconds since
    the command started, and a bar per counted step (initialisation, frames, held-out renders) with its ETA.

    Fed by the library's status records (`inrslam.status`, through `_StatusHandler`) and the SLAM loop's progress
    callback (`_frame_progress`). Bars stay on the terminal when done; a line after finished bars starts below them.
    """

    def __init__(self, console, t0: float | None = None, clock=time.perf_counter):
        self.console = console
        self.clock = clock
        self.t0 = _T0 if t0 is None else t0
        self.prog: Any = None  # rich Progress while bars are drawn
        self.tasks: dict[str, tuple[int, float, int]] = {}  # name -> (task id, time and count of its first update)

    def line(self, text: str) -> None:
        """A status line (below the bars when they are all done, above a bar still running)."""
        if self.prog is not None and all(t.finished for t in self.prog.tasks):
            self.close()
        self.console.print(f"[dim]{self.clock() - self.t0:6.1f} s[/dim]  {text}", highlight=False)

    def count(self, name: str, done: int, total: int, info: str = "") -> None:
        """Bar `name` at `done` of `total`; `info` is shown beside it, then the ETA."""
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        if self.prog is None:
            self.prog = Progress(TextColumn("[bold]{task.description:<7}"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=self.console,
                                 transient=False)
            self.prog.start()
            self.tasks = {}
        now = self.clock()
        if name not in self.tasks:
            self.tasks[name] = (self.prog.add_task(name, total=total, completed=done, info=""), now, done)
        task, t_first, first = self.tasks[name]
        eta = eta_text(now - t_first, done - first, total - done)
        self.prog.update(task, completed=done, total=total, info="  ".join(x for x in (info, eta) if x))

    def close(self) -> None:
        """Stop drawing the bars (they stay on the terminal)."""
        if self.prog is not None:
            self.prog.stop()
            self.prog = None


def eta_text(elapsed_s: float, done: int, remaining: int) -> str:
    """'ETA 2:05' from the rate so far (`done` steps in `elapsed_s`), 'ETA –' before the first step, '' at the end."""
    if remaining <= 0:
        return ""
    if done <= 0 or elapsed_s <= 0:
        return "ETA –"
    return f"ETA {_clock_time(elapsed_s / done * remaining)}"


def _clock_time(seconds: float) -> str:
    """'0:42', '12:05', '1:02:05'."""
    s = int(round(seconds))
    h, rest = divmod(s, 3600)
    return f"{h}:{rest // 60:02d}:{rest % 60:02d}" if h else f"{rest // 60}:{rest % 60:02d}"


class _StatusHandler(logging.Handler):
    """Hands the library's status records (`inrslam.status`) to a `_StatusDisplay`."""

    def __init__(self, display: _StatusDisplay):
        super().__init__(logging.INFO)
        self.display = display

    def emit(self, record: logging.LogRecord) -> None:
        from inrslam.status import progress_of

        try:
            counted = progress_of(record)
            if counted is None:
                self.display.line(record.getMessage())
            else:
                self.display.count(record.getMessage(), *counted)
        except Exception:  # noqa: BLE001 - a display problem must never stop a run
            self.handleError(record)


@contextmanager
def _status_display(console, quiet: bool) -> Iterator[_StatusDisplay | None]:
    """A `_StatusDisplay` receiving the "inrslam" status records while the block runs (None when `quiet`)."""
    if quiet:
        yield None
        return
    from inrslam.status import LOGGER

    display = _StatusDisplay(console)
    handler = _StatusHandler(display)
    log = logging.getLogger(LOGGER)
    level = log.level
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        yield display
    finally:
        log.removeHandler(handler)
        log.setLevel(level)
        display.close()


def _frame_progress(display: _StatusDisplay | None):
    """The SLAM loop's progress callback drawing the frame bar on `display` (None without a display): frame, frames
    per second and the ATE so far (every 10 frames, with ground truth), then the ETA."""
    if display is None:
        return None
    state: dict = {"t0": None, "start": 0, "ate": None}

    def cb(i: int, n: int, info: dict) -> None:
        if state["t0"] is None:
            state["t0"], state["start"] = time.perf_counter(), i
        if "gt" in info and (i % 10 == 0 or i == n - 1):
            state["ate"] = _current_ate(info["est"], info["gt"]) or state["ate"]
        text = f"frame {i}"
        if i > state["start"]:
            text += f"  {(i - state['start']) / max(time.perf_counter() - state['t0'], 1e-9):.2f} fps"
        if state["ate"] is not None:
            text += f"  ATE {state['ate'] * 100:.2f} cm"
        display.count("SLAM", i + 1, n, info=text)

    return cb


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

    rd = RunDir(run_dir)
    metrics = rd.read_metrics() or {}
    console.print(format_table(metrics))
    if metrics.get("lost_frames"):
        console.print(f"[yellow]warning:[/yellow] tracking was lost on {metrics['lost_frames']} frame(s) "
                      f"('tracking_lost' in log.jsonl): poses after them are unreliable; try a smaller data.stride "
                      f"or slam.lost.recover=true")
    pictures = [p.name + ("/" if p.is_dir() else "") for p in (rd.trajectory_plot, rd.mesh_thumbnail, rd.renders)
                if p.exists()]
    outputs = [name for name in ("trajectory.txt", "mesh.ply", "metrics.json", "log.jsonl", "config.yaml")
               if (run_dir / name).exists()]
    console.print(f"Outputs in [bold]{run_dir}[/bold]: {', '.join(outputs)}"
                  + (f"; pictures: {', '.join(pictures)}" if pictures else ""))


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
    if args.plain:
        print(dump_config(cfg), end="")
    else:
        from inrslam.config.keyhelp import commented_config

        print(commented_config(cfg), end="")
    return 0


def _eval_command(args) -> int:
    import json

    from rich.console import Console

    from inrslam.eval import run as ev

    console = Console()
    if args.run_dir:
        from inrslam.malloc_env import tune_malloc

        tune_malloc()  # the held-out renders allocate as a run does (inrslam.malloc_env)
        with _status_display(console, quiet=args.json):
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
            intr = _intrinsics_arg(args.intrinsics)
        metrics = ev.eval_mesh_files(args.mesh, args.gt_mesh, cameras_path=args.cameras, intrinsics=intr,
                                     icp=bool(args.icp), virtual_cameras=args.virtual_cameras, cull_gt=args.cull_gt)
    else:
        raise InrslamError("inrslam eval: give a RUN_DIR, or --traj/--gt, or --mesh/--gt-mesh")
    if args.json:
        print(json.dumps(metrics, indent=2, default=str))
    else:
        console.print(ev.format_table(metrics))
    return 0


def _seconds(text: str) -> float:
    """argparse type of a time tolerance: a finite number of seconds >= 0."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"expected a number of seconds >= 0, got {text!r}")
    return v


def _intrinsics_arg(text: str):
    """`Intrinsics` of `--intrinsics fx,fy,cx,cy,width,height`, or a one-line InrslamError saying what is wrong."""
    from inrslam.geometry.intrinsics import Intrinsics

    usage = f"--intrinsics expects fx,fy,cx,cy,width,height (numbers; width and height whole pixels), got {text!r}"
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise InrslamError(usage) from None
    if len(vals) != 6 or not all(math.isfinite(v) for v in vals) or any(v != int(v) for v in vals[4:]):
        raise InrslamError(usage)
    return Intrinsics(vals[0], vals[1], vals[2], vals[3], int(vals[4]), int(vals[5])).checked("--intrinsics")


def _run_eval_config(args):
    """Evaluation protocol of `inrslam eval RUN_DIR`: the run's own `eval` section (RUN_DIR/config.yaml, resolved
    without a preset, as it was written), or the default protocol when the run has no config.yaml; then the flags
    the user gave explicitly (--align, --max-diff, --icp, --virtual-cameras, --cull-gt) on top."""
    from dataclasses import replace

    from inrslam.config.loader import build_config
    from inrslam.errors import ConfigError
    from inrslam.eval.config import Alignment, EvalConfig
    from inrslam.io.rundir import RunDir
    from inrslam.io.yamlfile import load_yaml

    cfg_path = RunDir(args.run_dir).config
    cfg = EvalConfig()
    if cfg_path.is_file():  # only the `eval:` section matters here (other sections may come from older versions)
        data = load_yaml(cfg_path) or {}
        section = (data.get("eval") if isinstance(data, dict) else None) or {}
        if not isinstance(section, dict):
            raise ConfigError(f"{cfg_path}: eval: expected a mapping, got {type(section).__name__}")
        cfg = build_config(EvalConfig, [(section, f"{cfg_path} (eval section)")])
    if args.align is not None:
        cfg = replace(cfg, align=Alignment(args.align))
    if args.max_diff is not None:
        cfg = replace(cfg, max_time_diff=float(args.max_diff))
    if args.icp is not None:
        cfg = replace(cfg, icp=bool(args.icp))
    if args.virtual_cameras:
        cfg = replace(cfg, virtual_cameras=os.path.abspath(args.virtual_cameras))
    if args.cull_gt:
        cfg = replace(cfg, cull_gt=True)
    return cfg


def _bench_command(args) -> int:
    from inrslam.bench.sweep import run_sweep

    if not args.dry_run:
        _check_out_dir(args.out)
    res = run_sweep(args.spec, args.out, jobs=args.jobs, executor=args.executor, address=args.address,
                    partition=args.partition, time_min=args.time, dry_run=args.dry_run)
    if res.failed:
        print(f"inrslam bench: {len(res.failed)} of {len(res.runs)} runs failed (reasons in "
              f"{Path(args.out) / '<run>' / 'error.txt'}); the same command retries them", file=sys.stderr)
        return EXIT_RUNS_FAILED
    return 0


def _report_command(args) -> int:
    from inrslam.bench.leaderboard import collect_runs
    from inrslam.bench.report import build_report, status_summary

    if Path(args.runs_dir).is_dir():
        _check_out_dir(args.out or Path(args.runs_dir) / "report")
    out = build_report(args.runs_dir, args.out)
    print(f"report written to {out} ({status_summary(collect_runs(args.runs_dir, exclude=out))})")
    return 0


def _export_command(args) -> int:
    from inrslam.errors import ConfigError
    from inrslam.scenes import SceneConfig, export_replica, export_tum, load_scene

    out = Path(args.out)
    _check_out_dir(out)
    if out.is_dir() and any(out.iterdir()):
        raise ConfigError(f"--out {out}: exists and is not empty (give a new or empty folder)")
    name = args.scene.removeprefix("builtin:")
    dataset = load_scene(name, SceneConfig(frames=args.frames, width=args.width, height=args.height, seed=args.seed))
    (export_replica if args.layout == "replica" else export_tum)(dataset, out)
    print(f"exported builtin:{name} ({len(dataset)} frames, {args.layout} layout) to {out}; "
          f"run it with: inrslam run --data {out} --out RUN_DIR")
    return 0


COMMANDS = {"run": _run_command, "scenes": _scenes_command, "config": _config_command, "eval": _eval_command,
            "bench": _bench_command, "report": _report_command, "export": _export_command, "view": _view_command}


def _interrupted_message(args, stopped: str = "interrupted") -> str:
    """What Ctrl-C left behind and the command that continues it (one line), starting with `stopped`."""
    from inrslam.io.rundir import RunDir

    if args.command == "run":
        out = args.resume or args.out
        rd = RunDir(out) if out else None
        if rd is not None and rd.has_checkpoint():
            return f"{stopped}; the run can be resumed from its last checkpoint: inrslam run --resume {out}"
        if rd is not None and rd.holds_run():
            return (f"{stopped} before the first checkpoint; start it again with: inrslam run --config "
                    f"{rd.config} --out {out} --overwrite")
        return f"{stopped} before the run started; nothing was written"
    if args.command == "bench":  # the same command (executor flags included) resumes a sweep
        argv = [str(args.spec), "--out", str(args.out)] + (["--jobs", str(args.jobs)] if args.jobs != 1 else [])
        for flag, value in (("--executor", args.executor if args.executor != "local" else None),
                            ("--address", args.address), ("--partition", args.partition),
                            ("--time", args.time if args.executor == "slurm" and args.time != 60 else None)):
            argv += [flag, str(value)] if value is not None else []
        return (f"{stopped}; finished runs are kept and checkpointed ones continue: resume the sweep with "
                f"inrslam bench {shlex.join(argv)}")
    if args.command == "export":
        return f"{stopped}; nothing was exported to {args.out} (an export is written as a whole)"
    return stopped


def _one_line_warnings() -> None:
    """Our warnings (InrslamWarning) print as `inrslam: warning: ...`, without a source line."""
    import warnings

    from inrslam.errors import InrslamWarning

    default = warnings.formatwarning

    def fmt(message, category, filename, lineno, line=None):
        if issubclass(category, InrslamWarning):
            return f"inrslam: warning: {message}\n"
        return default(message, category, filename, lineno, line)

    warnings.formatwarning = fmt  # type: ignore[assignment]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    _one_line_warnings()
    # the registries' help text imports torch: only for `run --help`, so `run` can say what it loads first
    parser = build_parser(registry_help=argv[:1] == ["run"] and ("-h" in argv or "--help" in argv))
    args, extra = parser.parse_known_args(argv)
    # KEY=VALUE overrides anywhere on the line: argparse takes one run of positionals, the later ones come back here
    if extra and getattr(args, "overrides", None) is not None and all(OVERRIDE_RE.fullmatch(x) for x in extra):
        args.overrides = list(args.overrides) + extra
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    from inrslam.interrupts import Terminated, defer_interrupts_in_jit

    try:
        with defer_interrupts_in_jit():
            return COMMANDS[args.command](args)
    except InrslamError as e:
        print(f"inrslam {args.command}: error: {e}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as e:  # the machine's side (disk full, file too large, permissions): its file and reason
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        print(f"inrslam {args.command}: error: {where}{e.strerror or e} (finished output is kept; files are written "
              "whole or not at all)", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM / SIGHUP (`Terminated`): the same unwinding
        message = _interrupted_message(args, f"terminated by {e}" if isinstance(e, Terminated) else "interrupted")
        try:
            print(f"inrslam {args.command}: {message}", file=sys.stderr)
        except OSError:  # a closed terminal (SIGHUP) takes no more output
            pass
        return 128 + e.signum if isinstance(e, Terminated) else EXIT_INTERRUPTED  # as a shell reports it


if __name__ == "__main__":
    sys.exit(main())
