"""Compositing + losses, forward and backward: autograd (`composite` + `compute_losses`, `loss.kernel=torch`) against
the fused kernel (`loss.kernel=numba`), at a tracking batch (1024 rays) and a mapping batch (2048 rays) of the
paper's 60 samples per ray, float32; and the depth-guided sampler (`sample_depths`, torch against its bit-identical
numba pass). Interleaved repetitions in one run; prints medians and their ratio (never asserted in tests).

    python benchmarks/bench_losses.py                 # 2 threads (the machine's default)
    python benchmarks/bench_losses.py --threads 1
"""

from __future__ import annotations

import argparse
import statistics
import time

from iteration_setup import machine_line


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=60)
    ap.add_argument("--samples", type=int, default=60)
    ap.add_argument("--threads", type=int, default=0, help="torch / numba threads (0: the default)")
    args = ap.parse_args()
    from inrslam.fields.kernels.threads import set_threads

    if args.threads:
        set_threads(args.threads)
    print(machine_line(f"{args.samples} samples per ray, float32, median of {args.reps}"))
    for R in (1024, 2048):
        bench_batch(R, args.samples, args.reps)


def bench_batch(R: int, S: int, reps: int) -> None:
    """Print both comparisons for R rays of S samples."""
    import torch

    from inrslam.rendering import RenderOutput, composite, compute_losses
    from inrslam.rendering.config import LossConfig, SamplingConfig
    from inrslam.rendering.fused_losses import composite_losses
    from inrslam.rendering.losses import weighted_total
    from inrslam.rendering.sampling import sample_depths

    cfg, T = LossConfig(), 0.1
    g = torch.Generator().manual_seed(R)
    D = 0.5 + 2.5 * torch.rand(R, generator=g)
    z = torch.sort(D[:, None] + 0.3 * torch.randn(R, S, generator=g), dim=1).values
    s0 = (D[:, None] - z) / T + 0.2 * torch.randn(R, S, generator=g)
    w0 = torch.rand(R, S, generator=g) / S
    c0 = torch.rand(R, S, 3, generator=g)
    C = torch.rand(R, 3, generator=g)

    def torch_step():
        w, c, s = (x.clone().requires_grad_() for x in (w0, c0, s0))
        out = RenderOutput(*composite(w, c, z), w, s, z)
        compute_losses(out, C, D, cfg, T)["total"].backward()

    def fused_step():
        w, c, s = (x.clone().requires_grad_() for x in (w0, c0, s0))
        terms, _ = composite_losses(w, c, z, s, C, D, T, cfg.center_band, cfg.free_space_target, True, True)
        weighted_total(terms, cfg, True).backward()

    a, b = interleaved(torch_step, fused_step, reps)
    print(f"{R} rays x {S}: autograd {a:.2f} ms, fused {b:.2f} ms per forward + backward: {a / b:.2f}x", flush=True)

    dirs = torch.cat([torch.rand(R, 2, generator=g) - 0.5, torch.ones(R, 1)], dim=1)
    origins, box = torch.zeros(R, 3), torch.tensor([[-4.0, 4.0]] * 3)
    D2 = D.clone()
    D2[::10] = 0  # some rays without depth

    def sampler(kernel: str):
        return lambda: sample_depths(D2, dirs, origins, box, SamplingConfig(), T, g, kernel)

    a, b = interleaved(sampler("torch"), sampler("numba"), reps)
    print(f"{R} rays x {S}: sampling torch {a:.2f} ms, numba {b:.2f} ms: {a / b:.2f}x", flush=True)


def interleaved(first, second, reps: int) -> tuple[float, float]:
    """Median ms of each callable over `reps` alternating calls, after one warm-up call each (numba compiles or
    loads its cache)."""
    times: list[list[float]] = [[], []]
    for step in (first, second):
        step()
    for _ in range(reps):
        for k, step in enumerate((first, second)):
            t0 = time.perf_counter()
            step()
            times[k].append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times[0]), statistics.median(times[1])


if __name__ == "__main__":
    main()
