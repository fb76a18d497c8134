"""The SLURM executor's record of its jobs, so that a sweep run again after its driver died waits on the jobs still
in flight instead of submitting their runs a second time (docs/benchmark.md, "Executors").

`<out>/slurm/inflight.json` lists every submitted job not yet seen finished (`InflightBook`); `plan_reattach`
decides from the jobs' states (`sacct_states`, `squeue_states` on SLURM; `local_states` for submitit's local
cluster) which runs re-attach and which are submitted.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from inrslam.io.atomic import write_json
from inrslam.status import logger

log = logger(__name__)


INFLIGHT_FILE = "inflight.json"  # in <folder>/slurm: the jobs submitted and not yet seen finished
RECORDED_CLUSTERS = ("slurm", "local")  # "debug" runs its jobs inside the driver: nothing outlives it
LIVE_STATES = frozenset({"READY", "PENDING", "RUNNING", "REQUEUED", "COMPLETING", "PREEMPTED"})  # what submitit
# waits on (`is_done`), without UNKNOWN: an attached job in another state would read as failed at once
ENDED_STATES = frozenset({"COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "BOOT_FAIL",
                          "DEADLINE", "REVOKED", "FINISHED", "UNKNOWN"})  # SLURM's final states; FINISHED: local jobs


def _state_word(state: str) -> str:
    """The state itself of a scheduler's state text ('CANCELLED by 0' -> 'CANCELLED'; empty -> 'UNKNOWN')."""
    return (state.split() or ["UNKNOWN"])[0].upper()


def settled(state: str | None) -> str | None:
    """`state` where it decides (live as submitit waits on it, or ended); None for a job alive in a state submitit
    would not wait on (CONFIGURING, SUSPENDED, STOPPED, ...): its run cannot be re-attached, nor called finished."""
    if state is None:
        return None
    return state if _state_word(state) in LIVE_STATES | ENDED_STATES else None


def run_key(out_dir: str, name: str) -> str:
    """The run's absolute directory `out_dir/name`: what ties a recorded job to a call."""
    return os.path.abspath(os.path.join(out_dir, name))


def job_record(job_id: str, cluster: str, call: dict) -> dict:
    """The `inflight.json` entry of a submitted job: its id and cluster, the run's name, out_dir and run_dir."""
    out, name = os.path.abspath(call["out_dir"]), call["run"]["name"]
    return {"job_id": str(job_id), "cluster": cluster, "name": name, "out_dir": out, "run_dir": run_key(out, name)}


def is_live(state: str) -> bool:
    """Whether a scheduler state ('RUNNING', 'CANCELLED by 0', ...) means the job may still write its run."""
    return _state_word(state) in LIVE_STATES


@dataclass
class ReattachPlan:
    """What `plan_reattach` decided for the calls of one `SlurmExecutor.run`."""

    attach: list[tuple[dict, dict]] = field(default_factory=list)  # (record, call): the job is live, wait on it
    submit: list[dict] = field(default_factory=list)  # calls to submit as new jobs
    unsure: list[dict] = field(default_factory=list)  # records of runs submitted again, job state unknowable
    keep: list[dict] = field(default_factory=list)  # live or unknowable jobs of runs not in the calls


def plan_reattach(calls: list[dict], records: list[dict], states: Mapping[str, str | None]) -> ReattachPlan:
    """Wait on a call's recorded job when it is still live, else submit the call again.

    Args:
        calls: `run_one` keyword dicts (`run`, `out_dir`, ...).
        records: `inflight.json` entries (`job_record`), oldest first; a later one for the same run wins.
        states: job id -> scheduler state, None when it could not be determined. Finished and unknown
            ('UNKNOWN', missing) jobs are forgotten; undetermined ones are submitted again and listed in `unsure`.
    """
    plan, by_run = ReattachPlan(), dict[str, dict]()
    for rec in records:
        state = states.get(rec["job_id"], "UNKNOWN")
        if state is None or is_live(state):
            by_run[rec["run_dir"]] = rec
    for call in calls:
        live = by_run.pop(run_key(call["out_dir"], call["run"]["name"]), None)
        if live is not None and states.get(live["job_id"]) is not None:
            plan.attach.append((live, call))
            continue
        plan.submit.append(call)
        if live is not None:
            plan.unsure.append(live)
    plan.keep = list(by_run.values())
    return plan


