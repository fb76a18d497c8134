"""`build_report`: leaderboards (Markdown, CSV, LaTeX), plots and an HTML page from a folder of run directories.

    report/
      leaderboard.{md,csv,tex}            all scenes and seeds: mean ± std per G x F, best per column marked
      leaderboard_<scene>.{md,csv,tex}    the same per scene (mean ± std over seeds)
      runs.csv                            one line per run directory: status and the raw metrics.json values
      plots/*.png, *.svg                  memory-vs-ATE trade-off, per-metric bars, ATE over frames
      index.html                          tables + PNG plots, and per run its pictures (trajectory.png, mesh.png,
                                          renders/) with a link to its folder: relative links, nothing external

Nothing is re-run: only files the runs wrote are read.
"""

from __future__ import annotations

import csv
import datetime as _dt
import html
import io
import os
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

from inrslam.bench.leaderboard import (
    COLUMNS,
    RunRecord,
    aggregate,
    collect_runs,
    encoding_label,
    number,
    render_label,
    to_csv,
    to_html,
    to_latex,
    to_markdown,
)
from inrslam.bench.plots import plot_ate_over_frames, plot_bars, plot_tradeoff
from inrslam.bench.spec import sanitize
from inrslam.bench.sweep import STATUS_FILE
from inrslam.errors import DataError
from inrslam.io.atomic import write_text
from inrslam.io.rundir import RunDir, read_json

RENDERS_SHOWN = 2  # held-out pictures per run on the report page (the first ones)
RUN_FIELDS = ("name", "scene", "encoding", "render", "preset", "seed", "status", "error", "cpu", "threads")
METRIC_FIELDS = ("ate_rmse_m", "ate_mean_m", "rpe_trans_m", "rpe_rot_deg", "psnr_db", "ssim", "depth_l1_m",
                 "psnr_process_db", "depth_l1_process_m", "acc_m", "comp_m", "comp_ratio", "track_ms_per_frame",
                 "map_ms_per_call", "model_size_mb", "peak_memory_mb", "frames", "wall_time_s")


