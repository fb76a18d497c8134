"""The grid field's two decoders in one fused call (`fields.kernels.mlp.mlp2_pair`, used with
`field.decoder_kernel=numba|auto` and `field.coupling=coupled_base`) against two calls (the code before): one tracking
and one mapping iteration at `paper` settings with every fused kernel, interleaved in one process on the same map
and rays (median of --reps). Never asserted in tests.

    python benchmarks/bench_decoder_pair.py                     # dense, builtin:room
    python benchmarks/bench_decoder_pair.py --encoding hash

"Two calls" disables the pair for the run (`EncoderField._decode_pair` returns None): each decoder then concatenates
its own input and runs its own fused kernel, as before. "One call on [f, γ]" is the pair as it was before its kernel
took f and γ apart (`Mlp2Fn` on their concatenation, its (N, 4) output sliced): the same values bit for bit, with the
concatenation, the slices' copies and a strided colour. See docs/speed.md, "Fused grid decoders".
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

    def concatenated(self, feat, gam):
        """The pair before its kernel took f and γ apart: `Mlp2Fn` on [f, γ], its (N, 4) output sliced."""
        import torch

        from inrslam.fields.kernels.mlp import Mlp2Fn
        from inrslam.fields.models import FieldOutput

        ng = gam.shape[1]
        w1c = torch.cat([self.rgb_net[0].weight[:, ng:], self.rgb_net[0].weight[:, :ng]], dim=1)
        w1 = torch.cat([self.sdf_net[0].weight, w1c])
        w2 = torch.block_diag(self.sdf_net[2].weight, self.rgb_net[2].weight)
        y = Mlp2Fn.apply(torch.cat([feat, gam], dim=-1), w1, w2)
        return FieldOutput(y[:, 0], y[:, 1:])

    def use(impl) -> Callable[[], None]:
        def setter() -> None:
            EncoderField._decode_pair = impl  # type: ignore[method-assign]
        return setter

    variants = {"two": use(lambda self, feat, gam: None), "cat": use(concatenated), "one": use(pair)}
    print(machine_line(f"{args.data}, F={args.encoding}, paper settings + every fused kernel, median of {args.reps}"))
    for name, step in (("tracking", bench.track_iter), (f"mapping ({bench.cfg.slam.map_pixels} rays)", bench.map_iter)):
        ms = interleaved(step, variants, args.reps)
        print(f"{name} iteration: two decoder calls {ms['two']:7.2f} ms, one call on [f, γ] {ms['cat']:7.2f} ms, one "
              f"call on f and γ {ms['one']:7.2f} ms: {ms['two'] / ms['one']:4.2f}x / {ms['cat'] / ms['one']:4.2f}x",
              flush=True)
    EncoderField._decode_pair = pair  # type: ignore[method-assign]


if __name__ == "__main__":
    main()
