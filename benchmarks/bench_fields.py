"""Benchmark of the fused numba kernels vs the PyTorch reference (same run, same inputs). Prints a table.

    python benchmarks/bench_fields.py [--reps 5] [--threads 1]

Points are mapping-batch-like: rays (60 samples each) through a 6 x 5 x 3 m box. Times are medians over reps
after three warm-up calls per case (numba JIT is cached on disk). Peak memory = rise of the process's peak RSS
(/proc/self/status VmHWM, reset through /proc/self/clear_refs) during one steady-state mapping step.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import statistics
import time

import numpy as np
import torch

from inrslam.fields import FieldConfig, KernelChoice, build_field, make_optimizer, model_size_mb
from inrslam.fields.encoders import GridEncoder, TriPlaneEncoder
from inrslam.fields.resolution import plane_sizes

BOX = np.array([[0.0, 6.0], [0.0, 5.0], [0.0, 3.0]])
EXT = BOX[:, 1] - BOX[:, 0]


def ray_points(n: int, seed: int = 0) -> torch.Tensor:
    """n/60 rays x 60 samples, normalised coordinates in [0,1]^3 (a few samples leave the box and are clamped)."""
    g = torch.Generator().manual_seed(seed)
    rays = n // 60
    o = torch.rand(rays, 1, 3, generator=g) * 0.6 + 0.2
    d = torch.nn.functional.normalize(torch.randn(rays, 1, 3, generator=g), dim=-1) / torch.from_numpy(EXT).float()
    t = torch.linspace(0.1, 3.0, 60)[None, :, None]
    return (o + d * t).reshape(-1, 3).contiguous()


def timeit(fn, reps: int, warmup: int = 3) -> float:
    """Median wall time of fn over reps, after ``warmup`` untimed calls (numba cache load / JIT, one-time
    workspaces and allocator growth are all paid there)."""
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _peak_rss_reset() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _rss_kib(key: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1])
    return 0


def peak_delta_mb(fn) -> float:
    """Peak RSS rise (MiB) while running fn (NaN if the peak cannot be reset); free heap pages are returned to
    the OS first (malloc_trim) so that transient allocations show up."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:
        pass
    if not _peak_rss_reset():
        return float("nan")
    base = _rss_kib("VmRSS:")
    fn()
    return (_rss_kib("VmHWM:") - base) / 1024


