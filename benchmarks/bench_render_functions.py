"""Per-frame SLAM time of the rendering functions G against SDF(density), in one run (issue #20: NeuS and VolSDF at
the speed of the other rendering functions, target <= 2x SDF(density) per frame and at init). Prints a table and the
ratios; never asserted in tests.

    python benchmarks/bench_render_functions.py                               # dense hash triplane, 10 frames
    python benchmarks/bench_render_functions.py --encodings dense --frames 20 --init-iters 100
    python benchmarks/bench_render_functions.py --renders density neus neus:ray_difference volsdf

A render is ``NAME`` or ``NAME:NORMALS`` (NeuS's ``render.neus.normals``). The variants of one F run back to back
(interleaved per F), so the ratios compare runs under the same load. Per-frame time = (all tracking time + all
mapping time) / tracked frames; init = `slam.init_iters` iterations on frame 0 (default 50 of the preset's 500, so
the run stays minutes: the ratio is that of the full init).
"""

from __future__ import annotations

import argparse
import time

from iteration_setup import machine_line

import inrslam  # noqa: F401  (sets the OpenMP wait policy before torch loads its runtime)


def run_one(preset: str, encoding: str, render: str, frames: int, init_iters: int, data: str, threads: int
            ) -> dict:
    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.fields.kernels.threads import resolve_threads, thread_scope
    from inrslam.slam.system import SlamSystem

    name, _, normals = render.partition(":")
    overrides = [f"data.path={data}", f"data.max_frames={frames}", f"field.encoding={encoding}",
                 f"render.name={name}", f"slam.init_iters={init_iters}", "slam.checkpoint_every=0",
                 "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false", f"threads={threads}"]
    if normals:
        overrides.append(f"render.neus.normals={normals}")
    cfg = load_config(preset=preset, overrides=overrides)
    with thread_scope(resolve_threads(cfg.threads)):
        system = SlamSystem(cfg, open_dataset(cfg.data))
        t0 = time.perf_counter()
        system.run()
        wall = time.perf_counter() - t0
    s = system.state
    tracked = max(len(s.track_ms), 1)
    return {"track_ms": sum(s.track_ms) / tracked, "map_ms": sum(s.map_ms) / max(len(s.map_ms), 1),
            "per_frame_s": (sum(s.track_ms) + sum(s.map_ms)) / tracked / 1e3, "init_s": s.init_ms / 1e3,
            "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--renders", nargs="+", default=["density", "neus", "volsdf"],
                    help="NAME or NAME:NORMALS; the first is the reference of the ratios")
    ap.add_argument("--encodings", nargs="+", default=["dense", "hash", "triplane"])
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--init-iters", type=int, default=50)
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--threads", type=int, default=0, help="torch/numba threads (0 = all cores)")
    args = ap.parse_args()

    policy = inrslam.omp_env.wait_policy()["policy"]
    print(machine_line(f"{args.preset}, {args.data}, {args.frames} frames, init {args.init_iters} iters, threads "
                       f"{args.threads or 'all'}, OpenMP wait {policy}", threads=False))
    for enc in args.encodings:  # warm-up of every F x G: numba compiles (or loads) each F's kernels on first use,
        for render in args.renders:  # which would otherwise land in the init time of that F's first render
            run_one(args.preset, enc, render, 2, 2, args.data, args.threads)
    print(f"{'F':<9} {'G':<26} {'track ms/frame':>15} {'map ms/call':>12} {'s/frame':>8} {'init s':>7} "
          f"{'frame x':>8} {'init x':>7}")
    for enc in args.encodings:
        ref = None
        for render in args.renders:
            r = run_one(args.preset, enc, render, args.frames, args.init_iters, args.data, args.threads)
            ref = ref or r
            print(f"{enc:<9} {render:<26} {r['track_ms']:>15.0f} {r['map_ms']:>12.0f} {r['per_frame_s']:>8.3f} "
                  f"{r['init_s']:>7.1f} {r['per_frame_s'] / ref['per_frame_s']:>7.2f}x "
                  f"{r['init_s'] / ref['init_s']:>6.2f}x", flush=True)


if __name__ == "__main__":
    main()
