"""What the live viewer (`inrslam run --viewer`) costs the SLAM loop: the same short run with and without it, in one
invocation, and the ratio of their loop times (issue #15: at most 1.10). Never asserted in tests.

    python benchmarks/bench_viewer.py                                  # builtin:room, paper and fast, 60 frames
    python benchmarks/bench_viewer.py --presets fast --frames 100 --mesh-every 10 --repeats 3

The viewer run has a browser stand-in connected: a websocket client that receives every message (a real browser
would run on the user's machine, not the SLAM server), so the server's sending is part of the cost. Loop time = the
wall time from the first frame's progress call to the last (initialisation, the same in both, is left out; no
final mesh, evaluation or checkpoints). Runs alternate (plain, viewer, plain, viewer, ...) after a 3-frame warm-up
that pays the JIT compilation, and the ratio is of the median loop times, per preset.
"""

from __future__ import annotations

import argparse
import statistics
import threading
import time

from iteration_setup import machine_line


def make_system(preset: str, frames: int, data: str):
    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.slam.system import SlamSystem

    cfg = load_config(preset=preset, overrides=[
        f"data.path={data}", f"data.max_frames={frames}", "slam.checkpoint_every=0", "mesh.enabled=false",
        "eval.enabled=false", "output.tensorboard=false"])
    return SlamSystem(cfg, open_dataset(cfg.data))


def browser_stand_in(port: int) -> tuple[threading.Thread, dict]:
    """A thread that connects to the viser server as its web client does and drains every message."""
    import viser
    from websockets.sync.client import connect

    seen = {"messages": 0, "bytes": 0}
    ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)  # type: ignore[list-item]

    def drain() -> None:
        try:
            for msg in ws:
                seen["messages"] += 1
                seen["bytes"] += len(msg)
        except Exception:  # the server stopped
            pass

    t = threading.Thread(target=drain, daemon=True)
    t.start()
    seen["close"] = ws.close  # type: ignore[assignment]
    return t, seen


def timed_run(preset: str, frames: int, data: str, viewer: bool, mesh_every: int) -> dict:
    """One run; loop seconds from the first progress call to the last, and the viewer's own counters."""
    from inrslam.fields.kernels.threads import resolve_threads, thread_scope

    system = make_system(preset, frames, data)
    calls: list[float] = []
    live = server = seen = None
    if viewer:
        from inrslam.viewer.live import LiveViewer
        from inrslam.viewer.server import start_server

        server = start_server(port=0)
        _, seen = browser_stand_in(server.get_port())
        live = LiveViewer(server, mesh_every=mesh_every)

    def progress(i: int, n: int, info: dict) -> None:
        if live is not None:
            live(i, n, info)
        calls.append(time.perf_counter())

    with thread_scope(resolve_threads(system.cfg.threads)):
        system.run(progress=progress)
    out = {"loop_s": calls[-1] - calls[0], "frames": len(calls)}
    if live is not None and server is not None and seen is not None:
        time.sleep(0.5)  # let the last messages arrive
        out |= {"meshes": live.meshes, "mesh_s": live.mesh_s, "skipped": live.skipped_meshes, "busy_s": live.busy_s,
                "messages": seen["messages"], "mbytes": seen["bytes"] / 2**20}
        seen["close"]()
        from inrslam.viewer.server import stop_server

        stop_server(server)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["paper", "fast"])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--mesh-every", type=int, default=20, help="as inrslam run --viewer-mesh-every")
    ap.add_argument("--repeats", type=int, default=1, help="pairs of runs (plain, viewer)")
    args = ap.parse_args()

    print(machine_line(f"{args.data}, {args.frames} frames, mesh every {args.mesh_every}", threads=False), flush=True)
    ratios = {}
    for preset in args.presets:
        timed_run(preset, 3, args.data, viewer=False, mesh_every=args.mesh_every)  # warm-up: JIT, scene cache
        loops: dict[str, list[float]] = {"plain": [], "viewer": []}
        for _ in range(args.repeats):
            for kind in ("plain", "viewer"):
                r = timed_run(preset, args.frames, args.data, viewer=kind == "viewer", mesh_every=args.mesh_every)
                loops[kind].append(r["loop_s"])
                extra = ""
                if kind == "viewer":
                    extra = (f"  callback {r['busy_s']:.2f} s ({100 * r['busy_s'] / r['loop_s']:.1f} % of the loop), "
                             f"of which meshes {r['meshes']} ({r['mesh_s']:.2f} s; {r['skipped']} skipped for the "
                             f"budget); {r['messages']} messages, {r['mbytes']:.1f} MiB sent")
                print(f"{preset:<6} {kind:<7} loop {r['loop_s']:7.2f} s over {r['frames'] - 1} frames "
                      f"({r['loop_s'] / max(r['frames'] - 1, 1):.3f} s/frame){extra}", flush=True)
        ratios[preset] = statistics.median(loops["viewer"]) / statistics.median(loops["plain"])
    for preset, ratio in ratios.items():
        print(f"{preset}: viewer / plain loop time {ratio:.3f}x (median of {args.repeats})", flush=True)


if __name__ == "__main__":
    main()
