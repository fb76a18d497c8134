"""Shared set-up of the per-iteration benchmarks (`bench_iteration.py`, `bench_subnormal.py`,
`bench_decoder_pair.py`, `bench_render_kernel.py`): a `paper` map built over a few frames of a scene, and one
tracking and one mapping iteration (loss forward + backward, no optimiser step) on rays fixed once, so that code
variants can be timed interleaved in one process on the same work; the benchmark config of a `paper` run
(`paper_config`, also for `bench_slam.py` and `profile_frame.py`); every benchmark's first line (`machine_line`).
Not a benchmark itself."""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from inrslam.machine import cpu_line, openblas_core

#: Overrides that turn on every fused CPU kernel besides the lookups (which `paper` runs fused already).
FUSED = ["field.decoder_kernel=numba", "loss.kernel=numba", "render.kernel=numba"]


@dataclass
class IterationBench:
    cfg: Any  # the run's config
    model: Any  # the SceneModel after `frames` frames
    track_iter: Callable[[], None]  # one tracking iteration: the loss's gradient to a pose (map frozen)
    map_iter: Callable[[], None]  # one mapping iteration: the loss's gradient to the map (gradients cleared after)
    map_rays: Any = None  # the mapping iteration's rays (the arguments of `SceneModel.loss` after the pose)
    map_pose: Any = None  # (4, 4) camera-to-world pose of those rays


def paper_config(data: str, frames: int, encoding: str, init_iters: int, overrides: Sequence[str] = ()) -> Any:
    """The `paper` preset on `frames` frames of `data` with F = `encoding` and `init_iters` initialisation iterations,
    no checkpoints, mesh, evaluation or TensorBoard (benchmarks time the SLAM loop), then `overrides`."""
    from inrslam.config import load_config

    return load_config(preset="paper", overrides=[
        f"data.path={data}", f"data.max_frames={frames}", f"field.encoding={encoding}", f"slam.init_iters={init_iters}",
        "slam.checkpoint_every=0", "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false",
        *overrides])


def add_map_arguments(ap: argparse.ArgumentParser, frames: int = 8, encodings: Sequence[str] | None = None) -> None:
    """The options every per-iteration benchmark takes: `paper_map`'s --encoding (one of `encodings` if given),
    --data and --frames (default `frames`), and --reps."""
    ap.add_argument("--encoding", default="dense", choices=list(encodings) if encodings else None)
    ap.add_argument("--data", default="builtin:room")
    ap.add_argument("--frames", type=int, default=frames, help="frames run first to build the map")
    ap.add_argument("--reps", type=int, default=30)


def paper_map(encoding: str, data: str, frames: int, overrides: Sequence[str] = ()) -> IterationBench:
    """`paper` settings plus `overrides`, 100 initialisation iterations, frames 0..frames-1 processed; rays of
    frame `frames` sampled once (seed 0) at the tracking and mapping batch sizes."""
    import torch

    from inrslam.datasets import open_dataset
    from inrslam.slam.frame_tensors import FrameTensors
    from inrslam.slam.system import SlamSystem
    from inrslam.slam.tracking import frozen

    cfg = paper_config(data, frames + 1, encoding, 100, overrides)
    system = SlamSystem(cfg, open_dataset(cfg.data))
    for i in range(frames):
        system.process(i)
    model = system.model
    ft = FrameTensors(system.dataset[frames], system.device)
    g = torch.Generator().manual_seed(0)
    c2w = system.est[frames - 1].clone()
    track_rays = ft.sample(cfg.slam.track_pixels, g, cfg.slam.track_edge)
    map_rays = ft.sample(cfg.slam.map_pixels, g)

    def track_iter() -> None:
        pose = c2w.clone().requires_grad_()
        with frozen(model):
            losses, _ = model.loss(pose, *track_rays, g)
            losses["total"].backward()

    def map_iter() -> None:
        losses, _ = model.loss(c2w, *map_rays, g)
        losses["total"].backward()
        model.zero_grad(set_to_none=True)

    return IterationBench(cfg, model, track_iter, map_iter, map_rays, c2w)


def fused_map(args: argparse.Namespace) -> IterationBench:
    """`paper_map` with every fused kernel for `add_map_arguments`' options, after printing the benchmark's first line
    (machine, scene, F, repetitions, the seconds the map took to build)."""
    t0 = time.perf_counter()
    bench = paper_map(args.encoding, args.data, args.frames, FUSED)
    print(machine_line(f"{args.data}, F={args.encoding}, paper settings + every fused kernel, median of {args.reps}; "
                       f"map built in {time.perf_counter() - t0:.0f} s"))
    return bench


def machine_line(what: str, threads: bool = True) -> str:
    """'# machine: ..., cores, torch ..., OpenBLAS kernels ...[, threads ...]; <what>' for a benchmark's first line
    (`threads`: torch's thread count of this process; off where the benchmark runs its work elsewhere or says its
    threads in `what`). The OpenBLAS kernel set decides the fused decoders' speed (docs/speed.md, "Which BLAS
    kernels"), and `OPENBLAS_CORETYPE` overrides it: the line names it, and says when the variable chose it."""
    import os

    import torch

    core = openblas_core() or "unknown"
    forced = " (OPENBLAS_CORETYPE)" if os.environ.get("OPENBLAS_CORETYPE") else ""
    count = f", threads {torch.get_num_threads()}" if threads else ""
    return f"# machine: {cpu_line()}, torch {torch.__version__}, OpenBLAS kernels {core}{forced}{count}; {what}"


def module_switch(module: Any, name: str, values: dict[str, Any]) -> dict[str, Callable[[], None]]:
    """`interleaved`'s variants for a module-level switch: {label: a setter of module.<name> = value}, e.g.
    `module_switch(mlp, "KEEP_MASK", {"recompute": False, "mask": True})`."""
    def setter(value: Any) -> Callable[[], None]:
        return lambda: setattr(module, name, value)
    return {label: setter(value) for label, value in values.items()}


def interleaved(step: Callable[[], None], variants: dict[str, Callable[[], None]], reps: int) -> dict[str, float]:
    """Median ms of `step` under each variant (a setter called before each timed step), the variants taking turns
    rep by rep after one warm-up step each."""
    times: dict[str, list[float]] = {name: [] for name in variants}
    for setter in variants.values():
        setter()
        step()
    for _ in range(reps):
        for name, setter in variants.items():
            setter()
            t0 = time.perf_counter()
            step()
            times[name].append((time.perf_counter() - t0) * 1e3)
    return {name: statistics.median(t) for name, t in times.items()}
