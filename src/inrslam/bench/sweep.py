"""`run_sweep`: run every combination of a sweep spec as its own run directory, then build the leaderboard.

    out/
      sweep_spec.yaml        the spec as given (reproduce with `inrslam bench out/sweep_spec.yaml --out out`)
      sweep_status.json      per-run status (pending / complete / skipped / failed), rewritten atomically
      <scene>__<F>__<G>__<preset>__s<seed>/   one run directory each (as `inrslam run`), + bench.json, error.txt
      report/                leaderboard.{md,csv,tex}, plots, index.html (`build_report`)

Re-running the same command resumes: complete runs are skipped, checkpointed partial runs continue from their
checkpoint, the others start over.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import yaml

from inrslam.bench.executors import EXECUTORS, ExecutorOptions, make_executor
from inrslam.bench.spec import SPEC_KEYS, RunSpec, SweepSpec, expand, load_spec, validate_runs
from inrslam.bench.sweep_progress import SweepProgress
from inrslam.bench.worker import fn_path
from inrslam.errors import ConfigError
from inrslam.io.atomic import write_json, write_text
from inrslam.io.lock import LockHeld, acquire
from inrslam.io.rundir import RunDir
from inrslam.io.yamlfile import load_yaml

STATUS_FILE = "sweep_status.json"


@dataclass
class SweepResult:
    """What a sweep did: one result dict per run name (status, run_dir, error, seconds), the report folder."""

    out: Path
    runs: list[RunSpec]
    results: dict[str, dict] = field(default_factory=dict)
    report: Path | None = None
    interrupted: bool = False
    dry_run: bool = False

    def count(self, status: str) -> int:
        return sum(1 for r in self.results.values() if r.get("status") == status)

    @property
    def failed(self) -> list[str]:
        return [n for n, r in self.results.items() if r.get("status") == "failed"]

    def summary(self) -> str:
        """One line: how many runs completed, were skipped, failed, and where the report is."""
        n = len(self.runs)
        if self.dry_run:
            return (f"bench (dry run): {n} runs in {self.out}: {self.count('pending')} to run, "
                    f"{self.count('resume')} to resume, {self.count('skipped')} already complete")
        text = (f"bench: {n} runs in {self.out}: {self.count('complete')} completed, "
                f"{self.count('skipped')} already complete, {self.count('failed')} failed")
        if self.count("pending"):
            text += f", {self.count('pending')} not run (interrupted)"
        if self.failed:
            text += f" (see {self.out}/<run>/error.txt)"
        if self.report:
            text += f"; report {self.report / 'index.html'}"
        return text


def _now() -> str:
    return _dt.datetime.now().isoformat(timespec="seconds")


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def config_differences(run_dir: Path, cfg) -> list[str]:
    """Keys whose value in `run_dir/config.yaml` differs from the resolved `cfg` (keys present in both, the file's
    old key names read as the new ones, `inrslam.config.aliases`)."""
    from inrslam.config.aliases import apply_aliases
    from inrslam.config.loader import config_to_dict

    path = RunDir(run_dir).config
    try:
        data = load_yaml(path) or {}
    except ConfigError:
        return []
    try:
        old = _flatten(apply_aliases(data, str(path)) if isinstance(data, dict) else {})
    except ConfigError as e:
        return [str(e)]
    new = _flatten(config_to_dict(cfg))
    # `threads` is recorded as used (the sweep sets it per job), not as the spec asked
    return [f"{k}: {old[k]!r} -> {new[k]!r}" for k in sorted(set(old) & set(new) - {"threads"}) if old[k] != new[k]]


def _check_existing(runs: list[RunSpec], cfgs: dict, out: Path) -> None:
    """Refuse to skip or resume run directories that were made with a different config."""
    for run in runs:
        d = out / run.name
        if run.name in cfgs and (RunDir(d).is_complete() or RunDir(d).has_checkpoint()):
            diff = config_differences(d, cfgs[run.name])
            if diff:
                raise ConfigError(f"{d} was made with a different config ({'; '.join(diff[:3])}); "
                                  "use a new --out folder or delete that run directory")


def _write_status(out: Path, res: SweepResult, meta: dict, state: str) -> None:
    counts = {s: res.count(s) for s in ("pending", "complete", "skipped", "failed")}
    write_json(out / STATUS_FILE, {**meta, "state": state, "updated": _now(), "total": len(res.runs),
                                   "counts": counts, "runs": res.results})


def _save_spec(spec_arg, sp, out: Path) -> None:
    """`sweep_spec.yaml`, which `inrslam bench OUT/sweep_spec.yaml` runs again: the spec file as written, the dict
    as given, or a `SweepSpec` object as its validated fields (scene paths resolved; one made from a file and then
    changed in code keeps that file as its `source`, so the file is not what runs)."""
    if isinstance(spec_arg, dict):
        data = spec_arg
    elif not isinstance(spec_arg, SweepSpec) and Path(sp.source).is_file():
        write_text(out / "sweep_spec.yaml", Path(sp.source).read_text())
        return
    else:
        data = {k: v for k, v in dataclasses.asdict(sp).items() if k in SPEC_KEYS and v not in ("", None)}
    text = yaml.safe_dump(data, sort_keys=False)
    write_text(out / "sweep_spec.yaml", text)


def run_sweep(spec, out, jobs: int = 1, executor: str = "local", address: str | None = None,
              partition: str | None = None, time_min: int = 60, dry_run: bool = False, *,
              run_fn: str | Callable | None = None, validate: bool = True, report: bool = True,
              on_result: Callable[[dict], bool | None] | None = None, quiet: bool = False,
              **executor_options) -> SweepResult:
    """Run (or resume) a sweep; each combination becomes `out/<run name>/`. Returns a `SweepResult`.

    Args:
        spec: sweep spec YAML path, shipped spec name (e.g. 'tiny') or dict (see `inrslam.bench.spec`).
        out: folder holding one run directory per combination.
        jobs: parallel local processes (local executor); ray/slurm derive cores per run from it.
        executor: 'local', 'ray' or 'slurm' (registry `EXECUTORS`).
        address / partition / time_min: Ray address; SLURM partition and time limit per run (minutes).
        dry_run: only list the runs and what would happen to each (nothing is written).
        run_fn: module-level function (or 'module:function') doing one run, default the SLAM run (tests inject
            `inrslam.bench.testing:fake_run`).
        validate: resolve every run's config up-front with `load_config` (a typo fails before anything runs).
        report: build the leaderboard at the end (`build_report(out)`).
        on_result: called with each finished run's result; returning False stops the sweep (remaining runs stay
            pending; re-running resumes).
        quiet: print nothing (otherwise: a first line, one line per finished run with its ATE, time, the counts and
            an ETA (`inrslam.bench.sweep_progress`), and a one-line summary).
        executor_options: more `ExecutorOptions` (cpus_per_run, gpus_per_run, mem_gb, cluster, poll_s).
    """
    from inrslam.bench.report import build_report

    sp = load_spec(spec)
    runs = expand(sp)
    out = Path(out)
    cfgs = validate_runs(runs, sp.source, check_paths=not dry_run, spec=sp) if validate else {}
    _check_existing(runs, cfgs, out)
    EXECUTORS.get(executor)  # an unknown executor fails here, --dry-run included
    res = SweepResult(out=out, runs=runs, dry_run=dry_run)
    todo = []
    for run in runs:
        d = out / run.name
        if RunDir(d).is_complete():
            res.results[run.name] = {"name": run.name, "status": "skipped", "run_dir": str(d), "error": None}
        else:
            res.results[run.name] = {"name": run.name, "status": "resume" if dry_run and RunDir(d).has_checkpoint()
                                     else "pending", "run_dir": str(d), "error": None}
            todo.append(run)
    if dry_run:
        if not quiet:
            for run in runs:
                print(f"  {res.results[run.name]['status']:8s} {run.name}")
            print(res.summary())
        return res

    options = ExecutorOptions(jobs=jobs, folder=str(out), address=address, partition=partition, time_min=time_min,
                              **executor_options)
    ex = make_executor(executor, options)
    out.mkdir(parents=True, exist_ok=True)
    lock = _lock_folder(out)  # one sweep at a time per folder: a second would run the same runs into it
    try:
        _save_spec(spec, sp, out)
        meta = {"spec": sp.source, "executor": executor, "jobs": jobs, "started": _now()}
        _write_status(out, res, meta, "running")
        calls = [{"run": r.to_dict(), "out_dir": str(out), "run_fn": fn_path(run_fn)} for r in todo]
        state = "finished"
        shown = SweepProgress(len(todo), len(runs) - len(todo), jobs, executor)
        if not quiet:
            print(shown.start_line(), flush=True)
        stream = ex.run(calls) if calls else iter(())
        try:
            for result in stream:
                _record(out, result)
                res.results[result["name"]] = result
                _write_status(out, res, meta, "running")
                if not quiet:
                    print(shown.finished(result), flush=True)
                if on_result is not None and on_result(result) is False:
                    res.interrupted, state = True, "interrupted"
                    break
        except KeyboardInterrupt:
            res.interrupted = True
            _write_status(out, res, meta, "interrupted")
            raise
        except Exception as e:
            _write_status(out, res, {**meta, "error": f"{type(e).__name__}: {e}"}, "error")
            raise
        finally:
            close = getattr(stream, "close", None)
            if close:
                close()
        _write_status(out, res, meta, state)
        if report:
            res.report = build_report(out)
        if not quiet:
            print(res.summary())
        return res
    finally:
        lock.close()


LOCK_FILE = ".sweep.lock"


def _lock_folder(out: Path):
    """An exclusive lock on `out/.sweep.lock` (`inrslam.io.lock`; released when the returned file is closed, or the
    process ends); ConfigError when another sweep holds it."""
    try:
        return acquire(out / LOCK_FILE)
    except LockHeld as e:
        raise ConfigError(f"{out}: another inrslam bench is running into this folder ({e.holder}); wait for it to "
                          "end (re-running then resumes) or give another --out") from None


def _record(out: Path, result: dict) -> None:
    """Make sure a failed run has an error.txt, even when its worker died before writing one (not in a folder
    another process holds: `busy`)."""
    if result.get("status") != "failed" or result.get("busy"):
        return
    err = RunDir(result.get("run_dir") or out / result["name"]).error
    if not err.exists():
        write_text(err, (result.get("error") or "unknown error") + "\n")
