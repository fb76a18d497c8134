"""Where a `paper` frame's time goes: the torch profiler over a few tracked and mapped frames (after a warm-up), its
operations grouped into the fused kernels, the lazy Adam step and everything else, per tracking and per mapping
call. A guide for the next speed-up, not a benchmark: profiling slows the small operations more than the kernels,
so read the shares, and time with `bench_slam.py`. Never asserted in tests.

    python benchmarks/profile_frame.py                                  # dense, every fused kernel, frames 6-10
    python benchmarks/profile_frame.py --encoding hash --frames 5
    python benchmarks/profile_frame.py --set field.decoder_kernel=torch loss.kernel=torch render.kernel=torch
    python benchmarks/profile_frame.py --ops 10                         # and the 10 largest of "other operations"
"""

from __future__ import annotations

import argparse
from collections import defaultdict

from iteration_setup import FUSED, machine_line, paper_config

GROUPS = {  # profiler event name prefix -> group
    "MultilinearFnBackward": "lookups, backward", "MultilinearFn": "lookups, forward",
    "Mlp2FnBackward": "grid decoders, backward", "Mlp2Fn": "grid decoders, forward",
    "Mlp2SplitFnBackward": "grid decoders, backward", "Mlp2SplitFn": "grid decoders, forward",
    "Mlp3FnBackward": "plane decoders, backward", "Mlp3Fn": "plane decoders, forward",
    "CompositeLossFnBackward": "compositing + losses, backward", "CompositeLossFn": "compositing + losses, forward",
    "DensityWeightsFnBackward": "G's weights, backward", "DensityWeightsFn": "G's weights, forward",
    "DirectWeightsFnBackward": "G's weights, backward", "DirectWeightsFn": "G's weights, forward",
    "RayPointsFnBackward": "sample points, backward", "RayPointsFn": "sample points, forward",
    "Optimizer.step#LazyAdam": "lazy Adam step (map)", "Optimizer.step#Adam": "Adam step (poses)",
}


def group_of(name: str) -> str:
    for prefix, group in GROUPS.items():
        if name.startswith(prefix):
            return group
    return "other operations"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--encoding", default="dense")
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--warmup", type=int, default=6, help="frames run before profiling (>= 1: frame 0 initialises "
                    "the map, which is neither tracking nor mapping)")
    ap.add_argument("--frames", type=int, default=5, help="frames profiled")
    ap.add_argument("--init-iters", type=int, default=100)
    ap.add_argument("--ops", type=int, default=0, help="also list this many of the largest operations (by self time) "
                    "in the group 'other operations'")
    ap.add_argument("--set", nargs="*", default=FUSED, metavar="KEY=VALUE",
                    help="config overrides (default: every fused kernel on)")
    args = ap.parse_args()
    if args.warmup < 1:
        ap.error("--warmup must be at least 1")
    from torch.profiler import ProfilerActivity, profile, record_function

    import inrslam.slam.system as system_mod
    from inrslam.datasets import open_dataset

    cfg = paper_config(args.data, args.warmup + args.frames, args.encoding, args.init_iters, args.set)
    system = system_mod.SlamSystem(cfg, open_dataset(cfg.data))
    for i in range(args.warmup):
        system.process(i)

    def labelled(fn, label):
        def wrapper(*a, **k):
            with record_function(label):
                return fn(*a, **k)
        return wrapper

    # the system calls these by the names it imported
    system_mod.track_frame = labelled(system_mod.track_frame, "#track")  # type: ignore[attr-defined]
    system_mod.map_frame = labelled(system_mod.map_frame, "#map")  # type: ignore[attr-defined]
    n_track, n_map = len(system.state.track_ms), len(system.state.map_ms)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for i in range(args.warmup, args.warmup + args.frames):
            system.process(i)
    n_track, n_map = len(system.state.track_ms) - n_track, len(system.state.map_ms) - n_map
    # each event's self time, attributed to the #track / #map range that encloses it
    ranges = [(e.time_range.start, e.time_range.end, e.name) for e in prof.events() if e.name in ("#track", "#map")]
    totals: dict[str, dict[str, float]] = {"#track": defaultdict(float), "#map": defaultdict(float)}
    others: dict[str, dict[str, float]] = {"#track": defaultdict(float), "#map": defaultdict(float)}
    for e in prof.events():
        if e.name in ("#track", "#map"):
            continue
        for start, end, name in ranges:
            if start <= e.time_range.start <= end:
                group = group_of(e.name)
                totals[name][group] += e.self_cpu_time_total / 1e3
                if group == "other operations":
                    others[name][e.name] += e.self_cpu_time_total / 1e3
                break
    print(machine_line(f"{args.data}, F={args.encoding}, paper + {' '.join(args.set) or 'nothing'}; frames "
                       f"{args.warmup}-{args.warmup + args.frames - 1} profiled"))
    for name, calls, what in (("#track", n_track, "tracking"), ("#map", n_map, "mapping")):
        total = sum(totals[name].values())
        print(f"{what}: {calls} call(s), {total / max(calls, 1):.1f} ms of operations per call (profiled)")
        for group, ms in sorted(totals[name].items(), key=lambda kv: -kv[1]):
            print(f"  {group:<32} {ms / max(calls, 1):8.1f} ms per call  {100 * ms / max(total, 1e-9):5.1f} %")
            if group == "other operations":
                for op, op_ms in sorted(others[name].items(), key=lambda kv: -kv[1])[:args.ops]:
                    print(f"    {op[:40]:<40} {op_ms / max(calls, 1):8.1f} ms per call")


if __name__ == "__main__":
    main()
