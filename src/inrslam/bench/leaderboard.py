"""Leaderboards from run directories: collect, aggregate (mean ± std per G x F), mark the best, format.

Reads only what runs wrote (metrics.json, run_info.json, config.yaml, bench.json); never re-runs anything.
Columns follow the paper's leaderboards (docs/spec.md §11.1) plus model size: Acc, Comp [cm], Comp [%], ATE [cm],
PSNR [dB] and Depth L1 [cm] "from processes" (the training-time renders, `psnr_process_db`,
`depth_l1_process_m`), Track [ms] per frame, Map [ms] per call, Model [MB].
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from inrslam.bench.spec import scene_short_name
from inrslam.errors import ConfigError
from inrslam.io.rundir import RunDir
from inrslam.io.yamlfile import load_yaml

MISSING = "–"
SKIP_DIRS = {"report", "slurm", "checkpoints", "meshes", "tensorboard"}


@dataclass(frozen=True)
class Column:
    """One leaderboard column: `metric` (metrics.json key) times `scale`, displayed with `decimals`."""

    key: str
    title: str
    metric: str
    scale: float = 1.0
    higher_better: bool = False
    decimals: int = 2


COLUMNS: tuple[Column, ...] = (
    Column("acc_cm", "Acc [cm]", "acc_m", 100.0),
    Column("comp_cm", "Comp [cm]", "comp_m", 100.0),
    Column("comp_pct", "Comp [%]", "comp_ratio", 100.0, higher_better=True),
    Column("ate_cm", "ATE [cm]", "ate_rmse_m", 100.0),
    Column("drift_cm", "Drift [cm/100 fr]", "drift_m_per_100", 100.0),
    Column("psnr_db", "PSNR [dB]", "psnr_process_db", 1.0, higher_better=True),
    Column("depth_l1_cm", "Depth L1 [cm]", "depth_l1_process_m", 100.0),
    Column("track_ms", "Track [ms]", "track_ms_per_frame", 1.0, decimals=0),
    Column("map_ms", "Map [ms]", "map_ms_per_call", 1.0, decimals=0),
    Column("map_ms_frame", "Map [ms/frame]", "map_ms_per_frame", 1.0, decimals=0),
    Column("model_mb", "Model [MB]", "model_size_mb", 1.0),
)
COLUMN_BY_KEY = {c.key: c for c in COLUMNS}

# Paper names (docs/spec.md §0.1); unknown registry names are shown as they are.
RENDER_LABELS = {"direct": "SDF(direct)", "density": "SDF(density)", "neus": "SDF(surface)", "volsdf": "VolSDF",
                 "nerf": "NeRF"}
ENCODING_LABELS = {"mlp": "MLP", "dense": "Dense", "hash": "Sparse (hash)", "triplane": "Tri.", "tensorf": "Fact.",
                   "dense+tri": "Hybrid (Dense+Tri)", "hash+tri": "Hybrid (Hash+Tri)"}


def render_label(name: str) -> str:
    return RENDER_LABELS.get(name, name)


def encoding_label(name: str) -> str:
    return ENCODING_LABELS.get(name, name)


def _order(name: str, labels: dict) -> tuple:
    keys = list(labels)
    return (keys.index(name), "") if name in keys else (len(keys), name)


# ----------------------------------------------------------------------------------------------------------------
# collecting run directories


@dataclass
class RunRecord:
    """What one run directory says about itself."""

    run_dir: Path
    name: str
    scene: str
    encoding: str
    render: str
    preset: str
    seed: int | None
    complete: bool
    status: str
    metrics: dict = field(default_factory=dict)
    config: dict = field(default_factory=dict)
    error: str | None = None
    cpu: str = ""  # CPU model the run ran on (run_info.json `machine`; '' when not recorded)
    threads: int | None = None  # torch / numba threads the run used (run_info.json)

    def value(self, col: Column) -> float | None:
        """The column's value for this run (scaled), or None when missing/non-finite."""
        v = number(self.metrics.get(col.metric))
        return None if v is None else v * col.scale


