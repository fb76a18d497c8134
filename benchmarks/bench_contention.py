"""Per-frame SLAM time on a shared machine (issue #16): idle, and beside 1 and 2 competing CPU-bound processes,
under each OpenMP wait policy, in one run. Prints a table of seconds per frame and ratios; never asserted in tests.

    python benchmarks/bench_contention.py                               # dense, 12 frames, busy-loop competitors
    python benchmarks/bench_contention.py --competitor slam --competitors 0 1   # beside a second inrslam run
    python benchmarks/bench_contention.py --policies passive --encoding hash
    python benchmarks/bench_contention.py --frames 30 --late 12 --competitors 1   # competitors arrive mid-run

Policies: `adaptive` is what `import inrslam` chooses with GNU libgomp (the runtime's default, throttled to passive
waits while other processes load the machine: `inrslam.omp_env.load_guard`); `passive` INRSLAM_OMP_WAIT=passive
(OMP_WAIT_POLICY=PASSIVE: a thread waiting at a barrier sleeps; inrslam's default before `adaptive`); `default`
INRSLAM_OMP_WAIT=runtime, the OpenMP runtime's own default, never throttled (spin for a while, then sleep);
`active` OMP_WAIT_POLICY=ACTIVE (spin, never sleep); `spin=N` the runtime's default with libgomp's spin count
GOMP_SPINCOUNT=N. Each measurement is a fresh process, so the runtime reads the policy as it loads.
Competitors: `busy` = a single-threaded Python busy loop per competitor; `slam` = another inrslam run of the same
settings per competitor (under the same policy).
Per-frame time = (tracking + mapping time) / tracked frames, as in bench_slam.py (initialisation excluded).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

CHILD = r"""
import json, sys, time
from inrslam.config import load_config
from inrslam.datasets import open_dataset
from inrslam.fields.kernels.threads import resolve_threads, thread_scope
from inrslam.omp_env import load_guard, wait_policy
from inrslam.slam.system import SlamSystem
enc, frames, init_iters, repeat = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
cfg = load_config(preset="paper", overrides=[
    "data.path=builtin:room", f"data.max_frames={frames}", f"field.encoding={enc}", f"slam.init_iters={init_iters}",
    "slam.checkpoint_every=0", "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false"])
while True:
    with thread_scope(resolve_threads(0)), load_guard():
        s = SlamSystem(cfg, open_dataset(cfg.data)).run()
    n = max(len(s.state.track_ms), 1)
    print(json.dumps({"per_frame_s": (sum(s.state.track_ms) + sum(s.state.map_ms)) / n / 1e3,
                      "init_s_per_iter": s.state.init_ms / 1e3 / max(init_iters, 1), "omp": wait_policy()}),
          flush=True)
    if not repeat:
        break
"""

BUSY = "while True: pass"


def environment(policy: str) -> dict:
    env = dict(os.environ)
    for key in ("OMP_WAIT_POLICY", "INRSLAM_OMP_WAIT", "GOMP_SPINCOUNT"):
        env.pop(key, None)
    if policy == "active":  # spin at every barrier, never sleep
        env["OMP_WAIT_POLICY"] = "ACTIVE"
    elif policy in ("passive", "default"):
        env["INRSLAM_OMP_WAIT"] = "passive" if policy == "passive" else "runtime"
    elif policy.startswith("spin="):  # the runtime's default policy with another spin count (libgomp)
        env["INRSLAM_OMP_WAIT"] = "runtime"
        env["GOMP_SPINCOUNT"] = policy[len("spin="):]
    return env


def child(policy: str, args, repeat: bool) -> list[str]:
    return [sys.executable, "-c", CHILD, args.encoding, str(args.frames), str(args.init_iters), "1" if repeat else "0",
            policy]


def measure(policy: str, competitors: int, kind: str, args) -> dict:
    """One SLAM run's per-frame time beside `competitors` processes of `kind`."""
    env = environment(policy)
    comp: list[subprocess.Popen] = []

    def start_competitors() -> None:
        for _ in range(competitors):
            cmd = [sys.executable, "-c", BUSY] if kind == "busy" else child(policy, args, repeat=True)
            comp.append(subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))

    run: subprocess.Popen | None = None
    try:
        if args.late <= 0:  # competitors first, the measured run once they are under way
            start_competitors()
            time.sleep(args.settle if competitors else 0)
        run = subprocess.Popen(child(policy, args, repeat=False), env=env, stdout=subprocess.PIPE, text=True)
        if args.late > 0:  # the measured run first, the competitors arrive while it runs
            time.sleep(args.late)
            start_competitors()
        out, _ = run.communicate()
        if run.returncode:
            raise SystemExit(f"the measured run failed (exit {run.returncode})")
    finally:
        for p in comp + ([run] if run is not None and run.poll() is None else []):
            p.kill()
            p.wait()
    return json.loads(out.strip().splitlines()[-1])


def throttled(row: dict) -> str:
    """The share of the adaptive guard's samples in which it throttled the spinning ('-' without the guard)."""
    g = row.get("omp", {}).get("guard") or {}
    return f"{g['throttled_samples'] / g['samples']:.2f}" if g.get("samples") else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--encoding", default="dense")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--init-iters", type=int, default=20)
    ap.add_argument("--policies", nargs="+", default=["adaptive", "passive", "default"],
                    help="adaptive, passive, default, active, spin=N (libgomp's GOMP_SPINCOUNT under the default "
                         "policy)")
    ap.add_argument("--competitors", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--competitor", default="busy", choices=["busy", "slam"])
    ap.add_argument("--settle", type=float, default=15.0, help="seconds competitors run before the measured run "
                    "(a competing SLAM run needs its start-up behind it)")
    ap.add_argument("--late", type=float, default=0.0, help="start the competitors this many seconds after the "
                    "measured run instead of before it (0: before; they then arrive while a spinning run computes)")
    args = ap.parse_args()
    rows = []
    for policy in args.policies:
        for n in args.competitors:
            r = measure(policy, n, args.competitor, args)
            rows.append({"policy": policy, "competitors": n, **r})
            print(f"  {policy:13s} {n} {args.competitor}: {r['per_frame_s']:.2f} s/frame", file=sys.stderr, flush=True)
    import torch

    print(f"# machine: {platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}; {args.encoding}, "
          f"paper preset, {args.frames} frames of builtin:room; competitors: {args.competitor}"
          + (f", started {args.late:g} s after the measured run" if args.late > 0 else ""))
    idle = {r["policy"]: r["per_frame_s"] for r in rows if r["competitors"] == 0}
    base = idle.get("default")
    print(f"{'policy':13s} {'competitors':>11s} {'s/frame':>8s} {'x own idle':>10s} {'x default idle':>14s} "
          f"{'init s/it':>9s} {'throttled':>9s}")
    for r in rows:
        own = idle.get(r["policy"])
        print(f"{r['policy']:13s} {r['competitors']:>11d} {r['per_frame_s']:>8.2f} "
              f"{(r['per_frame_s'] / own) if own else float('nan'):>10.2f} "
              f"{(r['per_frame_s'] / base) if base else float('nan'):>14.2f} {r['init_s_per_iter']:>9.3f} "
              f"{throttled(r):>9s}")


if __name__ == "__main__":
    main()
