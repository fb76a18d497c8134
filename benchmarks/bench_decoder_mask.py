"""The fused decoders' backward in tracking from the forward's ReLU masks (`fields.kernels.mlp.KEEP_MASK`, on in the
library) against recomputing the hidden layers (off, the code before): for the grid F the fused decoder pair alone on
random inputs at the tracking batch size (input gradient only: tracking freezes the map), then for every F one
tracking iteration at `paper` settings with every fused kernel, interleaved in one process on the same map and rays
(median of --reps). Mapping needs the weight gradients, which read the hidden layers themselves, so it recomputes
them either way. Never asserted in tests.

    python benchmarks/bench_decoder_mask.py                  # dense, builtin:room
    python benchmarks/bench_decoder_mask.py --encoding hash  # also triplane, tensorf, dense+tri, hash+tri

See docs/speed.md, "Fused grid decoders".
"""

from __future__ import annotations

import argparse

from bench_decoder_padding import pair_alone
from iteration_setup import add_map_arguments, fused_map, interleaved, module_switch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_map_arguments(ap, encodings=["dense", "hash", "triplane", "tensorf", "dense+tri", "hash+tri"])
    args = ap.parse_args()
    import inrslam.fields.kernels.mlp as mlp

    variants = module_switch(mlp, "KEEP_MASK", {"recompute": False, "mask": True})
    bench = fused_map(args)
    rows = [("tracking iteration", lambda: interleaved(bench.track_iter, variants, args.reps))]
    if args.encoding in ("dense", "hash"):
        rows.insert(0, ("pair alone (7 -> 64 -> 4), tracking batch, forward + input gradient",
                        lambda: pair_alone(61440, 7, False, args.reps, variants)))
    for what, measure in rows:
        ms = measure()
        print(f"{what}: recompute {ms['recompute']:6.2f} ms, mask {ms['mask']:6.2f} ms: "
              f"{ms['recompute'] / ms['mask']:4.2f}x", flush=True)
    mlp.KEEP_MASK = True


if __name__ == "__main__":
    main()