def number(v: Any) -> float | None:
    """A metric's value as a finite float, or None (missing, not a number, a bool, non-finite, or an integer beyond
    float's range)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        f = float(v)
    except OverflowError:
        return None
    return f if math.isfinite(f) else None


def _mapping(x: Any) -> dict:
    """x when it is a dict, else {} (a file or section of the wrong type reads as empty)."""
    return x if isinstance(x, dict) else {}


def _is_run_dir(d: Path) -> bool:
    rd = RunDir(d)
    return any(p.is_file() for p in (rd.run_info, rd.metrics, rd.config, rd.bench, rd.error))


def find_run_dirs(runs_dir: str | os.PathLike, exclude: Path | None = None) -> list[Path]:
    """Run directories under `runs_dir` (itself, or nested at any depth), sorted by path."""
    root = Path(runs_dir)
    found = []
    stack = [root]
    while stack:
        d = stack.pop()
        if exclude is not None and d.resolve() == exclude.resolve():
            continue
        if _is_run_dir(d):
            found.append(d)
            continue
        stack += [c for c in d.iterdir() if c.is_dir() and c.name not in SKIP_DIRS and not c.name.startswith(".")]
    return sorted(found)


def read_run(run_dir: str | os.PathLike) -> RunRecord:
    """RunRecord from one run directory (missing files give empty fields).

    `status` is "complete", "corrupt: <files>" (run_info.json / metrics.json present but not a JSON object: never
    counted complete), "failed" (error.txt), else run_info.json's status or "not started".
    """
    d = Path(run_dir)
    rd = RunDir(d)
    metrics, info, bench = (_mapping(x) for x in (rd.read_metrics(), rd.read_run_info(), rd.read_json("bench")))
    try:
        config = _mapping(load_yaml(rd.config)) if rd.config.is_file() else {}
    except ConfigError:
        config = {}
    data_path = (_mapping(config.get("data")).get("path") or _mapping(info.get("dataset")).get("root") or "")
    scene = bench.get("scene") or (scene_short_name(str(data_path)) if data_path else d.name)
    encoding = metrics.get("encoding") or info.get("encoding") or _mapping(config.get("field")).get("encoding") or "?"
    render = metrics.get("render") or info.get("render") or _mapping(config.get("render")).get("name") or "?"
    seed = bench.get("seed", config.get("seed"))
    seed = seed if isinstance(seed, int) and not isinstance(seed, bool) else None  # a written-over file: no seed
    err = None
    if rd.error.is_file():
        try:
            text = rd.error.read_text(errors="replace")
        except OSError as e:
            text = f"error.txt unreadable ({e})"
        lines = [ln for ln in text.splitlines() if ln.strip()]
        err = lines[-1] if lines else "error"
    corrupt = rd.corrupt_files()
    complete = rd.is_complete() and not corrupt
    if corrupt:
        status = "corrupt: " + ", ".join(corrupt)
    else:
        status = "complete" if complete else ("failed" if err else str(info.get("status", "not started")))
    cpu = _mapping(info.get("machine")).get("cpu")
    threads = info.get("threads")
    return RunRecord(run_dir=d, name=d.name, scene=str(scene), encoding=str(encoding), render=str(render),
                     preset=str(bench.get("preset") or ""), seed=seed, complete=complete, status=status,
                     metrics=metrics if complete else {}, config=config, error=err,
                     cpu=cpu if isinstance(cpu, str) else "",
                     threads=threads if isinstance(threads, int) and not isinstance(threads, bool) else None)


def collect_runs(runs_dir: str | os.PathLike, exclude: Path | None = None) -> list[RunRecord]:
    """Every run directory under `runs_dir`, complete or not."""
    return [read_run(d) for d in find_run_dirs(runs_dir, exclude)]


# ----------------------------------------------------------------------------------------------------------------
# aggregation


@dataclass
class Row:
    """One G x F (x preset) row: per-column values over runs, their mean, std and the best flag."""

    render: str
    encoding: str
    preset: str
    runs: list[str]
    values: dict[str, list[float]]
    mean: dict[str, float | None] = field(default_factory=dict)
    std: dict[str, float | None] = field(default_factory=dict)
    best: dict[str, bool] = field(default_factory=dict)
    why: dict[str, str] = field(default_factory=dict)  # column key -> why it has no value ('' when it has one)
    total: int = 0  # the row's runs in the folder, complete or not (0: as many as `runs`)

    @property
    def n_runs(self) -> int:
        """The row's runs, complete or not."""
        return max(self.total, len(self.runs))

    def partial(self, key: str) -> bool:
        """Whether the mean of column `key` leaves out some of the row's runs (failed, unfinished, or null there):
        such a mean is shown with its count and never marked best, as the rows it would beat cover more."""
        return self.mean.get(key) is not None and len(self.values[key]) < self.n_runs


