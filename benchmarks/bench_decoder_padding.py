"""The grid decoders' backward with its input-side products padded to 8 columns for inputs 5-7 wide
(`fields.kernels.mlp.PAD_NARROW`, on in the library) against unpadded (off, the code before): the fused
pair alone on random inputs at the tracking and mapping batch sizes, then one tracking and one mapping iteration at
`paper` settings with every fused kernel, interleaved in one process on the same map and rays (median of --reps).
Never asserted in tests.

    python benchmarks/bench_decoder_padding.py                  # dense (input 7 wide: padded to 8), builtin:room
    python benchmarks/bench_decoder_padding.py --encoding hash

See docs/speed.md, "Fused grid decoders".
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from iteration_setup import add_map_arguments, fused_map, interleaved, module_switch


def pair_alone(n: int, n_in: int, need_w: bool, reps: int, variants: dict[str, Callable[[], None]]) -> dict:
    """Median ms of the fused pair's backward (7 -> 64 -> 4 at `paper`) on n random samples, per variant."""
    import torch

    from inrslam.fields.kernels.mlp import Mlp2SplitFn

    g = torch.Generator().manual_seed(0)
    xa, xb = torch.randn(n, n_in - 3, generator=g), torch.randn(n, 3, generator=g)
    w1, w2 = torch.randn(64, n_in, generator=g) / n_in ** 0.5, torch.randn(4, 64, generator=g) / 8
    w1.requires_grad_(need_w)
    w2.requires_grad_(need_w)
    xa.requires_grad_()
    xb.requires_grad_()
    cot = torch.randn(n, 1, generator=g), torch.randn(n, 3, generator=g)

    def step() -> None:
        ya, yb = Mlp2SplitFn.apply(xa, xb, w1, w2, 1)
        torch.autograd.backward((ya, yb), cot)

    return interleaved(step, variants, reps)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_map_arguments(ap, encodings=["dense", "hash"])
    args = ap.parse_args()
    import inrslam.fields.kernels.mlp as mlp

    variants = module_switch(mlp, "PAD_NARROW", {"unpadded": False, "padded": True})
    bench = fused_map(args)
    for n, need_w, what in ((61440, False, "tracking batch, input gradient"),
                            (122880, True, "mapping batch, input and weight gradients")):
        ms = pair_alone(n, 7, need_w, args.reps, variants)
        print(f"pair alone (7 -> 64 -> 4), {what}: unpadded {ms['unpadded']:6.2f} ms, padded {ms['padded']:6.2f} ms: "
              f"{ms['unpadded'] / ms['padded']:4.2f}x", flush=True)
    for name, step in (("tracking", bench.track_iter), (f"mapping ({bench.cfg.slam.map_pixels} rays)", bench.map_iter)):
        ms = interleaved(step, variants, args.reps)
        print(f"{name} iteration: unpadded {ms['unpadded']:6.2f} ms, padded {ms['padded']:6.2f} ms: "
              f"{ms['unpadded'] / ms['padded']:4.2f}x", flush=True)
    mlp.PAD_NARROW = True


if __name__ == "__main__":
    main()