def runs_csv(records: list[RunRecord]) -> str:
    """One line per run directory with its status and raw metrics.json values (empty when missing)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(RUN_FIELDS + METRIC_FIELDS)
    for r in records:
        w.writerow([r.name, r.scene, r.encoding, r.render, r.preset, "" if r.seed is None else r.seed, r.status,
                    r.error or "", r.cpu, "" if r.threads is None else r.threads]
                   + ["" if r.metrics.get(k) is None else r.metrics[k] for k in METRIC_FIELDS])
    return buf.getvalue()


@dataclass
class RunPictures:
    """A run's pictures for the report: each a path, or the reason it has none (`renders`: the first
    `RENDERS_SHOWN` held-out pictures, or the reason)."""

    trajectory: Path | str
    mesh: Path | str
    renders: list[Path] | str


def run_pictures(record: RunRecord) -> RunPictures:
    """What `record`'s folder holds of trajectory.png, mesh.png and renders/, and for each picture it lacks, why
    (read from its status, config.yaml and files)."""
    rd = RunDir(record.run_dir)
    cfg = record.config if isinstance(record.config, dict) else {}

    def section(name: str) -> dict:
        got = cfg.get(name)
        return got if isinstance(got, dict) else {}

    common = None
    if not record.complete:
        common = f"run {record.status}"
    elif section("output").get("renders") is False:
        common = "output.renders=false"
    older = "none (made by an older inrslam, or drawing {} failed: see log.jsonl)"

    def why(extra: list[tuple[bool, str]], name: str) -> str:
        return common or next((text for cond, text in extra if cond), older.format(name))

    traj: Path | str = rd.trajectory_plot if rd.trajectory_plot.is_file() else why(
        [(not rd.trajectory_gt.is_file(), "no ground truth (trajectory_gt.txt)")], "it")
    mesh: Path | str = rd.mesh_thumbnail if rd.mesh_thumbnail.is_file() else why(
        [(section("mesh").get("enabled") is False, "mesh.enabled=false"),
         (not rd.mesh.is_file(), "no mesh.ply (the map has no surface)")], "it")
    frames = sorted(rd.renders.glob("frame_*.png"))[:RENDERS_SHOWN] if rd.renders.is_dir() else []
    ev = section("eval")
    renders: list[Path] | str = frames or why(
        [(ev.get("enabled") is False, "evaluation off (eval.enabled=false)"),
         (ev.get("heldout_every") == 0, "no held-out frames (eval.heldout_every=0)")], "renders/")
    return RunPictures(trajectory=traj, mesh=mesh, renders=renders)


def status_summary(records: list[RunRecord]) -> str:
    """'5 runs: 3 complete, 1 corrupt: metrics.json, 1 running' (statuses in order of first appearance)."""
    counts: dict[str, int] = {}
    for r in records:
        counts[r.status] = counts.get(r.status, 0) + 1
    return f"{len(records)} runs" + (": " + ", ".join(f"{n} {s}" for s, n in counts.items()) if counts else "")


def machines_note(records: list[RunRecord]) -> str:
    """'' when the complete runs ran on one CPU model with one thread count (or none recorded one); else a sentence
    saying that Track / Map times mix machines or thread counts, with the runs per machine."""
    done = [r for r in records if r.complete]
    cpus: dict[str, int] = {}
    for r in done:
        key = f"{r.cpu or 'not recorded'}, {r.threads if r.threads is not None else '?'} thread(s)"
        cpus[key] = cpus.get(key, 0) + 1
    if len(cpus) <= 1:
        return ""
    listed = "; ".join(f"{k}: {n} run(s)" for k, n in sorted(cpus.items(), key=lambda kv: (-kv[1], kv[0])))
    return (f"Times mix machines or thread counts ({listed}): compare Track / Map only between runs of one machine "
            "(runs.csv names each run's).")


def _write_tables(out: Path, stem: str, rows, title: str, scene: str | None = None) -> None:
    write_text(out / f"{stem}.md", to_markdown(rows, COLUMNS, title=title))
    write_text(out / f"{stem}.csv", to_csv(rows, COLUMNS, scene=scene))
    write_text(out / f"{stem}.tex", to_latex(rows, COLUMNS, caption=title))


def build_report(runs_dir: str | os.PathLike, out: str | os.PathLike | None = None) -> Path:
    """Aggregate every run directory under `runs_dir` into `out` (default `runs_dir/report`). Returns `out`.

    Raises DataError (and creates nothing) when `runs_dir` is not an existing folder.
    """
    runs_dir = Path(runs_dir)
    if not runs_dir.is_dir():
        what = "is not a folder" if runs_dir.exists() else "does not exist"
        raise DataError(f"{runs_dir}: runs folder {what} (give the folder holding the run directories)")
    out = Path(out) if out is not None else runs_dir / "report"
    out.mkdir(parents=True, exist_ok=True)
    records = collect_runs(runs_dir, exclude=out)
    complete = [r for r in records if r.complete]
    scenes = sorted({r.scene for r in complete})
    seeds = sorted({r.seed for r in complete if r.seed is not None})
    rows = aggregate(records)  # failed and unfinished runs count in their rows' totals
    what = f"{len(complete)} runs, {len(scenes)} scene(s), {len(seeds)} seed(s)"
    _write_tables(out, "leaderboard", rows, f"Leaderboard: mean ± std over scenes and seeds ({what})")
    scene_rows = {}
    for scene in scenes:
        scene_rows[scene] = aggregate([r for r in records if r.scene == scene])
        _write_tables(out, f"leaderboard_{sanitize(scene)}", scene_rows[scene],
                      f"Leaderboard, scene {scene}: mean ± std over seeds", scene=scene)
    write_text(out / "runs.csv", runs_csv(records))
    plots_dir = out / "plots"
    plots = {"tradeoff": plot_tradeoff(rows, plots_dir), "bars": plot_bars(rows, plots_dir),
             "frames": plot_ate_over_frames(complete, plots_dir)}
    write_text(out / "index.html", _html(runs_dir, out, records, rows, scene_rows, plots, what))
    return out


_CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1400px;color:#222}
table{border-collapse:collapse;margin:1em 0;font-size:14px}th,td{border:1px solid #ccc;padding:3px 8px}
th{background:#f3f3f3}td.num{text-align:right;font-variant-numeric:tabular-nums}
img{max-width:100%;border:1px solid #eee;margin:0.5em 0}.fail{color:#b00}code{background:#f6f6f6;padding:0 3px}
td.missing{color:#777}ol.notes{font-size:13px;color:#555;margin-top:-0.5em}span.where{color:#888}
table.runs td{vertical-align:top}img.thumb{height:130px;width:auto;margin:0}img.panel{height:75px;width:auto;margin:0}
td.none{color:#777;font-size:13px;max-width:14em}"""


def _img(out: Path, paths: list[Path]) -> str:
    return "\n".join(f"<img src='{html.escape(p.relative_to(out).as_posix())}' alt='{html.escape(p.stem)}'>"
                     for p in paths if p.suffix == ".png")


def _href(out: Path, path: Path) -> str:
    """`path` relative to the report folder `out`, URL-quoted and HTML-escaped (for href / src)."""
    return html.escape(urllib.parse.quote(Path(os.path.relpath(path, out)).as_posix(), safe="/"), quote=True)


