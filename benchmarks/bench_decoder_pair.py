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
import os
import platform
import statistics
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--encoding", default="dense", choices=["dense", "hash"])
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--frames", type=int, default=8, help="frames run first to build the map")
    ap.add_argument("--reps", type=int, default=30)
    args = ap.parse_args()
    import torch

    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.fields.models import EncoderField
    from inrslam.slam.frame_tensors import FrameTensors
    from inrslam.slam.system import SlamSystem
    from inrslam.slam.tracking import frozen

    cfg = load_config(preset="paper", overrides=[
        f"data.path={args.data}", f"data.max_frames={args.frames + 1}", f"field.encoding={args.encoding}",
        "field.decoder_kernel=numba", "loss.kernel=numba", "slam.init_iters=100", "slam.checkpoint_every=0",
        "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false"])
    system = SlamSystem(cfg, open_dataset(cfg.data))
    for i in range(args.frames):
        system.process(i)
    model = system.model
    ft = FrameTensors(system.dataset[args.frames], system.device)
    g = torch.Generator().manual_seed(0)
    c2w = system.est[args.frames - 1].clone()
    track_rays = ft.sample(cfg.slam.track_pixels, g, cfg.slam.track_edge)
    map_rays = ft.sample(cfg.slam.map_pixels, g)
    pair = EncoderField._decode_pair

    def use_pair(on: bool) -> None:
        EncoderField._decode_pair = pair if on else (lambda self, feat, gam: None)  # type: ignore[method-assign]

    def track_iter() -> None:
        pose = c2w.clone().requires_grad_()
        with frozen(model):
            losses, _ = model.loss(pose, *track_rays, g)
            losses["total"].backward()

    def map_iter() -> None:
        losses, _ = model.loss(c2w, *map_rays, g)
        losses["total"].backward()
        model.zero_grad(set_to_none=True)

    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}"
          f", threads {torch.get_num_threads()}; {args.data}, F={args.encoding}, paper settings + every fused kernel, "
          f"median of {args.reps}")
    for name, step in (("tracking", track_iter), (f"mapping ({cfg.slam.map_pixels} rays)", map_iter)):
        times: dict[bool, list[float]] = {True: [], False: []}
        for on in (False, True):  # warm-up
            use_pair(on)
            step()
        for _ in range(args.reps):
            for on in (False, True):
                use_pair(on)
                t0 = time.perf_counter()
                step()
                times[on].append((time.perf_counter() - t0) * 1e3)
        two, one = statistics.median(times[False]), statistics.median(times[True])
        print(f"{name} iteration: two decoder calls {two:7.2f} ms, one call {one:7.2f} ms: {two / one:4.2f}x",
              flush=True)
    use_pair(True)


if __name__ == "__main__":
    main()