def encoder_fwd_bwd(enc, x: torch.Tensor, kernel: str, wrt: str):
    enc.kernel = KernelChoice(kernel)
    enc.table.requires_grad_(wrt == "params")
    cot = torch.randn(x.shape[0], enc.out_dim)

    def run():
        enc.table.grad = None
        xr = x.clone().requires_grad_(wrt == "inputs")
        (enc(xr) * cot).sum().backward()

    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None,
                    help="torch and numba threads for both paths (default: all cores); 1 separates kernel cost from "
                         "thread-pool effects")
    args = ap.parse_args()
    if args.threads:
        import numba

        torch.set_num_threads(args.threads)
        numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    torch.manual_seed(0)
    rows = []

    def add(name, n, t_fused, t_ref, extra=""):
        rows.append((name, n, t_fused, t_ref, t_ref / t_fused, extra))
        print(f"{name:<38} {n:>7} {t_fused * 1e3:>10.1f} {t_ref * 1e3:>10.1f} {t_ref / t_fused:>7.1f}x  {extra}",
              flush=True)

    try:
        load = open("/proc/loadavg").read().split()[:3]
    except OSError:
        load = ["?"]
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}; numba threads "
          f"{__import__('numba').get_num_threads()}; load average {' '.join(load)}")
    print(f"{'case':<38} {'points':>7} {'fused ms':>10} {'ref ms':>10} {'ratio':>8}")
    hash_enc = GridEncoder(EXT, 0.24, 0.02, 16, 2, True, 19, False, 1e-4, KernelChoice.NUMBA)
    tri_enc = TriPlaneEncoder(plane_sizes(EXT, 0.24, 0.02, 2, False), 2, False, 0.01, KernelChoice.NUMBA)
    for n in (61_440, 122_880):
        x = ray_points(n)
        for wrt in ("params", "inputs"):
            tf = timeit(encoder_fwd_bwd(hash_enc, x, "numba", wrt), args.reps)
            tr = timeit(encoder_fwd_bwd(hash_enc, x, "torch", wrt), args.reps)
            add(f"hash 16x2 2^19 fwd+bwd->{wrt}", n, tf, tr)
        for wrt in ("params", "inputs"):
            tf = timeit(encoder_fwd_bwd(tri_enc, x, "numba", wrt), args.reps)
            tr = timeit(encoder_fwd_bwd(tri_enc, x, "torch", wrt), args.reps)
            add(f"tri-plane 2x2 fwd+bwd->{wrt}", n, tf, tr)

    # Grid decoders (7 -> 32 -> 1 and -> 3, no biases, `paper` settings): fused mlp2 vs autograd, forward + backward
    # to the inputs only (tracking) and to inputs and weights (mapping).
    from inrslam.fields.kernels.mlp import mlp2

    for n in (61_440, 122_880):
        x = torch.randn(n, 7)
        for wrt in ("inputs", "params"):
            ws = [torch.randn(32, 7) / 7 ** 0.5, torch.randn(1, 32) / 32 ** 0.5, torch.randn(3, 32) / 32 ** 0.5]
            ws = [w.requires_grad_(wrt == "params") for w in ws]
            xg = x.clone().requires_grad_()

            def dec(kernel, xg=xg, ws=ws):
                def run():
                    xg.grad = None
                    for w in ws:
                        w.grad = None
                    (mlp2(xg, ws[0], ws[1], kernel).sum() + mlp2(xg, ws[0], ws[2], kernel).sum()).backward()
                return run

            add(f"grid decoders 7-32-1/3 fwd+bwd->{wrt}", n, timeit(dec("numba"), args.reps),
                timeit(dec("torch"), args.reps))

    # Plane decoders (tri-plane, TensoRF: 7 -> 32 -> 32 -> 1 and -> 3, with biases): fused mlp3 vs autograd (the
    # nn.Sequential the fields run with field.decoder_kernel=torch), forward + backward to the inputs only (tracking)
    # and to inputs and weights (as the grid decoders' rows).
    from inrslam.fields.models import plane_decoder, run_plane_decoder

    for n in (61_440, 122_880):
        x = torch.randn(n, 7)
        for wrt in ("inputs", "params"):
            nets = [plane_decoder(7, 32, 1), plane_decoder(7, 32, 3)]
            for net in nets:
                net.requires_grad_(wrt == "params")
            xg = x.clone().requires_grad_()

            def pdec(kernel, xg=xg, nets=nets):
                def run():
                    xg.grad = None
                    for net in nets:
                        net.zero_grad(set_to_none=True)
                    sum(run_plane_decoder(net, xg, kernel).sum() for net in nets).backward()
                return run

            add(f"plane decoders 7-32-32-1/3 fwd+bwd->{wrt}", n, timeit(pdec("numba"), args.reps),
                timeit(pdec("torch"), args.reps))

    # The per-level plane combinations, forward + backward to the lookup's features: tri-plane's sum of 2 x 3 planes
    # and TensoRF's products of 2 x (3 planes, 3 lines), 2 features; fused (kernels.combine, bit-identical) vs autograd.
    from inrslam.fields.kernels.combine import plane_sum, vm_product

    for n in (61_440, 122_880):
        for name, width, combine in (("tri-plane sums 2x2", 6, lambda f, k: plane_sum(f, 2, k)),
                                     ("TensoRF products 2x2", 12, lambda f, k: vm_product(f, 2, False, k))):
            feats = torch.randn(n, width, 2).requires_grad_()
            cot = torch.randn(n, 4)

            def comb(kernel, feats=feats, cot=cot, combine=combine):
                def run():
                    feats.grad = None
                    combine(feats, kernel).backward(cot)
                return run

            add(f"{name} fwd+bwd", n, timeit(comb("numba"), args.reps), timeit(comb("torch"), args.reps))

    # Dense 2-level grid (24 cm, 2 cm) on the 6 x 5 x 3 m box: full mapping step.
    for n in (61_440, 122_880):
        res = {}
        for kernel in ("numba", "torch"):
            torch.manual_seed(0)
            cfg = FieldConfig(encoding="dense", kernel=KernelChoice(kernel))
            field = build_field(cfg, BOX)
            # fused: lazy row-wise Adam; reference: plain torch.optim.Adam on the dense gradient
            opt = make_optimizer(field, 0.01) if kernel == "numba" else torch.optim.Adam(field.parameters(), 0.01)
            xw = torch.from_numpy(BOX[:, 0]).float() + ray_points(n, seed=1) * torch.from_numpy(EXT).float()
            target = torch.randn(n)

            def step():
                opt.zero_grad(set_to_none=True)
                out = field(xw)
                loss = (out.sdf - target).square().mean() + out.rgb_logits.square().mean()
                loss.backward()
                opt.step()

            t = timeit(step, args.reps)  # the warm-up allocates Adam's moments
            peak = peak_delta_mb(step)
            res[kernel] = (t, peak, model_size_mb(field))
            del field, opt
        pm = res["numba"][2]
        add("dense 2x2 @2cm mapping step", n, res["numba"][0], res["torch"][0],
            f"params {pm:.0f} MiB; step peak +{res['numba'][1]:.0f} MiB fused ({res['numba'][1] / pm:.2f}x params)"
            f", +{res['torch'][1]:.0f} MiB ref ({res['torch'][1] / pm:.2f}x)")

    # The same dense grid without decoders: encoder lookup fwd+bwd + optimizer step on the table only.
    enc_cfg = (EXT, 0.24, 0.02, 2, 2, False, 19, False, 1e-4)
    for n in (61_440, 122_880):
        res = {}
        x = ray_points(n, seed=2)
        for kernel in ("numba", "torch"):
            enc = GridEncoder(*enc_cfg, KernelChoice(kernel))
            opt = make_optimizer(enc, 0.01) if kernel == "numba" else torch.optim.Adam(enc.parameters(), 0.01)
            cot = torch.randn(n, enc.out_dim)

            def estep():
                opt.zero_grad(set_to_none=True)
                (enc(x) * cot).sum().backward()
                opt.step()

            res[kernel] = (timeit(estep, args.reps), peak_delta_mb(estep), model_size_mb(enc))
            del enc, opt
        pm = res["numba"][2]
        add("dense 2x2 @2cm encoder-only step", n, res["numba"][0], res["torch"][0],
            f"step peak +{res['numba'][1]:.0f} MiB fused ({res['numba'][1] / pm:.2f}x), "
            f"+{res['torch'][1]:.0f} MiB ref ({res['torch'][1] / pm:.2f}x)")

    print("\ntargets: hash >= 10x (params and inputs), dense mapping step >= 4x with peak <= 2x params, "
          "tri-plane >= 2x; grid and plane decoders: none (field.decoder_kernel, docs/speed.md)")


if __name__ == "__main__":
    main()
