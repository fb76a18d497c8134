"""Subnormal gradients in the fused backward kernels: one tracking and one mapping iteration at `paper` settings with
every fused kernel (`field.decoder_kernel=numba loss.kernel=numba`), the kernels counting subnormal gradients as zero
(today) against keeping them (the code before), interleaved in one process on the same map and rays (median of
--reps). Also prints how many of the decoders' output gradients are subnormal when nothing flushes. Never asserted
in tests.

    python benchmarks/bench_subnormal.py                       # dense, builtin:room
    python benchmarks/bench_subnormal.py --encoding hash
    python benchmarks/bench_subnormal.py --encoding triplane   # the plane decoders' kernel

"Kept" runs the same kernels with the threshold set to 0 (nothing counts as subnormal), i.e. the arithmetic of the
kernels before they flushed. See docs/speed.md, "Subnormal gradients".
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--encoding", default="dense")
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--frames", type=int, default=8, help="frames run first to build the map")
    ap.add_argument("--reps", type=int, default=30)
    args = ap.parse_args()
    import numpy as np
    import torch

    import inrslam.fields.kernels.mlp as mlp_mod
    import inrslam.fields.kernels.mlp3 as mlp3_mod
    import inrslam.rendering.fused_losses as loss_mod
    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.fields.kernels.subnormal import tiny_of
    from inrslam.slam.frame_tensors import FrameTensors
    from inrslam.slam.system import SlamSystem
    from inrslam.slam.tracking import frozen

    cfg = load_config(preset="paper", overrides=[
        f"data.path={args.data}", f"data.max_frames={args.frames + 1}", f"field.encoding={args.encoding}",
        "field.decoder_kernel=numba", "loss.kernel=numba", "slam.init_iters=100", "slam.checkpoint_every=0",
        "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false"])
    system = SlamSystem(cfg, open_dataset(cfg.data))
    for i in range(args.frames):
        system.process(i)
    model = system.model
    ft = FrameTensors(system.dataset[args.frames], system.device)
    g = torch.Generator().manual_seed(0)
    c2w = system.est[args.frames - 1].clone()
    track_rays = ft.sample(cfg.slam.track_pixels, g, cfg.slam.track_edge)
    map_rays = ft.sample(cfg.slam.map_pixels, g)
    modules = (mlp_mod, mlp3_mod, loss_mod)

    def flush(on: bool) -> None:
        for m in modules:
            m.tiny_of = tiny_of if on else (lambda dtype: 0.0)  # type: ignore[attr-defined]

    counts: list[tuple[int, int]] = []  # (subnormal, all) of each decoder output gradient seen while counting
    counting = [False]
    tiny = float(np.finfo(np.float32).tiny)

    captured: list[tuple] = []  # the grid decoders' saved inputs and output gradients of one tracking iteration

    def count(fn):
        def backward(ctx, gy):
            if counting[0]:
                counts.append((int(((gy.abs() < tiny) & (gy != 0)).sum()), gy.numel()))
                if fn is grid_backward and len(captured) < 2:
                    captured.append((*ctx.saved_tensors, gy.detach().contiguous().clone()))
            return fn(ctx, gy)
        return staticmethod(backward)

    grid_backward = mlp_mod.Mlp2Fn.backward

    mlp_mod.Mlp2Fn.backward = count(mlp_mod.Mlp2Fn.backward)  # type: ignore[method-assign]
    mlp3_mod.Mlp3Fn.backward = count(mlp3_mod.Mlp3Fn.backward)  # type: ignore[method-assign]

    def track_iter() -> None:
        pose = c2w.clone().requires_grad_()
        with frozen(model):
            losses, _ = model.loss(pose, *track_rays, g)
            losses["total"].backward()

    def map_iter() -> None:
        losses, _ = model.loss(c2w, *map_rays, g)
        losses["total"].backward()
        model.zero_grad(set_to_none=True)

    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}"
          f", threads {torch.get_num_threads()}; {args.data}, F={args.encoding}, paper settings + every fused kernel, "
          f"median of {args.reps}")
    for name, step in (("tracking", track_iter), (f"mapping ({cfg.slam.map_pixels} rays)", map_iter)):
        counts.clear()
        counting[0] = True
        flush(False)  # what reaches the decoders when no kernel flushes
        step()
        counting[0] = False
        share = sum(c[0] for c in counts) / max(sum(c[1] for c in counts), 1)
        times: dict[bool, list[float]] = {True: [], False: []}
        for _ in range(args.reps):
            for on in (False, True):
                flush(on)
                t0 = time.perf_counter()
                step()
                times[on].append((time.perf_counter() - t0) * 1e3)
        kept, flushed = statistics.median(times[False]), statistics.median(times[True])
        print(f"{name} iteration: subnormal decoder output gradients {100 * share:.1f} %; kept {kept:7.2f} ms, "
              f"counted as zero {flushed:7.2f} ms: {kept / flushed:4.2f}x", flush=True)
        if captured and name == "tracking":  # the grid decoders' backward kernel alone on these gradients
            for x, w1t, w2, gy in captured:
                arrs = [t.numpy() for t in (x, w1t, w2)]
                gy_np = gy.to(w1t.dtype).numpy()
                zeroed = np.where(np.abs(gy_np) < tiny, 0, gy_np).astype(gy_np.dtype)
                gx = np.empty(x.shape, gy_np.dtype)
                empty = np.zeros((0, *w1t.shape), gy_np.dtype), np.zeros((0, *w2.shape), gy_np.dtype)
                block = mlp_mod.block_rows(w1t, w2)
                kt: dict[bool, list[float]] = {True: [], False: []}
                for _ in range(args.reps):
                    for zero in (False, True):
                        t0 = time.perf_counter()
                        mlp_mod._backward(*arrs, zeroed if zero else gy_np, block, True, False, 0.0, gx, *empty)
                        kt[zero].append((time.perf_counter() - t0) * 1e3)
                a, b = statistics.median(kt[False]), statistics.median(kt[True])
                print(f"  its decoder backward kernel ({w2.shape[0]} output(s)), threshold 0: on the gradients as "
                      f"they are {a:.2f} ms, with the subnormal ones set to 0 {b:.2f} ms: {a / b:4.2f}x", flush=True)
    flush(True)


if __name__ == "__main__":
    main()
