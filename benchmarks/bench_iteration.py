"""One tracking and one mapping iteration (loss forward + backward, no optimiser step) at `paper` settings, with the
CPU kernels added one at a time, interleaved in one process on the same map and rays (median of --reps; steadier
on a noisy machine than whole runs one after the other). Prints ms per iteration and the ratio to the first row;
never asserted in tests.

    python benchmarks/bench_iteration.py                              # dense, builtin:room
    python benchmarks/bench_iteration.py --encoding hash --reps 40

Rows: `paper` as it runs (fused lookups, numba sampler: bit-identical to the torch one), then the torch sampler
(the reference, for its share), then `field.decoder_kernel=numba`, then also `loss.kernel=numba`. For the F with
planes (tri-plane, TensoRF, the hybrids) also `paper` and every fused kernel with the per-level plane sums / plane x
line products in autograd (the references of `fields.kernels.combine`, bit-identical to the kernels), for their
share. For the MLP the `field.decoder_kernel=numba` row runs its float32 network in blocks of samples
(`fields.kernels.blocked_mlp`), and two more rows give `paper` with `field.mlp.precision=bfloat16` (its hidden layers
and heads under bfloat16 autocast).

    python benchmarks/bench_iteration.py --encoding mlp --reps 5
"""

from __future__ import annotations

import argparse
import functools

from iteration_setup import add_map_arguments, interleaved, machine_line, paper_map


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_map_arguments(ap, frames=6)
    args = ap.parse_args()
    import inrslam.fields.encoders as encoders_mod
    import inrslam.slam.model as model_mod
    from inrslam.fields.config import MlpPrecision
    from inrslam.fields.kernels.combine import plane_sum, vm_product
    from inrslam.fields.models import MLPField
    from inrslam.rendering.sampling import sample_depths

    bench = paper_map(args.encoding, args.data, args.frames)
    model = bench.model

    def variant(sampler: str, decoder: str, loss: str, combine: str = "auto", precision: str = "float32") -> None:
        model_mod.sample_depths = functools.partial(sample_depths, kernel=sampler)  # type: ignore[assignment]
        encoders_mod.vm_product = (  # type: ignore[assignment]
            lambda f, levels, faithful, backend: vm_product(f, levels, faithful, combine))
        encoders_mod.plane_sum = lambda f, levels, backend: plane_sum(f, levels, combine)  # type: ignore[assignment]
        model.field.decoder_backend = decoder
        model.cfg.loss.kernel = loss
        if isinstance(model.field, MLPField):
            model.field.precision = MlpPrecision(precision)

    variants = [("paper (numba sampler)", ("auto", "torch", "torch")), ("torch sampler", ("torch", "torch", "torch")),
                ("+ decoder_kernel=numba", ("auto", "numba", "torch")),
                ("+ loss.kernel=numba", ("auto", "numba", "numba"))]
    if args.encoding in ("triplane", "tensorf", "dense+tri", "hash+tri"):
        variants += [("paper, planes combined autograd", ("auto", "torch", "torch", "torch")),
                     ("all fused, planes autograd", ("auto", "numba", "numba", "torch"))]
    if args.encoding == "mlp":
        variants += [("paper, mlp.precision=bfloat16", ("auto", "torch", "torch", "auto", "bfloat16")),
                     ("+ loss.kernel=numba, bfloat16", ("auto", "torch", "numba", "auto", "bfloat16"))]

    print(machine_line(f"{args.data}, F={args.encoding}, paper settings, median of {args.reps}"))
    for name, step in (("tracking", bench.track_iter), (f"mapping ({bench.cfg.slam.map_pixels} rays)", bench.map_iter)):
        ms = interleaved(step, {label: functools.partial(variant, *v) for label, v in variants}, args.reps)
        base = ms[variants[0][0]]
        print(f"{name} iteration:")
        for label, _ in variants:
            print(f"  {label:<32} {ms[label]:7.2f} ms  {base / ms[label]:5.2f}x", flush=True)
    variant("auto", "torch", "torch")
    encoders_mod.vm_product, encoders_mod.plane_sum = vm_product, plane_sum  # type: ignore[assignment]


if __name__ == "__main__":
    main()
