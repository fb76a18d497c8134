"""The grid field's two decoders in one fused call (`fields.kernels.mlp.mlp2_pair`, used with
`field.decoder_kernel=numba|auto` and `field.coupling=coupled_base`) against two calls (the code before): one tracking
and one mapping iteration at `paper` settings with every fused kernel, interleaved in one process on the same map
and rays (median of --reps). Never asserted in tests.

    python benchmarks/bench_decoder_pair.py                     # dense, builtin:room
    python benchmarks/bench_decoder_pair.py --encoding hash

"Two calls" disables the pair for the run (`EncoderField._decode_pair` returns None): each decoder then concatenates
its own input and runs its own fused kernel, as before. See docs/speed.md, "Fused grid decoders".
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from iteration_setup import add_map_arguments, interleaved, machine_line, paper_map


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_map_arguments(ap, encodings=["dense", "hash"])
    args = ap.parse_args()
    from inrslam.fields.models import EncoderField

    bench = paper_map(args.encoding, args.data, args.frames, ["field.decoder_kernel=numba", "loss.kernel=numba"])
    pair = EncoderField._decode_pair

    def use_pair(on: bool) -> Callable[[], None]:
        def setter() -> None:
            EncoderField._decode_pair = pair if on else (lambda self, feat, gam: None)  # type: ignore[method-assign]
        return setter

    print(machine_line(f"{args.data}, F={args.encoding}, paper settings + every fused kernel, median of {args.reps}"))
    for name, step in (("tracking", bench.track_iter), (f"mapping ({bench.cfg.slam.map_pixels} rays)", bench.map_iter)):
        ms = interleaved(step, {"two": use_pair(False), "one": use_pair(True)}, args.reps)
        print(f"{name} iteration: two decoder calls {ms['two']:7.2f} ms, one call {ms['one']:7.2f} ms: "
              f"{ms['two'] / ms['one']:4.2f}x", flush=True)
    EncoderField._decode_pair = pair  # type: ignore[method-assign]


if __name__ == "__main__":
    main()