def _mean_std(vals: list[float]) -> tuple[float | None, float | None]:
    if not vals:
        return None, None
    m = sum(vals) / len(vals)
    if len(vals) < 2:
        return m, None
    return m, math.sqrt(sum((v - m) ** 2 for v in vals) / (len(vals) - 1))  # sample std (n-1)


def aggregate(records: list[RunRecord], columns: tuple[Column, ...] = COLUMNS) -> list[Row]:
    """Group complete runs by (render, encoding, preset); mean ± sample std over seeds and scenes; mark bests.
    Runs of `records` that are not complete count in their row's `total` (a mean over fewer is `Row.partial`)."""
    groups: dict[tuple, list[RunRecord]] = {}
    totals: dict[tuple, int] = {}
    for r in records:
        key = (r.render, r.encoding, r.preset)
        totals[key] = totals.get(key, 0) + 1
        if r.complete:
            groups.setdefault(key, []).append(r)
    rows = []
    for (ren, enc, preset), recs in sorted(groups.items(), key=lambda kv: (_order(kv[0][0], RENDER_LABELS),
                                                                         _order(kv[0][1], ENCODING_LABELS), kv[0][2])):
        values = {c.key: [v for v in (r.value(c) for r in recs) if v is not None] for c in columns}
        row = Row(render=ren, encoding=enc, preset=preset, runs=sorted(r.name for r in recs), values=values,
                  total=totals[(ren, enc, preset)])
        for c in columns:
            row.mean[c.key], row.std[c.key] = _mean_std(values[c.key])
            row.why[c.key] = missing_reason(recs, c) if row.mean[c.key] is None else ""
        rows.append(row)
    mark_best(rows, columns)
    return rows


# words of the evaluation notes (metrics.json `eval_notes`) that explain a missing value of these metrics
NOTE_WORDS = {"acc_m": ("Acc/Comp", "mesh metrics"), "comp_m": ("Acc/Comp", "mesh metrics"),
              "comp_ratio": ("Acc/Comp", "mesh metrics"), "ate_rmse_m": ("ATE",),
              "drift_m_per_100": ("ATE", "drift")}


def missing_reason(records: list[RunRecord], col: Column) -> str:
    """Why the runs have no value for `col`: the first evaluation note that explains it, else what metrics.json
    holds; one clause per distinct reason, with the number of runs when several share it."""
    reasons: dict[str, int] = {}
    for r in records:
        words = NOTE_WORDS.get(col.metric, ()) + (col.metric,)
        notes = [n for n in (r.metrics.get("eval_notes") or []) if any(w in str(n) for w in words)]
        if notes:
            why = str(notes[0])
        elif col.metric not in r.metrics:
            why = f"metrics.json has no {col.metric}"
        else:
            why = f"{col.metric} is null in metrics.json"
        reasons[why] = reasons.get(why, 0) + 1
    if not reasons:
        return "no complete run"
    return "; ".join(why if n == 1 else f"{why} ({n} runs)" for why, n in reasons.items())


def missing_notes(rows: list[Row], columns: tuple[Column, ...] = COLUMNS) -> list[tuple[str, str]]:
    """The distinct reasons for the '–' cells of a table, in order of appearance, each with where it applies:
    [(reason, 'Acc [cm], Comp [cm]: every row; ATE [cm]: SDF(direct) / Dense')]."""
    where: dict[str, dict[str, list[str]]] = {}
    for c in columns:
        for r in rows:
            if r.mean.get(c.key) is None:
                why = r.why.get(c.key) or "no value"
                where.setdefault(why, {}).setdefault(c.title, []).append(
                    f"{render_label(r.render)} / {encoding_label(r.encoding)}" + (f" [{r.preset}]" if r.preset else ""))
    out = []
    for why, cols in where.items():
        by_rows: dict[str, list[str]] = {}  # the same rows for several columns: named once
        for title, labels in cols.items():
            key = "every row" if len(labels) == len(rows) else ", ".join(labels)
            by_rows.setdefault(key, []).append(title)
        out.append((why, "; ".join(f"{', '.join(titles)}: {key}" for key, titles in by_rows.items())))
    return out


