"""`run_slam` / `resume_slam`: the plain functions behind `inrslam run` (scripts, notebooks and the benchmark call
them too). They sit above `slam` and `eval`: run SLAM, then evaluate the run directory it wrote."""

from __future__ import annotations

import dataclasses
import os
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from inrslam.config.loader import dump_config, load_config
from inrslam.errors import ConfigError, InrslamWarning, RunError
from inrslam.interrupts import hold_interrupts, interrupt
from inrslam.io.atomic import write_text
from inrslam.io.rundir import RunDir
from inrslam.malloc_env import tune_malloc
from inrslam.omp_env import load_guard
from inrslam.runner.writer import RunWriter
from inrslam.slam.system import Progress, SlamSystem
from inrslam.slam.systems import system_class
from inrslam.status import logger, stage
from inrslam.status import progress as report_progress

log = logger(__name__)


def run_slam(cfg, out_dir: str | os.PathLike, progress: Progress | None = None, overwrite: bool = False,
             threads: int | None = None) -> Path:
    """Run SLAM with a resolved `RunConfig`, write the run directory `out_dir` and evaluate it.

    Args:
        cfg: `RunConfig` (from `inrslam.config.load_config`).
        out_dir: run directory; must not hold a run unless `overwrite`.
        progress: optional callable(frame_index, n_frames, info) called after every frame.
        threads: torch / numba threads for this run when `cfg.threads` is 0 (None: every core); recorded in
            `run_info.json` and reused by `resume_slam`.
    """
    from inrslam.datasets import open_dataset
    from inrslam.fields.kernels.threads import resolve_threads, thread_scope

    tune_malloc()  # freed tensors stay in the heap for the next iteration (inrslam.malloc_env)
    out = Path(out_dir)
    rd = RunDir(out)
    if rd.holds_run() and not overwrite:
        raise ConfigError(f"{out} already holds a run: continue it with --resume {out}, or pass --overwrite")
    stage(log, f"opening the dataset {cfg.data.path}")
    dataset = open_dataset(cfg.data)
    threads = resolve_threads(cfg.threads or threads or 0)
    with thread_scope(threads), load_guard():
        stage(log, f"building the map: {cfg.field.encoding} x {cfg.render.name}, {len(dataset)} frames")
        system = system_class(cfg)(cfg, dataset)
        with rd.lock():  # one process at a time in a run folder (created here)
            if rd.holds_run() and not overwrite:  # another process made it since the check above
                raise ConfigError(f"{out} already holds a run: continue it with --resume {out}, or pass --overwrite")
            if overwrite:  # only now: a run that cannot start (bad data, bad config) leaves the old one as it was
                rd.clear()
            # the resolved config, with the thread count used: `--config` reproduces the run (docs/reliability.md)
            write_text(rd.config, dump_config(dataclasses.replace(cfg, threads=threads)))
            return _drive(system, RunWriter(system, rd, threads), resume=False, progress=progress)


def resume_slam(run_dir: str | os.PathLike, progress: Progress | None = None) -> Path:
    """Continue an interrupted run from its last checkpoint, with the run's own resolved `config.yaml`; a complete
    run is left as it is (resuming is idempotent)."""
    from inrslam.datasets import open_dataset
    from inrslam.fields.kernels.threads import resolve_threads, thread_scope

    tune_malloc()
    run_dir = Path(run_dir)
    rd = RunDir(run_dir)
    if not rd.holds_run():
        raise ConfigError(f"{run_dir}: not a run directory (no config.yaml)")
    if _left_complete(rd):  # checked before the lock too: a finished run may sit in a folder this user cannot write
        return run_dir
    with rd.lock():  # before anything is read: the process holding it may still be writing
        if _left_complete(rd):  # nothing to do (resuming it would mark it running again and redo its evaluation)
            return run_dir
        cfg = load_config(rd.config, preset=None, check_variants=False)  # checked when the run was made
        stage(log, f"opening the dataset {cfg.data.path}")
        dataset = open_dataset(cfg.data)
        info = rd.read_run_info() or {}  # what the interrupted run recorded of its machine and threads
        threads = _recorded_threads(info) if not cfg.threads else None
        threads = threads or resolve_threads(cfg.threads)
        _warn_other_blas(run_dir, info)
        with thread_scope(threads), load_guard():
            stage(log, f"building the map and loading the checkpoint {rd.checkpoint}")
            system = system_class(cfg)(cfg, dataset)
            return _drive(system, RunWriter(system, rd, threads), resume=True, progress=progress)


def _left_complete(rd: RunDir) -> bool:
    """Whether the run in `rd` is complete (said on the status line): `resume_slam` then leaves it as it is."""
    if not rd.is_complete():
        return False
    stage(log, f"{rd.root}: the run is already complete; nothing to resume (--overwrite runs it again)")
    return True


