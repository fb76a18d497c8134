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
from collections.abc import Callable

from iteration_setup import add_map_arguments, interleaved, machine_line, paper_map


def replay_kernel(x, w1t, w2, gy, tiny: float, reps: int) -> tuple[float, float]:
    """Median ms of the grid decoder's backward kernel to the input alone (threshold 0: nothing flushed) on the output
    gradients gy as they are, and with their subnormal entries set to zero."""
    import numpy as np

    import inrslam.fields.kernels.mlp as mlp_mod

    arrs = [t.numpy() for t in (x, w1t, w2)]
    gy_np = gy.to(w1t.dtype).numpy()
    zeroed = np.where(np.abs(gy_np) < tiny, 0, gy_np).astype(gy_np.dtype)
    gx = np.empty(x.shape, gy_np.dtype)
    empty = np.zeros((0, *w1t.shape), gy_np.dtype), np.zeros((0, *w2.shape), gy_np.dtype)
    block = mlp_mod.block_rows(w1t, w2)
    grads = {"in": gy_np}

    def kernel() -> None:
        mlp_mod._backward(*arrs, grads["in"], block, True, False, 0.0, gx, *empty)

    ms = interleaved(kernel, {"kept": lambda: grads.update({"in": gy_np}),
                              "zero": lambda: grads.update({"in": zeroed})}, reps)
    return ms["kept"], ms["zero"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_map_arguments(ap)
    args = ap.parse_args()
    import numpy as np
    import torch

    import inrslam.fields.kernels.mlp as mlp_mod
    import inrslam.fields.kernels.mlp3 as mlp3_mod
    import inrslam.rendering.fused_losses as loss_mod
    from inrslam.fields.kernels.subnormal import tiny_of

    bench = paper_map(args.encoding, args.data, args.frames, ["field.decoder_kernel=numba", "loss.kernel=numba"])
    modules = (mlp_mod, mlp3_mod, loss_mod)

    def flush(on: bool) -> Callable[[], None]:
        def setter() -> None:
            for m in modules:
                m.tiny_of = tiny_of if on else (lambda dtype: 0.0)  # type: ignore[attr-defined]
        return setter

    counts: list[tuple[int, int]] = []  # (subnormal, all) of each decoder output gradient seen while counting
    counting = [False]
    tiny = float(np.finfo(np.float32).tiny)
    captured: list[tuple] = []  # the grid decoders' saved inputs and output gradients of one tracking iteration

    def count(fn):
        def backward(ctx, *gys):
            if counting[0]:
                gy = torch.cat([g.to(gys[0].dtype) for g in gys], dim=1)  # the pair's two output gradients as one
                counts.append((int(((gy.abs() < tiny) & (gy != 0)).sum()), gy.numel()))
                if fn in grid_backwards and len(captured) < 2:
                    saved = ctx.saved_tensors
                    x = torch.cat(saved[:-2], dim=1)  # the pair's [xa, xb], as the single decoder's x
                    captured.append((x, *saved[-2:], gy.detach().contiguous().clone()))
            return fn(ctx, *gys)
        return staticmethod(backward)

    grid_backwards = (mlp_mod.Mlp2Fn.backward, mlp_mod.Mlp2SplitFn.backward)
    mlp_mod.Mlp2Fn.backward = count(mlp_mod.Mlp2Fn.backward)  # type: ignore[method-assign]
    mlp_mod.Mlp2SplitFn.backward = count(mlp_mod.Mlp2SplitFn.backward)  # type: ignore[method-assign]
    mlp3_mod.Mlp3Fn.backward = count(mlp3_mod.Mlp3Fn.backward)  # type: ignore[method-assign]

    print(machine_line(f"{args.data}, F={args.encoding}, paper settings + every fused kernel, median of {args.reps}"))
    for name, step in (("tracking", bench.track_iter), (f"mapping ({bench.cfg.slam.map_pixels} rays)", bench.map_iter)):
        counts.clear()
        counting[0] = True
        flush(False)()  # what reaches the decoders when no kernel flushes
        step()
        counting[0] = False
        share = sum(c[0] for c in counts) / max(sum(c[1] for c in counts), 1)
        ms = interleaved(step, {"kept": flush(False), "zero": flush(True)}, args.reps)
        print(f"{name} iteration: subnormal decoder output gradients {100 * share:.1f} %; kept {ms['kept']:7.2f} ms, "
              f"counted as zero {ms['zero']:7.2f} ms: {ms['kept'] / ms['zero']:4.2f}x", flush=True)
        if captured and name == "tracking":  # the grid decoders' backward kernel alone on these gradients
            for x, w1t, w2, gy in captured:
                kept, zero = replay_kernel(x, w1t, w2, gy, tiny, args.reps)
                print(f"  its decoder backward kernel ({w2.shape[0]} output(s)), threshold 0: on the gradients as "
                      f"they are {kept:.2f} ms, with the subnormal ones set to 0 {zero:.2f} ms: {kept / zero:4.2f}x",
                      flush=True)
    flush(True)()


if __name__ == "__main__":
    main()
