"""Executors: run `inrslam.bench.worker.run_one(**call)` for many calls and yield each result as it finishes.

One interface, `Executor.run(calls) -> Iterator[dict]`, registered in `EXECUTORS` (local, ray, slurm). Every
executor runs the same module-level function, so results do not depend on the executor. Closing the iterator early
(the sweep was asked to stop) cancels the work not yet finished.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections import deque
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing.connection import wait as wait_for_processes
from pathlib import Path
from typing import Iterator, Protocol

from inrslam.bench.slurm_jobs import (
    INFLIGHT_FILE,
    RECORDED_CLUSTERS,
    InflightBook,
    ReattachPlan,
    attach_job,
    local_states,
    plan_reattach,
    read_inflight,
    sacct_states,
    settled,
)
from inrslam.bench.worker import run_one
from inrslam.errors import ConfigError, InrslamError
from inrslam.interrupts import hold_interrupts, interrupt, signals_blocked
from inrslam.registry import Registry
from inrslam.status import logger

log = logger(__name__)


@dataclass
class ExecutorOptions:
    """Options shared by the executors (each uses the ones that apply to it)."""

    jobs: int = 1  # local: parallel worker processes; ray/slurm: used to derive cpus_per_run when not given
    folder: str = "."  # sweep output folder (slurm logs go to folder/slurm)
    address: str | None = None  # ray: cluster address (None = start a local instance unless one is running)
    partition: str | None = None  # slurm: partition
    time_min: int = 60  # slurm: time limit per run, minutes
    cpus_per_run: int | None = None  # CPU cores (= torch threads) per run; None = cores // jobs (slurm: 4;
    # ray: the cluster's CPUs // jobs, at most one node's)
    gpus_per_run: float = 0  # ray/slurm: GPUs per run
    mem_gb: float | None = None  # slurm: memory per run
    cluster: str | None = None  # slurm: submitit cluster; None = auto (slurm), "local" or "debug" for testing
    poll_s: float | None = None  # slurm: seconds between job-state polls (default 10 on slurm, 0.2 otherwise)

    def threads(self, default: int | None = None) -> int:
        if self.cpus_per_run:
            return int(self.cpus_per_run)
        if default:
            return default
        return max(1, (os.cpu_count() or 1) // max(1, self.jobs))


class Executor(Protocol):
    def run(self, calls: list[dict]) -> Iterator[dict]:
        """Execute `run_one(**call)` for each call; yield its result dict as soon as it is available."""


EXECUTORS: Registry[type] = Registry("executor")


def make_executor(name: str, options: ExecutorOptions) -> Executor:
    """Build the executor registered as `name`."""
    return EXECUTORS.get(name)(options)


def failed_result(call: dict, error: str) -> dict:
    """Result of a call whose worker died or could not report back."""
    run = call["run"]
    return {"name": run["name"], "run_dir": str(Path(call["out_dir"]) / run["name"]), "status": "failed",
            "error": error, "seconds": None, "pid": None}


@EXECUTORS.register("local", help="process pool on this machine (spawn, one fresh process per run)")
class LocalExecutor:
    """`jobs` spawn processes, a fresh one per run (so per-run peak memory is measured alone).

    A run that kills its process (segfault, out of memory) breaks the pool; the runs in flight are then retried one
    at a time so the culprit is identified and recorded as failed while the others complete.
    """

    def __init__(self, options: ExecutorOptions):
        self.jobs = max(1, int(options.jobs))
        self.threads = options.threads()

    def run(self, calls: list[dict]) -> Iterator[dict]:
        ctx = mp.get_context("spawn")
        queue, suspects = deque(calls), deque()
        while queue or suspects:
            isolated = bool(suspects)
            src, width = (suspects, 1) if isolated else (queue, self.jobs)
            pool = ProcessPoolExecutor(max_workers=width, mp_context=ctx, max_tasks_per_child=1)
            inflight: dict = {}
            try:
                broken = False
                while (src or inflight) and not broken:
                    while src and len(inflight) < width:
                        call = src.popleft()
                        inflight[pool.submit(run_one, threads=self.threads, **call)] = call
                    done = set()
                    while not done:  # in steps: a signal taken on another thread is handled by the next step
                        done, _ = wait(inflight, timeout=WAKE_S, return_when=FIRST_COMPLETED)
                    for fut in done:
                        call = inflight.pop(fut)
                        try:
                            res = fut.result()
                        except BrokenProcessPool:
                            broken = True
                            inflight[fut] = call
                            continue
                        except KeyboardInterrupt as e:  # a signal to that worker alone (`kill PID`, a memory
                            # watchdog): its run saved its frame and is failed; the sweep goes on
                            res = failed_result(call, f"the worker was stopped by {e or 'SIGINT'} (its run resumes "
                                                      "from its last checkpoint)")
                        except Exception as e:  # noqa: BLE001 - e.g. an unpicklable result
                            res = failed_result(call, f"{type(e).__name__}: {e}")
                        yield res
                if broken:
                    wait(inflight, timeout=60)
                    lost = []
                    for fut, call in list(inflight.items()):
                        del inflight[fut]
                        if fut.done() and fut.exception() is None:
                            yield fut.result()  # finished just before the pool broke
                        else:
                            lost.append(call)
                    if len(lost) == 1:
                        yield failed_result(lost[0], "worker process died (crash, out of memory or killed)")
                    else:
                        suspects.extend(lost)
            finally:
                if inflight:  # stopped early: do not leave runs going in the background
                    stop_workers(list(getattr(pool, "_processes", {}).values()))
                pool.shutdown(wait=True, cancel_futures=True)


WAKE_S = 1.0  # the driver waits for results in steps of this many seconds: Python runs a signal's handler in the
# main thread, which a signal the process took on another thread does not wake from a blocking wait
STOP_GRACE_S = 30.0  # how long a stopped worker may take to end its frame and save it (SLURM's default KillWait)


def stop_workers(procs: list, grace_s: float = STOP_GRACE_S) -> None:
    """SIGTERM each worker process (each ends the frame in progress and saves it), then SIGKILL those still running
    after `grace_s` seconds: one blocked in a long call, or one whose process got the signal on a thread that does
    not run Python, must not keep the sweep from stopping."""
    for p in procs:
        p.terminate()
    running = {p.sentinel: p for p in procs}
    deadline = time.monotonic() + grace_s
    while running and (left := deadline - time.monotonic()) > 0:
        for ended in wait_for_processes(list(running), timeout=left):
            running.pop(ended)
    for p in running.values():
        try:
            p.kill()
        except OSError:  # ended meanwhile
            pass


def _import_ray():
    try:
        import ray
    except ImportError:
        raise InrslamError("the ray executor needs Ray: pip install inrslam[ray]") from None
    return ray


def ray_cpus_per_run(nodes: list[dict], jobs: int, cpus_per_run: int | None = None) -> int:
    """CPU cores (= torch threads) per Ray task, from the cluster's nodes (`ray.nodes()`), not the driver's cores.

    Args:
        nodes: `ray.nodes()` dicts; the alive ones' `Resources["CPU"]` count.
        jobs: runs meant to share the cluster at once.
        cpus_per_run: asked count; None = total CPUs // jobs, at most the largest node's CPUs (at least 1).
    Raises ConfigError when `cpus_per_run` exceeds every node's CPUs (Ray would never schedule the task).
    """
    cpus = [int(n.get("Resources", {}).get("CPU", 0)) for n in nodes if n.get("Alive")]
    largest = max(cpus, default=0)
    if cpus_per_run:
        if int(cpus_per_run) > largest:
            raise ConfigError(f"cpus_per_run={cpus_per_run}: no Ray node has that many CPUs (the largest has "
                              f"{largest}); give at most {largest}")
        return int(cpus_per_run)
    return max(1, min(largest, sum(cpus) // max(1, int(jobs))))


@EXECUTORS.register("ray", help="one Ray task per run (ray.init(address) or a local instance)")
class RayExecutor:
    """One `@ray.remote(num_cpus, num_gpus)` task per run; uses an initialised Ray, else `ray.init(address)`.

    CPUs per run come from the cluster's nodes once Ray is up (`ray_cpus_per_run`).
    """

    def __init__(self, options: ExecutorOptions):
        _import_ray()  # fail early with the install hint
        self.options = options

    def run(self, calls: list[dict]) -> Iterator[dict]:
        ray = _import_ray()
        started = False
        if not ray.is_initialized():
            ray.init(address=self.options.address, include_dashboard=False, log_to_driver=False)
            started = True
        refs: dict = {}
        try:
            threads = ray_cpus_per_run(ray.nodes(), self.options.jobs, self.options.cpus_per_run)
            # max_calls=1: a fresh worker process per run, so per-run peak memory is measured alone
            task = ray.remote(num_cpus=threads, num_gpus=self.options.gpus_per_run, max_retries=0,
                              max_calls=1)(run_one)
            refs = {task.remote(threads=threads, **call): call for call in calls}
            while refs:
                done, _ = ray.wait(list(refs), num_returns=1, timeout=WAKE_S)  # in steps, as the local pool
                for ref in done:
                    call = refs.pop(ref)
                    try:
                        res = ray.get(ref)
                    except Exception as e:  # noqa: BLE001 - worker crash, cancellation
                        res = failed_result(call, f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}")
                    yield res
        finally:
            for ref in refs:
                ray.cancel(ref, force=True)
            if started:
                ray.shutdown()


def _import_submitit():
    try:
        import submitit
    except ImportError:
        raise InrslamError("the slurm executor needs submitit: pip install inrslam[slurm]") from None
    return submitit


@EXECUTORS.register("slurm", help="SLURM job array through submitit (cluster='local'/'debug' for testing)")
class SlurmExecutor:
    """submitit `AutoExecutor(folder=<out>/slurm)`: one job per run, submitted as an array.

    Every submitted job is recorded in `<out>/slurm/inflight.json`. A later `run` on a run whose recorded job is
    still pending or running waits on that job instead of submitting the run again (a killed driver leaves its
    array running; two jobs must not write one run directory).
    """

    def __init__(self, options: ExecutorOptions):
        if float(options.gpus_per_run) != int(options.gpus_per_run):
            raise ConfigError(f"gpus_per_run={options.gpus_per_run:g}: SLURM gives whole GPUs to a job; use an "
                              "integer (a fraction of a GPU is for the ray executor)")
        _import_submitit()  # fail early with the install hint
        self.options = options
        self.threads = options.threads(default=None if options.cpus_per_run else 4)

    def _submitit_executor(self, submitit):
        o = self.options
        ex = submitit.AutoExecutor(folder=Path(o.folder) / "slurm", cluster=o.cluster)
        params = {"timeout_min": int(o.time_min), "cpus_per_task": self.threads, "name": "inrslam-bench"}
        if o.gpus_per_run:
            params["gpus_per_node"] = int(o.gpus_per_run)
        if o.mem_gb:
            params["mem_gb"] = o.mem_gb
        if o.partition:
            params["slurm_partition"] = o.partition
        ex.update_parameters(**params)
        return ex

    def _plan(self, cluster: str, folder: Path, calls: list[dict]) -> ReattachPlan:
        """Read `inflight.json`, ask the scheduler about its jobs, decide which calls re-attach."""
        records = [r for r in read_inflight(folder / INFLIGHT_FILE) if r["cluster"] == cluster]
        if cluster not in RECORDED_CLUSTERS or not records:
            return ReattachPlan(submit=list(calls))
        ids = [r["job_id"] for r in records]
        raw, why = sacct_states(ids) if cluster == "slurm" else local_states(folder, ids)
        states = {j: settled(state) for j, state in raw.items()}
        plan = plan_reattach(calls, records, states)
        for rec in plan.unsure:  # submitted again: if the old job still runs it, the new one finds its folder locked
            reason = f"state {raw[rec['job_id']]}, which submitit does not wait on" if raw.get(rec["job_id"]) else why
            log.warning("cannot tell whether %s job %s of run %s is still running (%s); submitting the run again",
                        cluster, rec["job_id"], rec["name"], reason)
        for rec, _ in plan.attach:  # a warning: shown by `inrslam bench` (an earlier driver was killed)
            log.warning("re-attaching to %s job %s (%s) of run %s, still in flight from an earlier sweep: waiting on "
                        "it instead of submitting the run again", cluster, rec["job_id"], states[rec["job_id"]],
                        rec["name"])
        return plan

    def run(self, calls: list[dict]) -> Iterator[dict]:
        submitit = _import_submitit()
        ex = self._submitit_executor(submitit)
        folder = Path(ex.folder)
        plan = self._plan(ex.cluster, folder, calls)
        book = InflightBook(folder / INFLIGHT_FILE, ex.cluster, plan.keep)
        pending = []
        for rec, call in plan.attach:
            job = attach_job(submitit, ex.cluster, folder, rec["job_id"])
            pending.append((job, call))
            book.add(job.job_id, call)
        with hold_interrupts() as held:  # a Ctrl-C here waits until the submitted jobs are recorded
            if plan.submit:
                with signals_blocked():  # and sbatch, in the terminal's process group too, is not stopped by it
                    with ex.batch():
                        new = [(ex.submit(run_one, threads=self.threads, **call), call) for call in plan.submit]
                for job, call in new:
                    book.add(job.job_id, call)
                pending += new
            book.save()
        if held.signum is not None:
            _cancel(pending, book)
            raise interrupt(held.signum)
        poll = self.options.poll_s if self.options.poll_s is not None else (10.0 if ex.cluster == "slurm" else 0.2)
        yield from self._wait(pending, book, poll, folder)

    def _wait(self, pending: list, book: InflightBook, poll: float, folder: Path) -> Iterator[dict]:
        """Yield each job's result as it finishes (forgetting its record); cancel the rest when closed early."""
        try:
            while pending:
                for job, call in list(pending):
                    if not job.done():
                        continue
                    pending.remove((job, call))
                    try:
                        res = job.result()
                    except Exception as e:  # noqa: BLE001 - job failed, timed out or was cancelled
                        res = failed_result(call, f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
                                                  f" (logs in {folder})")
                    book.remove(job.job_id)
                    yield res
                end = time.monotonic() + poll if pending else 0.0
                while (left := end - time.monotonic()) > 0:  # in steps, as the local pool waits
                    time.sleep(min(left, WAKE_S))
        finally:
            _cancel(pending, book)


def _cancel(pending: list, book: InflightBook) -> None:
    """Cancel the jobs not finished (best effort) and forget the records of those cancelled."""
    cancelled = []
    for job, _ in pending:
        try:
            job.cancel(check=False)
        except Exception:  # noqa: BLE001 - best effort
            continue
        cancelled.append(job.job_id)
    book.remove(*cancelled)
