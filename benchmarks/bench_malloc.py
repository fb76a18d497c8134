"""glibc malloc settings (`inrslam.malloc_env`): the same run with `INRSLAM_MALLOC=default` and `tuned` (inrslam's
default), alternated in fresh processes, in one run. Prints per run the initialisation, tracking and mapping times
from `metrics.json`, the process's minor page faults and peak memory, then the medians and the ratios default /
tuned, and whether the trajectories are byte-identical. Never asserted in tests.

    python benchmarks/bench_malloc.py                                    # dense, `paper`, 12 frames of room, 3 pairs
    python benchmarks/bench_malloc.py --encoding hash --frames 20 --reps 2
    python benchmarks/bench_malloc.py --preset accurate --set slam.init_iters=50
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = r"""
import json, resource, sys
from inrslam.cli import main
code = main(sys.argv[1:])
ru = resource.getrusage(resource.RUSAGE_SELF)
print("RUSAGE " + json.dumps({"minflt": ru.ru_minflt, "maxrss_mb": ru.ru_maxrss / 1024}), flush=True)
sys.exit(code)
"""

KEYS = (("init_ms", "init [s]", 1e-3), ("track_ms_per_frame", "tracking [ms/frame]", 1.0),
        ("map_ms_per_call", "mapping [ms/call]", 1.0))


def one_run(mode: str, out: Path, args) -> dict:
    cmd = [sys.executable, "-c", CHILD, "run", "--preset", args.preset, "--data", args.data, "--encoding",
           args.encoding, "--max-frames", str(args.frames), "--out", str(out), "--overwrite", "--quiet",
           "eval.enabled=false", "mesh.enabled=false", "output.tensorboard=false",
           f"slam.init_iters={args.init_iters}", *args.set]
    env = dict(os.environ, INRSLAM_MALLOC=mode)
    res = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if res.returncode != 0:
        sys.exit(f"run failed ({mode}):\n{res.stderr[-2000:]}")
    usage = json.loads(next(line for line in res.stdout.splitlines() if line.startswith("RUSAGE "))[7:])
    metrics = json.loads((out / "metrics.json").read_text())
    rec = {key: metrics[key] * scale for key, _, scale in KEYS}
    rec.update(faults_k=usage["minflt"] / 1e3, peak_mb=usage["maxrss_mb"])
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--encoding", default="dense")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--init-iters", type=int, default=100)
    ap.add_argument("--reps", type=int, default=3, help="pairs of runs (default, tuned), alternated")
    ap.add_argument("--set", nargs="*", default=[], help="more config overrides KEY=VALUE")
    args = ap.parse_args()

    rows: dict[str, list[dict]] = {"default": [], "tuned": []}
    identical = True
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.reps):
            outs = {}
            for mode in ("default", "tuned") if rep % 2 == 0 else ("tuned", "default"):
                outs[mode] = Path(tmp) / f"{mode}{rep}"
                rows[mode].append(one_run(mode, outs[mode], args))
                r = rows[mode][-1]
                print(f"  {mode:7s} run {rep}: init {r['init_ms']:.2f} s, tracking {r['track_ms_per_frame']:.0f} ms, "
                      f"mapping {r['map_ms_per_call']:.0f} ms, {r['faults_k']:.0f} k faults, "
                      f"peak {r['peak_mb']:.0f} MB",
                      flush=True)
            identical &= filecmp.cmp(outs["default"] / "trajectory.txt", outs["tuned"] / "trajectory.txt",
                                     shallow=False)
    print(f"\n{args.preset}, {args.encoding}, {args.frames} frames of {args.data}, {args.init_iters} init iterations, "
          f"{args.reps} runs each (medians)\n")
    print("| | INRSLAM_MALLOC=default | tuned | default / tuned |\n|:--|--:|--:|--:|")
    cols = [(key, label) for key, label, _ in KEYS]
    cols += [("faults_k", "minor page faults [k]"), ("peak_mb", "peak memory [MB]")]
    for key, label in cols:
        d = statistics.median(r[key] for r in rows["default"])
        t = statistics.median(r[key] for r in rows["tuned"])
        print(f"| {label} | {d:.2f} | {t:.2f} | {d / t:.2f}x |")
    print(f"\ntrajectories byte-identical: {identical}")


if __name__ == "__main__":
    main()
