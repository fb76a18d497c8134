"""Per-frame SLAM time of the `accurate` and `gicp` presets (or any, `--presets`) against `paper`, in one run
(issue: accurate preset, target <= 2x paper). Prints a table and the ratios; never asserted in tests.

    python benchmarks/bench_presets.py                           # 40 frames of builtin:room, every F in --encodings
    python benchmarks/bench_presets.py --encodings dense hash --frames 60 --data builtin:cluttered
    python benchmarks/bench_presets.py --presets paper paper_fused --encodings dense hash --frames 60
    python benchmarks/bench_presets.py --frames 30 --data ../shared/data/7scenes_redkitchen --set data.dataset=7scenes \
        data.bounds_frames=40                                    # config overrides for every preset

Per-frame time = (all tracking time + all mapping time) / tracked frames: the steady-state cost of a frame (tracking
every frame, mapping every 5th). Initialisation (same in every preset) is excluded and printed apart.
"""

from __future__ import annotations

import argparse
import time

from iteration_setup import machine_line

PRESETS = ["paper", "accurate", "gicp"]


def run_one(preset: str, encoding: str, frames: int, data: str, extra: list[str] = ()) -> dict:
    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.fields.kernels.threads import resolve_threads, thread_scope
    from inrslam.slam.system import SlamSystem

    cfg = load_config(preset=preset, overrides=[
        f"data.path={data}", f"data.max_frames={frames}", f"field.encoding={encoding}", "slam.checkpoint_every=0",
        "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false", *extra])
    with thread_scope(resolve_threads(cfg.threads)):
        system = SlamSystem(cfg, open_dataset(cfg.data))
        t0 = time.perf_counter()
        system.run()
        wall = time.perf_counter() - t0
        tracked = max(len(system.state.track_ms), 1)
        return {"preset": preset, "encoding": encoding, "render": cfg.render.name,
                "track_ms": sum(system.state.track_ms) / tracked,
                "map_ms": sum(system.state.map_ms) / max(len(system.state.map_ms), 1),
                "per_frame_s": (sum(system.state.track_ms) + sum(system.state.map_ms)) / tracked / 1e3,
                "init_s": system.state.init_ms / 1e3, "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=PRESETS)
    ap.add_argument("--encodings", nargs="+", default=["dense"])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides for every preset")
    args = ap.parse_args()

    print(machine_line(f"data {args.data}, {args.frames} frames", threads=False))
    print(f"{'preset':<11} {'F':<9} {'G':<8} {'track ms/frame':>15} {'map ms/call':>12} {'s/frame':>8} {'init s':>7}")
    for enc in args.encodings:
        rows = {}
        for preset in args.presets:
            r = rows[preset] = run_one(preset, enc, args.frames, args.data, args.set)
            print(f"{preset:<11} {enc:<9} {r['render']:<8} {r['track_ms']:>15.0f} {r['map_ms']:>12.0f} "
                  f"{r['per_frame_s']:>8.3f} {r['init_s']:>7.1f}", flush=True)
        if "paper" in rows:
            for preset, r in rows.items():
                if preset != "paper":
                    ratio = r["per_frame_s"] / rows["paper"]["per_frame_s"]
                    print(f"{enc:<9} {preset}/paper per-frame time: {ratio:.2f}x", flush=True)


if __name__ == "__main__":
    main()
