"""Compositing + losses, forward and backward: autograd (`composite` + `compute_losses`, `loss.kernel=torch`) against
the fused kernel (`loss.kernel=numba`), at a tracking batch (1024 rays) and a mapping batch (2048 rays) of the
paper's 60 samples per ray, float32. Interleaved repetitions in one run; prints medians and their ratio (never
asserted in tests).

    python benchmarks/bench_losses.py                 # 2 threads (the machine's default)
    python benchmarks/bench_losses.py --threads 1
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=60)
    ap.add_argument("--samples", type=int, default=60)
    ap.add_argument("--threads", type=int, default=0, help="torch / numba threads (0: the default)")
    args = ap.parse_args()
    import torch

    from inrslam.fields.kernels.threads import set_threads
    from inrslam.rendering import RenderOutput, composite, compute_losses
    from inrslam.rendering.config import LossConfig
    from inrslam.rendering.fused_losses import composite_losses

    if args.threads:
        set_threads(args.threads)
    cfg, T = LossConfig(), 0.1
    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}"
          f", threads {torch.get_num_threads()}; {args.samples} samples per ray, float32, median of {args.reps}")
    for R in (1024, 2048):
        g = torch.Generator().manual_seed(R)
        S = args.samples
        D = 0.5 + 2.5 * torch.rand(R, generator=g)
        z = torch.sort(D[:, None] + 0.3 * torch.randn(R, S, generator=g), dim=1).values
        s0 = (D[:, None] - z) / T + 0.2 * torch.randn(R, S, generator=g)
        w0 = torch.rand(R, S, generator=g) / S
        c0 = torch.rand(R, S, 3, generator=g)
        C = torch.rand(R, 3, generator=g)

        def torch_step():
            w, c, s = (x.clone().requires_grad_() for x in (w0, c0, s0))
            out = RenderOutput(*composite(w, c, z), w, s, z)
            loss = compute_losses(out, C, D, cfg, T)["total"]
            loss.backward()

        def fused_step():
            w, c, s = (x.clone().requires_grad_() for x in (w0, c0, s0))
            terms, _ = composite_losses(w, c, z, s, C, D, T, cfg.center_band, cfg.free_space_target, True, True)
            loss = (cfg.color * terms["color"] + cfg.depth * terms["depth"] + cfg.free_space * terms["free_space"]
                    + cfg.center * terms["center"] + cfg.tail * terms["tail"])
            loss.backward()

        times: dict[str, list[float]] = {"torch": [], "fused": []}
        for step in (torch_step, fused_step):  # warm-up (numba compiles or loads its cache)
            step()
        for _ in range(args.reps):
            for name, step in (("torch", torch_step), ("fused", fused_step)):
                t0 = time.perf_counter()
                step()
                times[name].append((time.perf_counter() - t0) * 1e3)
        a, b = statistics.median(times["torch"]), statistics.median(times["fused"])
        print(f"{R} rays x {S}: autograd {a:.2f} ms, fused {b:.2f} ms per forward + backward: {a / b:.2f}x", flush=True)


if __name__ == "__main__":
    main()
