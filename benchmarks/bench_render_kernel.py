"""`render.kernel=numba` (fused G weights and normalised sample points) against `render.kernel=torch` (autograd,
the reference): first each piece alone, forward + backward, at a tracking (1024 rays) and a mapping (2048 rays)
batch of the paper's 60 samples per ray, float32; then one tracking and one mapping iteration at `paper` settings
with every other fused kernel on (`field.decoder_kernel=numba loss.kernel=numba`), the renderer's kernel switched
rep by rep in one process on the same map and rays (median of --reps). Never asserted in tests.

    python benchmarks/bench_render_kernel.py                    # SDF(density), the paper's G; dense
    python benchmarks/bench_render_kernel.py --render direct    # SDF(direct), `accurate`'s G
    python benchmarks/bench_render_kernel.py --encoding hash
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from iteration_setup import add_map_arguments, interleaved, machine_line, paper_map


def weights_alone(render: str, R: int, S: int, reps: int) -> tuple[float, float]:
    """Median ms of the weights' forward + backward (a random output gradient) by autograd and fused."""
    import torch

    from inrslam.rendering.config import RenderConfig
    from inrslam.rendering.renderers import build_renderer

    g = torch.Generator().manual_seed(R)
    D = 0.5 + 2.5 * torch.rand(R, 1, generator=g)
    z = torch.sort(D + 0.3 * torch.randn(R, S, generator=g), dim=1).values
    s0 = (D - z) / 0.1 + 0.2 * torch.randn(R, S, generator=g)
    g_out = torch.randn(R, S, generator=g)
    dirs = torch.tensor([[0.0, 0.0, 1.0]]).expand(R, 3)
    renderer = build_renderer(RenderConfig(name=render))

    def step() -> None:
        s = s0.clone().requires_grad_()
        renderer(s, z, dirs, None, 0.1).backward(g_out)

    ms = interleaved(step, {k: (lambda k=k: setattr(renderer, "kernel", k)) for k in ("torch", "numba")}, reps)
    return ms["torch"], ms["numba"]


def points_alone(R: int, S: int, reps: int) -> tuple[float, float]:
    """Median ms of the normalised sample points' forward + backward to origins and directions: reference, fused."""
    import torch

    from inrslam.fields.kernels.ray_points import ray_points_normalised, ray_points_normalised_torch

    g = torch.Generator().manual_seed(R)
    o0, d0 = torch.randn(R, 3, generator=g), torch.randn(R, 3, generator=g)
    z = torch.sort(0.2 + 4 * torch.rand(R, S, generator=g), dim=1).values
    lo, ext = torch.tensor([-3.0, -3.0, -1.0]), torch.tensor([6.0, 6.0, 3.0])
    g_out = torch.randn(R * S, 3, generator=g)
    fn = {"torch": ray_points_normalised_torch, "numba": ray_points_normalised}
    which = ["torch"]

    def step() -> None:
        o, d = o0.clone().requires_grad_(), d0.clone().requires_grad_()
        fn[which[0]](o, d, z, lo, ext).backward(g_out)

    ms = interleaved(step, {k: (lambda k=k: which.__setitem__(0, k)) for k in ("torch", "numba")}, reps)
    return ms["torch"], ms["numba"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--render", default="density", choices=["density", "direct"])
    add_map_arguments(ap)
    args = ap.parse_args()

    print(machine_line(f"SDF({args.render}), float32, median of {args.reps} (each piece alone: of {3 * args.reps})"))
    for R in (1024, 2048):
        a, b = weights_alone(args.render, R, 60, 3 * args.reps)
        print(f"weights alone, {R} rays x 60: autograd {a:.2f} ms, fused {b:.2f} ms per forward + backward: "
              f"{a / b:.2f}x", flush=True)
        a, b = points_alone(R, 60, 3 * args.reps)
        print(f"sample points alone, {R} rays x 60: autograd {a:.2f} ms, fused {b:.2f} ms per forward + backward: "
              f"{a / b:.2f}x", flush=True)
    bench = paper_map(args.encoding, args.data, args.frames,
                      ["field.decoder_kernel=numba", "loss.kernel=numba", f"render.name={args.render}"])
    renderer = bench.model.renderer

    def kernel(name: str) -> Callable[[], None]:
        return lambda: setattr(renderer, "kernel", name)

    print(f"# {args.data}, F={args.encoding}, paper settings + the fused decoders and losses")
    for name, step in (("tracking", bench.track_iter), (f"mapping ({bench.cfg.slam.map_pixels} rays)", bench.map_iter)):
        ms = interleaved(step, {"torch": kernel("torch"), "numba": kernel("numba")}, args.reps)
        print(f"{name} iteration: render.kernel=torch {ms['torch']:7.2f} ms, numba {ms['numba']:7.2f} ms: "
              f"{ms['torch'] / ms['numba']:4.2f}x", flush=True)


if __name__ == "__main__":
    main()
