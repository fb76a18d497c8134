"""Supplementary Table 4 analogue: mapping time per frame of the Explicit Hybrid Encoding mapper (`--preset ehe`)
against the dense F x SDF(density) system at paper settings mapping with the same given poses (`--preset paper
--poses gt`), with mesh Acc / Comp / Comp%, parameters and peak memory of both, measured in one run. Each system runs
in its own process (`inrslam run`), one after the other, so peak memory is each run's own. Never asserted in tests.

    python benchmarks/bench_ehe.py                                          # builtin:room, 100 frames
    python benchmarks/bench_ehe.py --frames 400 --data ../shared/data/7scenes_redkitchen --dataset 7scenes

Acc / Comp / Comp% are against the part of the GT mesh the frames saw (`eval.cull_gt=true`: the GT mesh culled with
the same cameras as the reconstruction; docs/metrics.md), so that a short sequence is not charged for walls it never
saw; `eval.cull_gt=false` as an override measures against the whole GT mesh. Both systems map the same depth: the
`ehe` preset maps depth noisier than 2 mm at 1 m after a bilateral filter (`slam.map_filtered_depth`), and the paper
system is given the same overrides (on Kinect-class or noise-free depth the filter's gate leaves the depth as it is).

Mapping s/frame = all mapping time after the first frame / (frames - 1): EHE maps every frame (10 iterations, early
ending), the paper system every 5th (20 iterations), both over their keyframes. The first frame (EHE: 100
iterations; paper: 500 initialisation iterations) is printed apart, and "incl. first" adds it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from iteration_setup import machine_line

# both map the same depth: `ehe` maps depth noisier than 2 mm at 1 m after the bilateral filter, so the paper system
# is given the same filtered depth (its own loop otherwise unchanged)
SAME_DEPTH = ["slam.map_filtered_depth=true", "slam.gicp.depth_filter=2"]
SYSTEMS = {"EHE 1x2 (ehe)": (["--preset", "ehe"], []),
           "dense 2x2 + density (paper, --poses gt)": (["--preset", "paper", "--poses", "gt"], SAME_DEPTH)}


def run_one(system: tuple[list[str], list[str]], out: Path, data: str, dataset: str | None, frames: int,
            extra: list[str]) -> dict:
    """One `inrslam run` (system = its options, its overrides) in a subprocess; returns its metrics.json."""
    args_sys, overrides = system
    cmd = [sys.executable, "-m", "inrslam.cli", "run", *args_sys, "--data", data, "--out", str(out), "--quiet",
           "--overwrite", f"data.max_frames={frames}", "output.tensorboard=false", "slam.checkpoint_every=0",
           "eval.heldout_max=5", "eval.cull_gt=true", *overrides, *extra]
    if dataset:
        cmd += ["--dataset", dataset]
    subprocess.run(cmd, check=True)
    return json.loads((out / "metrics.json").read_text())


def _cm(v) -> str:
    return f"{100 * v:.2f}" if v is not None else "-"


def _num(v, fmt: str, scale: float = 1.0) -> str:
    return format(scale * v, fmt) if v is not None else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--dataset", default=None, help="force the reader (e.g. 7scenes)")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1,
                    help="torch / numba threads of both runs (0 = every core; 1 default: steadier on a shared machine)")
    ap.add_argument("--out", default=None, help="keep the run directories here (default: a temporary folder)")
    ap.add_argument("overrides", nargs="*", help="KEY=VALUE overrides for both runs")
    args = ap.parse_args()

    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_ehe_"))
    print(machine_line(f"data {args.data}, {args.frames} frames, {args.threads or 'all'} thread(s); runs in {root}",
                       threads=False))
    rows = {}
    for k, (name, sys_args) in enumerate(SYSTEMS.items()):
        rows[name] = run_one(sys_args, root / f"run{k}", args.data, args.dataset, args.frames,
                             [f"threads={args.threads}", *args.overrides])
    head = ("| system | mapping s/frame | s/call | first frame s | incl. first s/frame | Acc cm | Comp cm | Comp % "
            "| params MB | peak MB | held-out PSNR dB | held-out depth L1 cm |")
    print(head)
    print("|---" * (head.count("|") - 1) + "|")
    for name, m in rows.items():
        n = m["frames"]
        per = m["map_ms_per_frame"] / 1e3
        incl = (m["map_ms_per_frame"] * (n - 1) + m["init_ms"]) / n / 1e3
        print(f"| {name} | {per:.3f} | {m['map_ms_per_call'] / 1e3:.3f} | {m['init_ms'] / 1e3:.1f} | {incl:.3f} | "
              f"{_cm(m['acc_m'])} | {_cm(m['comp_m'])} | {_num(m['comp_ratio'], '.1f', 100)} | "
              f"{m['model_size_mb']:.1f} | {m['peak_memory_mb']:.0f} | {_num(m['psnr_db'], '.2f')} | "
              f"{_cm(m['depth_l1_m'])} |")
    ehe, dense = rows.values()
    print(f"speed-up per frame (dense / EHE): {dense['map_ms_per_frame'] / ehe['map_ms_per_frame']:.2f}x; per mapping "
          f"call: {dense['map_ms_per_call'] / ehe['map_ms_per_call']:.2f}x; EHE voxels {ehe.get('ehe_voxels')}, "
          f"vertices {ehe.get('ehe_vertices')}, keyframes {ehe.get('ehe_keyframes')}")


if __name__ == "__main__":
    main()