def _picture(out: Path, got, css: str) -> str:
    """Table cell: the pictures (each a link to itself) or '– reason'."""
    if isinstance(got, str):
        return f"<td class='none'>– {html.escape(got)}</td>"
    paths = got if isinstance(got, list) else [got]
    return "<td>" + "<br>".join(f"<a href='{_href(out, p)}'><img class='{css}' src='{_href(out, p)}' "
                                f"alt='{html.escape(p.name)}' loading='lazy'></a>" for p in paths) + "</td>"


def _runs_table(out: Path, records: list[RunRecord]) -> str:
    """One row per run: name linked to its folder, F / G / scene, ATE, then trajectory.png, mesh.png and the first
    held-out pictures."""
    rows = ["<table class='runs'><tr><th>run</th><th>ATE [cm]</th><th>trajectory.png</th><th>mesh.png</th>"
            "<th>renders/ (observed | rendered | depth | depth error)</th></tr>"]
    for r in records:
        pics = run_pictures(r)
        ate = number(r.metrics.get("ate_rmse_m"))
        ate_text = "–" if ate is None else f"{ate * 100:.2f}"
        what = f"{encoding_label(r.encoding)} / {render_label(r.render)}, {r.scene}" + (
            f", seed {r.seed}" if r.seed is not None else "") + (f", {r.preset}" if r.preset else "")
        status = "" if r.complete else f"<br><span class='fail'>{html.escape(r.status)}</span>"
        rows.append(f"<tr><td><a href='{_href(out, r.run_dir)}/'>{html.escape(r.name)}</a><br>"
                    f"<small>{html.escape(what)}</small>{status}</td><td class='num'>{ate_text}</td>"
                    + _picture(out, pics.trajectory, "thumb") + _picture(out, pics.mesh, "thumb")
                    + _picture(out, pics.renders, "panel") + "</tr>")
    rows.append("</table>")
    return "\n".join(rows)


def _html(runs_dir: Path, out: Path, records, rows, scene_rows: dict, plots: dict, what: str) -> str:
    e = html.escape
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>inrslam leaderboard</title>"
             f"<style>{_CSS}</style></head><body>",
             f"<h1>inrslam leaderboard</h1><p>Runs from <code>{e(str(runs_dir))}</code>: {e(what)}. Generated "
             f"{e(_dt.datetime.now().isoformat(timespec='seconds'))} by <code>inrslam report {e(str(runs_dir))}</code>."
             " PSNR and Depth L1 are measured on the frames processed during the run (as the paper's leaderboards);"
             " Track = ms per frame, Map = ms per mapping call; bold = best per column; – = not measured (the numbered"
             " notes under each table say why). <a href='#runs'>Each run's pictures</a> are at the end.</p>"]
    status = read_json(runs_dir / STATUS_FILE)
    if isinstance(status, dict) and status:
        counts = status.get("counts")
        counts = ", ".join(f"{k} {v}" for k, v in counts.items()) if isinstance(counts, dict) else ""
        parts.append(f"<p>Sweep <code>{e(str(status.get('spec', '')))}</code>: state {e(str(status.get('state')))}"
                     f" ({e(counts)}).</p>")
    mixed = machines_note(records)
    if mixed:
        parts.append(f"<p class='fail'>{e(mixed)}</p>")
    parts += ["<h2>All scenes</h2>", to_html(rows, COLUMNS),
              "<p>Tables: <a href='leaderboard.md'>Markdown</a>, <a href='leaderboard.csv'>CSV</a>, "
              "<a href='leaderboard.tex'>LaTeX</a>, <a href='runs.csv'>per-run CSV</a>.</p>"]
    if plots["tradeoff"]:
        parts += ["<h2>Memory vs accuracy</h2>", _img(out, plots["tradeoff"])]
    if plots["bars"]:
        parts += ["<h2>Metrics per F x G</h2>", _img(out, plots["bars"])]
    for scene, srows in scene_rows.items():
        parts += [f"<h2>Scene {e(scene)}</h2>", to_html(srows, COLUMNS)]
        parts += [_img(out, [p for p in plots["frames"] if p.stem == f"ate_frames_{sanitize(scene)}"])]
    if records:
        parts += ["<h2 id='runs'>Runs</h2>", "<p>Each run's pictures (click for full size) and its folder; – says why "
                  "a picture is missing.</p>", _runs_table(out, records)]
    bad = [r for r in records if not r.complete]
    if bad:
        parts.append("<h2>Runs not in the tables</h2><table><tr><th>run</th><th>status</th><th>error</th></tr>")
        for r in bad:
            parts.append(f"<tr><td>{e(r.name)}</td><td class='fail'>{e(r.status)}</td>"
                         f"<td>{e(r.error or '')}</td></tr>")
        parts.append("</table>")
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"