def mark_best(rows: list[Row], columns: tuple[Column, ...] = COLUMNS) -> None:
    """Set `row.best[key]` for the row(s) with the best mean of each column (ties all marked), among the means
    over all of a row's runs (a `Row.partial` mean is never best)."""
    for c in columns:
        means = [m for r in rows if (m := r.mean.get(c.key)) is not None and not r.partial(c.key)]
        target = (max if c.higher_better else min)(means) if means else None
        for r in rows:
            m = r.mean.get(c.key)
            r.best[c.key] = (m is not None and target is not None and not r.partial(c.key)
                             and math.isclose(m, target, rel_tol=1e-12, abs_tol=1e-15))


PARTIAL_NOTE = "(k/n): mean over k of the row's n runs (the others failed, did not finish or have no value); not ranked"


# ----------------------------------------------------------------------------------------------------------------
# formatting


def format_cell(row: Row, col: Column, pm: str = " ± ") -> str:
    """'1.37 ± 0.12' (std only with two or more runs), '1.37 (2/3)' for a `Row.partial` mean, or '–' when
    missing."""
    m = row.mean.get(col.key)
    if m is None:
        return MISSING
    s = row.std.get(col.key)
    text = f"{m:.{col.decimals}f}"
    if s is not None:
        text += f"{pm}{s:.{col.decimals}f}"
    if row.partial(col.key):
        text += f" ({len(row.values[col.key])}/{row.n_runs})"
    return text


def _has_partial(rows: list[Row], columns: tuple[Column, ...]) -> bool:
    return any(r.partial(c.key) for r in rows for c in columns)


def _show_preset(rows: list[Row]) -> bool:
    return len({r.preset for r in rows}) > 1


def _runs_count(row: Row) -> int:
    return len(row.runs)


def to_markdown(rows: list[Row], columns: tuple[Column, ...] = COLUMNS, title: str | None = None) -> str:
    """GitHub Markdown table; best per column in bold."""
    preset = _show_preset(rows)
    head = ["G", "F"] + (["preset"] if preset else []) + ["runs"] + [
        c.title + (" ↑" if c.higher_better else " ↓") for c in columns]
    lines = [f"### {title}", ""] if title else []
    lines += ["| " + " | ".join(head) + " |", "|" + "|".join(":--" if i < len(head) - len(columns) else "--:"
                                                             for i in range(len(head))) + "|"]
    for r in rows:
        cells = [render_label(r.render), encoding_label(r.encoding)] + ([r.preset] if preset else []) + [
            str(_runs_count(r))]
        for c in columns:
            text = format_cell(r, c)
            cells.append(f"**{text}**" if r.best.get(c.key) else text)
        lines.append("| " + " | ".join(cells) + " |")
    if not rows:
        lines.append("| " + " | ".join([MISSING] * len(head)) + " |")
    notes = missing_notes(rows, columns)
    if notes or _has_partial(rows, columns):
        lines += [""] + [f"- {MISSING}: {why} ({cells})" for why, cells in notes]
        lines += [f"- {PARTIAL_NOTE}"] if _has_partial(rows, columns) else []
    return "\n".join(lines) + "\n"


