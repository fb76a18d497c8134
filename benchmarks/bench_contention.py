"""Per-frame SLAM time on a shared machine (issue #16): idle, and beside 1 and 2 competing CPU-bound processes,
under each OpenMP wait policy, in one run. Prints a table of seconds per frame and ratios; never asserted in tests.

    python benchmarks/bench_contention.py                               # dense, 12 frames, busy-loop competitors
    python benchmarks/bench_contention.py --competitor slam --competitors 0 1   # beside a second inrslam run
    python benchmarks/bench_contention.py --policies passive --encoding hash

Policies: `passive` is what `import inrslam` sets (OMP_WAIT_POLICY=PASSIVE: a thread waiting at a barrier sleeps);
`default` the OpenMP runtime's own default, as before inrslam set a policy (spin for a while, then sleep: the child
imports torch before inrslam); `active` OMP_WAIT_POLICY=ACTIVE (spin, never sleep); `spin=N` the default policy with
libgomp's spin count GOMP_SPINCOUNT=N. Each measurement is a fresh
process, so the runtime reads the policy as it loads. Competitors: `busy` = a single-threaded Python busy loop per
competitor; `slam` = another inrslam run of the same settings per competitor (under the same policy).
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
if sys.argv[5] == "default" or sys.argv[5].startswith("spin="):
    import torch  # loaded before inrslam: the OpenMP runtime keeps its own default (spin, then sleep)
from inrslam.config import load_config
from inrslam.datasets import open_dataset
from inrslam.fields.kernels.threads import resolve_threads, thread_scope
from inrslam.omp_env import wait_policy
from inrslam.slam.system import SlamSystem
enc, frames, init_iters, repeat = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
cfg = load_config(preset="paper", overrides=[
    "data.path=builtin:room", f"data.max_frames={frames}", f"field.encoding={enc}", f"slam.init_iters={init_iters}",
    "slam.checkpoint_every=0", "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false"])
while True:
    with thread_scope(resolve_threads(0)):
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
    env.pop("OMP_WAIT_POLICY", None)
    if policy == "active":  # spin at every barrier, never sleep
        env["OMP_WAIT_POLICY"] = "ACTIVE"
    elif policy.startswith("spin="):  # the runtime's default policy with another spin count (libgomp)
        env["GOMP_SPINCOUNT"] = policy[len("spin="):]
    return env


def child(policy: str, args, repeat: bool) -> list[str]:
    return [sys.executable, "-c", CHILD, args.encoding, str(args.frames), str(args.init_iters), "1" if repeat else "0",
            policy]


def measure(policy: str, competitors: int, kind: str, args) -> dict:
    """One SLAM run's per-frame time beside `competitors` processes of `kind`."""
    env = environment(policy)
    comp = []
    for _ in range(competitors):
        cmd = [sys.executable, "-c", BUSY] if kind == "busy" else child(policy, args, repeat=True)
        comp.append(subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    try:
        time.sleep(args.settle if competitors else 0)
        out = subprocess.run(child(policy, args, repeat=False), env=env, capture_output=True, text=True,
                             check=True).stdout
    finally:
        for p in comp:
            p.kill()
            p.wait()
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--encoding", default="dense")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--init-iters", type=int, default=20)
    ap.add_argument("--policies", nargs="+", default=["passive", "default"],
                    help="passive, default, active, spin=N (libgomp's GOMP_SPINCOUNT under the default policy)")
    ap.add_argument("--competitors", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--competitor", default="busy", choices=["busy", "slam"])
    ap.add_argument("--settle", type=float, default=15.0, help="seconds competitors run before the measured run "
                    "(a competing SLAM run needs its start-up behind it)")
    args = ap.parse_args()
    rows = []
    for policy in args.policies:
        for n in args.competitors:
            r = measure(policy, n, args.competitor, args)
            rows.append({"policy": policy, "competitors": n, **r})
            print(f"  {policy:13s} {n} {args.competitor}: {r['per_frame_s']:.2f} s/frame", file=sys.stderr, flush=True)
    import torch

    print(f"# machine: {platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}; {args.encoding}, "
          f"paper preset, {args.frames} frames of builtin:room; competitors: {args.competitor}")
    idle = {r["policy"]: r["per_frame_s"] for r in rows if r["competitors"] == 0}
    base = idle.get("default")
    print(f"{'policy':13s} {'competitors':>11s} {'s/frame':>8s} {'x own idle':>10s} {'x default idle':>14s} "
          f"{'init s/it':>9s}")
    for r in rows:
        own = idle.get(r["policy"])
        print(f"{r['policy']:13s} {r['competitors']:>11d} {r['per_frame_s']:>8.2f} "
              f"{(r['per_frame_s'] / own) if own else float('nan'):>10.2f} "
              f"{(r['per_frame_s'] / base) if base else float('nan'):>14.2f} {r['init_s_per_iter']:>9.3f}")


if __name__ == "__main__":
    main()