def read_inflight(path: Path) -> list[dict]:
    """The job records in `path` (none when it is missing; a damaged file is reported and ignored)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        jobs = data["jobs"]
        return [r for r in jobs if {"job_id", "cluster", "name", "run_dir"} <= set(r)]
    except FileNotFoundError:
        return []
    except (OSError, ValueError, KeyError, TypeError) as e:
        log.warning("%s is unreadable (%s): no job is re-attached", path, e)
        return []


def sacct_states(job_ids: list[str]) -> tuple[dict[str, str | None], str | None]:
    """SLURM state of each job id by one `sacct` call, parsed by submitit ('UNKNOWN' for a job sacct does not
    list); every state None, with the reason, when sacct cannot be run (missing, accounting off, timeout)."""
    from submitit.slurm.slurm import SlurmInfoWatcher

    cmd = ["sacct", "-o", "JobID,State", "--parsable2"]
    for main in _array_ids(job_ids):
        cmd += ["-j", main]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=120).stdout
    except (OSError, subprocess.SubprocessError) as e:
        states: dict[str, str | None] = dict.fromkeys(job_ids)
        why: str | None = f"sacct failed: {str(e).splitlines()[0] if str(e) else type(e).__name__}"
    else:
        info = SlurmInfoWatcher().read_info(out)
        states, why = {j: info.get(j, {}).get("State") or "UNKNOWN" for j in job_ids}, None
    unseen = [j for j in job_ids if states[j] in (None, "UNKNOWN")]  # not yet in the accounting, or no sacct
    queued = squeue_states(unseen) if unseen else {}
    if queued is not None:
        states.update({j: queued.get(j, "UNKNOWN") for j in unseen})  # squeue lists every live job
        why = None
    return states, why


def _array_ids(job_ids: list[str]) -> list[str]:
    """The jobs (arrays) of job ids ('123_4' -> '123'), sorted and each once: what sacct and squeue are asked for."""
    return sorted({j.split("_")[0] for j in job_ids})


def squeue_states(job_ids: list[str]) -> dict[str, str] | None:
    """States of those of `job_ids` still in SLURM's queue, by one `squeue` call (a job it does not list has
    ended); None when squeue cannot be run. Array ranges ('123_[5-7]') are expanded as sacct's are."""
    from submitit.slurm.slurm import SlurmInfoWatcher

    cmd = ["squeue", "-h", "-o", "%i|%T", "-j", ",".join(_array_ids(job_ids))]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.SubprocessError):
        return None
    if done.returncode != 0:  # one job id that left the queue's memory is an error; several are not
        return {} if "invalid job id" in done.stderr.lower() else None
    info = SlurmInfoWatcher().read_info("JobID|State\n" + done.stdout)
    return {j: info[j]["State"] for j in job_ids if j in info and info[j].get("State")}


def local_state(folder: Path, job_id: str) -> str:
    """State of a submitit local job (its id is its controller's pid), from any process: 'FINISHED' (result
    written), 'RUNNING' (`/proc/<id>/cmdline` is the controller for `folder`) or 'UNKNOWN' (gone)."""
    from submitit.core.utils import JobPaths

    if JobPaths(folder, job_id, 0).result_pickle.exists():
        return "FINISHED"
    try:
        args = Path(f"/proc/{int(job_id)}/cmdline").read_bytes().split(b"\0")  # empty for a zombie
        at = args.index(b"submitit.local._local")
        return "RUNNING" if os.path.samefile(os.fsdecode(args[at + 1]), folder) else "UNKNOWN"
    except (OSError, ValueError, IndexError):
        return "UNKNOWN"


def local_states(folder: Path, job_ids: list[str]) -> tuple[dict[str, str | None], str | None]:
    """`local_state` of each job; every state None where there is no /proc to look processes up."""
    if not Path("/proc/self/cmdline").is_file():
        return dict.fromkeys(job_ids), "no /proc to look up the local job processes"
    return {j: local_state(folder, j) for j in job_ids}, None


class OrphanLocalJob:
    """A submitit local job started by an earlier driver (not our child): polled through /proc and its result."""

    def __init__(self, folder: Path, job_id: str):
        import submitit

        self.folder, self.job_id = Path(folder), job_id
        self._job: Any = submitit.LocalJob(folder, job_id)

    def done(self) -> bool:
        return local_state(self.folder, self.job_id) != "RUNNING"

    def result(self) -> Any:
        return self._job.result()

    def cancel(self, check: bool = False) -> None:
        if local_state(self.folder, self.job_id) == "RUNNING":
            os.kill(int(self.job_id), signal.SIGINT)  # what submitit's LocalJob.cancel sends its controller


def attach_job(submitit, cluster: str, folder: Path, job_id: str):
    """A job object (`done`, `result`, `cancel`) for a job an earlier driver submitted."""
    return submitit.SlurmJob(folder, job_id) if cluster == "slurm" else OrphanLocalJob(folder, job_id)


class InflightBook:
    """`<folder>/slurm/inflight.json`: the submitted jobs of this sweep folder not yet seen finished, rewritten
    atomically on every change, so a driver killed at any point leaves the old or the new list."""

    def __init__(self, path: Path, cluster: str, keep: list[dict] | None = None):
        self.path, self.cluster = path, cluster
        self.keep = list(keep or [])  # records of other runs' live jobs, carried over
        self.jobs: dict[str, dict] = {}

    def add(self, job_id: str, call: dict) -> None:
        self.jobs[str(job_id)] = job_record(job_id, self.cluster, call)

    def remove(self, *job_ids: str) -> None:
        """Forget these jobs (saved once, if any was recorded)."""
        if [self.jobs.pop(str(j)) for j in job_ids if str(j) in self.jobs]:
            self.save()

    def save(self) -> None:
        if self.cluster in RECORDED_CLUSTERS:
            write_json(self.path, {"jobs": self.keep + list(self.jobs.values())})