def to_csv(rows: list[Row], columns: tuple[Column, ...] = COLUMNS, scene: str | None = None) -> str:
    """CSV: render, encoding, preset, runs (complete), then <key>_mean, <key>_std, <key>_n, <key>_best per column,
    `best` (the columns this row is best in, ';'-separated) and `runs_total` (complete or not). Missing values are
    empty cells."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    head = (["scene"] if scene is not None else []) + ["render", "encoding", "preset", "runs"]
    for c in columns:
        head += [f"{c.key}_mean", f"{c.key}_std", f"{c.key}_n", f"{c.key}_best"]
    w.writerow(head + ["best", "runs_total"])
    for r in rows:
        line = ([scene] if scene is not None else []) + [r.render, r.encoding, r.preset, len(r.runs)]
        for c in columns:
            m, s = r.mean.get(c.key), r.std.get(c.key)
            line += ["" if m is None else repr(m), "" if s is None else repr(s), len(r.values[c.key]),
                     int(bool(r.best.get(c.key)))]
        w.writerow(line + [";".join(c.key for c in columns if r.best.get(c.key)), r.n_runs])
    return buf.getvalue()


_TEX = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "_": r"\_", "#": r"\#", "$": r"\$", "{": r"\{",
        "}": r"\}", "^": r"\textasciicircum{}", "~": r"\textasciitilde{}"}
_TEX_SPECIAL = re.compile("|".join(re.escape(k) for k in _TEX))


def _tex_escape(text: str) -> str:
    r"""LaTeX text for `text`, every special character replaced in one pass.

    Example: 'a_b\c' -> 'a\_b\textbackslash{}c'."""
    return _TEX_SPECIAL.sub(lambda m: _TEX[m.group()], text)


def to_latex(rows: list[Row], columns: tuple[Column, ...] = COLUMNS, caption: str | None = None) -> str:
    """booktabs tabular (needs \\usepackage{booktabs}); best per column in \\textbf; G printed once per group."""
    preset = _show_preset(rows)
    n_lead = 2 + (1 if preset else 0) + 1
    spec = "l" * n_lead + "r" * len(columns)
    head = ["G", "F"] + (["preset"] if preset else []) + ["runs"] + [
        _tex_escape(c.title) + (r"$\uparrow$" if c.higher_better else r"$\downarrow$") for c in columns]
    lines = [r"\begin{table}[t]", r"\centering", r"\small"]
    if caption:
        lines.append(r"\caption{" + _tex_escape(caption) + "}")
    lines += [r"\begin{tabular}{" + spec + "}", r"\toprule", " & ".join(head) + r" \\", r"\midrule"]
    prev = None
    for r in rows:
        if prev is not None and r.render != prev:
            lines.append(r"\midrule")
        g = _tex_escape(render_label(r.render)) if r.render != prev else ""
        cells = [g, _tex_escape(encoding_label(r.encoding))] + ([_tex_escape(r.preset)] if preset else []) + [
            str(len(r.runs))]
        for c in columns:
            text = format_cell(r, c, pm=r" $\pm$ ")
            text = "--" if text == MISSING else text
            cells.append(r"\textbf{" + text + "}" if r.best.get(c.key) else text)
        lines.append(" & ".join(cells) + r" \\")
        prev = r.render
    lines += [r"\bottomrule", r"\end{tabular}"]
    if _has_partial(rows, columns):
        lines.append(r"\\[2pt]{\footnotesize " + _tex_escape(PARTIAL_NOTE) + "}")
    lines.append(r"\end{table}")
    return "\n".join(lines) + "\n"


def to_html(rows: list[Row], columns: tuple[Column, ...] = COLUMNS) -> str:
    """HTML <table> (best in <b>), for the report page; a '–' cell carries a footnote number (and a tooltip) that
    the notes under the table explain."""
    import html

    preset = _show_preset(rows)
    head = ["G", "F"] + (["preset"] if preset else []) + ["runs"] + [
        c.title + (" ↑" if c.higher_better else " ↓") for c in columns]
    notes = missing_notes(rows, columns)
    number = {why: k + 1 for k, (why, _) in enumerate(notes)}
    out = ["<table>", "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for r in rows:
        cells = [render_label(r.render), encoding_label(r.encoding)] + ([r.preset] if preset else []) + [
            str(len(r.runs))]
        tds = [f"<td>{html.escape(x)}</td>" for x in cells]
        for c in columns:
            text = html.escape(format_cell(r, c))
            if r.mean.get(c.key) is None:
                why = r.why.get(c.key) or "no value"
                tds.append(f"<td class='num missing' title='{html.escape(why, quote=True)}'>{text}"
                           f"<sup>{number[why]}</sup></td>")
            elif r.best.get(c.key):
                tds.append(f"<td class='num'><b>{text}</b></td>")
            else:
                tds.append(f"<td class='num'>{text}</td>")
        out.append("<tr>" + "".join(tds) + "</tr>")
    out.append("</table>")
    if notes:
        out.append("<ol class='notes'>" + "".join(
            f"<li>{MISSING}: {html.escape(why)} <span class='where'>({html.escape(cells)})</span></li>"
            for why, cells in notes) + "</ol>")
    if _has_partial(rows, columns):
        out.append(f"<p class='notes'>{html.escape(PARTIAL_NOTE)}</p>")
    return "\n".join(out)
