"""Per-frame SLAM time at the `paper` preset for each scene representation F, fused kernels vs the plain-PyTorch
reference kernels, in one run (issue #5 speed table). Prints a table; never asserted in tests.

    python benchmarks/bench_slam.py                       # all F, fused and reference, 15 frames of builtin:room
    python benchmarks/bench_slam.py --encodings dense triplane --frames 20 --kernels numba
    python benchmarks/bench_slam.py --encodings dense hash --kernels numba --decoders torch numba   # fused decoders
    python benchmarks/bench_slam.py --encodings dense hash --kernels numba --decoders numba --losses torch numba
    python benchmarks/bench_slam.py --encodings mlp --kernels numba --mlp-precisions float32 bfloat16 --frames 8

Per-frame time = (all tracking time + all mapping time) / tracked frames, i.e. the steady-state cost of a frame
(tracking every frame, mapping every 5th). The 500-iteration initialisation is excluded (reported apart).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence

from iteration_setup import machine_line, paper_config

ENCODINGS = ["mlp", "dense", "hash", "triplane", "tensorf", "dense+tri", "hash+tri"]


def run_one(encoding: str, kernel: str, frames: int, render: str, data: str, init_iters: int,
            overrides: Sequence[str] = (), decoder: str = "torch", loss: str = "torch",
            precision: str = "float32") -> dict:
    from inrslam.datasets import open_dataset
    from inrslam.slam.system import SlamSystem

    cfg = paper_config(data, frames, encoding, init_iters, [
        f"field.kernel={kernel}", f"field.decoder_kernel={decoder}", f"loss.kernel={loss}", f"render.name={render}",
        *overrides, *([f"field.mlp.precision={precision}"] if encoding == "mlp" else [])])
    system = SlamSystem(cfg, open_dataset(cfg.data))
    t0 = time.perf_counter()
    system.run()
    wall = time.perf_counter() - t0
    tracked = len(system.state.track_ms)
    per_frame = (sum(system.state.track_ms) + sum(system.state.map_ms)) / max(tracked, 1)
    return {"encoding": encoding, "kernel": kernel, "decoder": decoder, "loss": loss, "precision": precision,
            "track_ms": sum(system.state.track_ms) / max(tracked, 1),
            "map_ms": sum(system.state.map_ms) / max(len(system.state.map_ms), 1), "per_frame_s": per_frame / 1e3,
            "init_ms_per_iter": system.state.init_ms / max(init_iters, 1), "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--encodings", nargs="+", default=ENCODINGS)
    ap.add_argument("--kernels", nargs="+", default=["numba", "torch"])
    ap.add_argument("--frames", type=int, default=15)
    ap.add_argument("--ref-frames", type=int, default=6, help="frames for the (slow) reference-kernel runs")
    ap.add_argument("--render", default="density")
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--init-iters", type=int, default=20, help="initialisation iterations (not timed per frame)")
    ap.add_argument("--json", help="also write the rows to this JSON file")
    ap.add_argument("--decoders", nargs="+", default=["torch"], help="field.decoder_kernel values (grid decoders: "
                    "torch autograd or the fused numba kernel)")
    ap.add_argument("--losses", nargs="+", default=["torch"], help="loss.kernel values (compositing + losses: "
                    "torch autograd or the fused numba kernel)")
    ap.add_argument("--mlp-precisions", nargs="+", default=["float32"], help="field.mlp.precision values (the MLP "
                    "F only: float32, or its hidden layers and heads in bfloat16)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="more config overrides for every run "
                    "(e.g. slam.track_iters=10)")
    args = ap.parse_args()
    print(machine_line(f"data {args.data}, G={args.render}, paper preset"))
    print(f"{'F':<10} {'lookups':<7} {'decoder':<7} {'losses':<7} {'track ms/frame':>15} {'map ms/call':>12} "
          f"{'s/frame':>8} {'init ms/it':>11}")
    rows = []
    for enc in args.encodings:
        for kernel in args.kernels:
            for decoder in args.decoders:
                for loss in args.losses:
                    for prec in (args.mlp_precisions if enc == "mlp" else ["float32"]):
                        frames = args.frames if kernel != "torch" else args.ref_frames
                        r = run_one(enc, kernel, frames, args.render, args.data, args.init_iters, args.set, decoder,
                                    loss, prec)
                        rows.append(r)
                        print(f"{enc if prec == 'float32' else enc + ' bf16':<10} {kernel:<7} {decoder:<7} {loss:<7} "
                              f"{r['track_ms']:>15.0f} {r['map_ms']:>12.0f} {r['per_frame_s']:>8.2f} "
                              f"{r['init_ms_per_iter']:>11.0f}", flush=True)
        mine = [r for r in rows if r["encoding"] == enc]
        by_prec = {r["precision"]: r for r in mine}
        if "float32" in by_prec and "bfloat16" in by_prec:
            a, b = by_prec["float32"], by_prec["bfloat16"]
            print(f"{enc:<10} ratio   float32/bfloat16 MLP: per frame {a['per_frame_s'] / b['per_frame_s']:.2f}x, "
                  f"tracking {a['track_ms'] / b['track_ms']:.2f}x, mapping {a['map_ms'] / b['map_ms']:.2f}x, "
                  f"init {a['init_ms_per_iter'] / b['init_ms_per_iter']:.2f}x", flush=True)
        mine = [r for r in mine if r["precision"] == "float32"]
        if len(args.losses) > 1:
            for kernel in args.kernels:
                for decoder in args.decoders:
                    by = {r["loss"]: r for r in mine if (r["kernel"], r["decoder"]) == (kernel, decoder)}
                    if "torch" in by and "numba" in by:
                        a, b = by["torch"], by["numba"]
                        print(f"{enc:<10} ratio   torch/fused losses ({kernel} lookups, {decoder} decoders): per "
                              f"frame {a['per_frame_s'] / b['per_frame_s']:.2f}x, tracking "
                              f"{a['track_ms'] / b['track_ms']:.2f}x, mapping {a['map_ms'] / b['map_ms']:.2f}x",
                              flush=True)
        l0 = args.losses[0]
        pick = {(r["kernel"], r["decoder"]): r for r in mine if r["loss"] == l0}
        d0 = args.decoders[0]
        if ("numba", d0) in pick and ("torch", d0) in pick:
            print(f"{enc:<10} ratio   reference/fused lookups, per-frame time: "
                  f"{pick['torch', d0]['per_frame_s'] / pick['numba', d0]['per_frame_s']:.1f}x", flush=True)
        if ("numba", "torch") in pick and ("numba", "numba") in pick:
            a, b = pick["numba", "torch"], pick["numba", "numba"]
            print(f"{enc:<10} ratio   torch/fused decoders: per frame {a['per_frame_s'] / b['per_frame_s']:.2f}x, "
                  f"tracking {a['track_ms'] / b['track_ms']:.2f}x, mapping {a['map_ms'] / b['map_ms']:.2f}x, "
                  f"init {a['init_ms_per_iter'] / b['init_ms_per_iter']:.2f}x", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