def _drive(system: SlamSystem, writer: RunWriter, resume: bool, progress: Progress | None) -> Path:
    """Feed the loop every remaining frame, writing as it goes; then the final outputs and the evaluation."""
    writer.start(resume)
    # Ctrl-C / SIGTERM (from `inrslam run`) let the frame in progress end; it is saved, then the run stops
    with hold_interrupts() as held:
        for i in range(system.state.next_frame, system.n_frames):
            held.note = f"finishing frame {i} and saving it, then stopping (Ctrl-C again stops at once)"
            if i == 0:  # the map's initialisation stops at once (it cannot be saved part-way)
                held.active = False
                with _initialisation_status(system):
                    writer.log(system.process(i))
                held.active = True
            else:
                writer.log(system.process(i))
            saved = writer.after_frame(i)
            try:
                if progress and held.signum is None:
                    progress(i, system.n_frames, system.progress_info(i))
            finally:  # a signal held by now (also one the callback saw before it failed) saves the frame
                if held.signum is not None:
                    if not saved:
                        writer.checkpoint()  # every finished frame is kept: a resume goes on from the next one
                    raise interrupt(held.signum)
    if held.signum is not None:  # arrived as the last frame's turn ended
        writer.checkpoint()
        raise interrupt(held.signum)
    metrics = writer.finish()
    return _evaluate(system, writer, metrics)


INIT_UPDATES = 50  # progress records of the first frame's initialisation (at most)


@contextmanager
def _initialisation_status(system: SlamSystem) -> Iterator[None]:
    """Status of frame 0, the map's initialisation (`slam.init_iters` optimiser steps): counted by a post-step hook
    on one of the run's optimisers, removed afterwards. It only observes: the steps are the same with or without it."""
    total = int(system.cfg.slam.init_iters)
    upto = "at most " if getattr(system.cfg.slam, "init_stop_window", 0) > 0 else ""  # may end on a plateau
    stage(log, f"initialising the map on frame 0 ({upto}{total} iterations; the first ones also load the numba "
               f"kernels)")
    optimizers = list(getattr(system.state, "optimizers", {}).values())
    if total <= 0 or not optimizers:
        yield
        return
    every = -(-total // INIT_UPDATES)  # ceil: at most INIT_UPDATES records
    done = 0

    def counted(optimizer, args, kwargs) -> None:
        nonlocal done
        done += 1
        if done % every == 0 or done == total:
            report_progress(log, "init", min(done, total), total)

    handle = optimizers[0].register_step_post_hook(counted)
    try:
        yield
    finally:
        handle.remove()
    if done < total:  # iterations without a step (a non-finite loss, or a mapper with other optimisers) end here too
        report_progress(log, "init", total, total)


def _recorded_threads(info: dict) -> int | None:
    """The thread count an interrupted run used (`info`: its `run_info.json`), so its resumed part sums in the same
    order."""
    n = info.get("threads")
    return int(n) if isinstance(n, int) and n > 0 else None


def _warn_other_blas(run_dir: Path, info: dict, current: str | None = None) -> str | None:
    """Warn (and return the message) when the run in `run_dir` is resumed on other OpenBLAS kernels than it started
    with (`machine.openblas_core` of `info`, its run_info.json; `current`: this process's, for tests): the fused
    decoders' products then round differently, so the resumed part is not bit for bit what an uninterrupted run
    would have computed."""
    from inrslam.machine import openblas_core

    started = (info.get("machine") or {}).get("openblas_core")
    now = openblas_core() if current is None else current
    if not started or not now or started == now:
        return None
    msg = (f"{run_dir}: the run started on OpenBLAS kernels {started} and resumes on {now} (OPENBLAS_CORETYPE): "
           "fused kernels round differently, so the result will not equal an uninterrupted run bit for bit")
    warnings.warn(msg, InrslamWarning, stacklevel=2)
    return msg


def _evaluate(system: SlamSystem, writer: RunWriter, metrics: dict) -> Path:
    """Held-out renders with the final map and estimated poses, the process metrics written with them, then every
    result metric (docs/metrics.md). A step that fails does not stop the others: what can be written is, the
    failure goes to log.jsonl with its traceback, and the run ends with one RunError naming every failed step."""
    from inrslam.eval.config import HeldoutDepth
    from inrslam.eval.heldout import heldout_metrics
    from inrslam.eval.run import evaluate_run

    ev = system.cfg.eval
    rd = writer.rd
    if ev.enabled and ev.heldout_every:
        # frames between keyframes (offset by half the mapping period), rendered without jitter
        depth = HeldoutDepth(ev.heldout_depth).value  # expected (weighted mean) or surface (SDF zero crossing)
        render = lambda c2w, intr: system.model.render_image(c2w, intr, n_coarse=ev.heldout_samples, depth=depth,
                                                             refine=ev.heldout_refine)
        sink = writer.write_render if system.cfg.output.renders else None
        stage(log, "rendering the held-out frames (full frames, without their depth)")
        with writer.step("held-out renders"):
            metrics.update(heldout_metrics(render, system.dataset, system.est, ev.heldout_every, ev.heldout_max,
                                           offset=system.cfg.slam.map_every // 2, sink=sink))
    writer.close_tensorboard()  # open until here: the held-out pictures go to TensorBoard too
    rd.write_metrics(metrics)
    writer.write_run_info("slam_done")
    if ev.enabled:
        with writer.step("evaluation"):
            evaluate_run(rd.root, ev)
    if writer.failures:
        raise RunError(f"{rd.root}: SLAM finished and its outputs are written, but {'; '.join(writer.failures)} "
                       f"(traceback in log.jsonl); after fixing it, evaluate with: inrslam eval {rd.root}")
    writer.write_run_info("complete")
    if not system.cfg.output.keep_checkpoint:  # only once complete: until then it is what a resume needs
        freed = rd.remove_checkpoints()
        writer.log([{"type": "checkpoint_removed", "bytes": freed}])
    return rd.root
