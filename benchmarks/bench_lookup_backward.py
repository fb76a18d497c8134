"""The fused lookups' backward before and after its two changes, interleaved in one process on the same map and rays
(median of --reps): a tracking iteration, a mapping iteration, and a mapping iteration whose camera pose is optimised
too (as `paper`'s bundle adjustment does with every keyframe but the first), at `paper` settings with every fused
kernel. Never asserted in tests.

    python benchmarks/bench_lookup_backward.py                  # dense, builtin:room
    python benchmarks/bench_lookup_backward.py --encoding hash

"Before": the accumulator's touched rows counted and drained one level per thread (`marked_runs` with one run per
level: a fine dense level holds almost every touched row, so one thread did nearly all of it, as the old kernels,
which counted each level at the end of the accumulate kernel) and the gradient to the points summed into a zeroed
(N, 3) float64 array, then cast to float32. "After": counted and drained in runs of `sparse_rows.DRAIN_CHUNK` bitmap
bytes over every thread, and the points' gradient written in float32 straight from the float64 sums
(`function._input_grad`). Both give the same bits. See docs/speed.md, "The lookups' backward".
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from iteration_setup import FUSED, add_map_arguments, interleaved, machine_line, paper_map


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_map_arguments(ap, encodings=["dense", "hash"])
    args = ap.parse_args()
    import numpy as np
    import torch

    import inrslam.fields.kernels.function as function
    import inrslam.fields.kernels.sparse_rows as sparse_rows

    bench = paper_map(args.encoding, args.data, args.frames, FUSED)
    runs, input_grad = sparse_rows.marked_runs, function._input_grad

    def runs_per_level(rows, mark_off, mark):
        return runs(rows, mark_off, mark, 1 << 62)

    def input_grad_float64(xn, table, layout, jac, g_np):
        if jac is None:
            return input_grad(xn, table, layout, jac, g_np)
        gx64 = np.zeros((xn.shape[0], 3), np.float64)
        function.trilinear.tri_backward_x_jac(jac, g_np, gx64)
        return torch.from_numpy(gx64).to(xn.dtype)

    def use(r, ig) -> Callable[[], None]:
        def setter() -> None:
            sparse_rows.marked_runs = r
            function._input_grad = ig
        return setter

    model, rays, c2w = bench.model, bench.map_rays, bench.map_pose

    def map_ba_iter() -> None:
        pose = c2w.clone().requires_grad_()
        losses, _ = model.loss(pose, *rays, torch.Generator().manual_seed(0))
        losses["total"].backward()
        model.zero_grad(set_to_none=True)

    variants = {"before": use(runs_per_level, input_grad_float64), "after": use(runs, input_grad)}
    print(machine_line(f"{args.data}, F={args.encoding}, paper settings + every fused kernel, median of {args.reps}"))
    for name, step in (("tracking", bench.track_iter), (f"mapping ({bench.cfg.slam.map_pixels} rays)", bench.map_iter),
                       ("mapping, pose optimised too", map_ba_iter)):
        ms = interleaved(step, variants, args.reps)
        print(f"{name} iteration: before {ms['before']:7.2f} ms, after {ms['after']:7.2f} ms: "
              f"{ms['before'] / ms['after']:4.2f}x", flush=True)
    use(runs, input_grad)()


if __name__ == "__main__":
    main()
