"""Leaderboard plots (matplotlib, Agg backend), each saved as PNG and SVG.

Every plot gives each G one colour and each F one marker (`styles`), keeps its legends outside the axes, and
draws an error bar (sample std) only where a value is a mean of two or more runs.

- `plot_tradeoff`: model size [MB] (log x) vs ATE [cm], one point per F x G (supplementary Fig. 3).
- `plot_bars`: one grouped-bar chart per metric, F on the x axis, one bar per G.
- `plot_ate_over_frames`: per scene, small multiples (one panel per F x G, rows G, columns F, shared axes) of the
  translational error of every frame after aligning the whole trajectory.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from inrslam.bench.leaderboard import (
    COLUMNS,
    ENCODING_LABELS,
    RENDER_LABELS,
    Column,
    Row,
    RunRecord,
    _order,
    encoding_label,
    render_label,
)
from inrslam.bench.spec import sanitize
from inrslam.errors import ConfigError, DataError
from inrslam.eval.config import Alignment
from inrslam.eval.trajectory import associate, ate
from inrslam.io.atomic import atomic_path
from inrslam.io.rundir import RunDir
from inrslam.io.trajectory import read_tum
from inrslam.io.yamlfile import load_yaml

MARKERS = "osD^v<>pPX*h"
PRESET_FILLS = ("full", "none", "left", "right", "bottom", "top")  # marker fill per preset (tradeoff plot)
PRESET_LINES = ("-", "--", ":", "-.")  # line style per preset (ATE over frames)
OUTSIDE = {"loc": "upper left", "bbox_to_anchor": (1.02, 1.0), "borderaxespad": 0.0}  # legend right of the axes


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, out_dir: Path, stem: str) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for ext in ("png", "svg"):
        path = out_dir / f"{stem}.{ext}"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=120, bbox_inches="tight", format=ext)
        paths.append(path)
    _plt().close(fig)
    return paths


def _renders(rows) -> list[str]:
    return sorted(dict.fromkeys(r.render for r in rows), key=lambda g: _order(g, RENDER_LABELS))


def _encodings(rows) -> list[str]:
    return sorted(dict.fromkeys(r.encoding for r in rows), key=lambda f: _order(f, ENCODING_LABELS))


def styles(rows) -> tuple[dict, dict]:
    """({G: colour}, {F: marker}) for the rows (anything with .render / .encoding): tab10 colours and `MARKERS`
    in the leaderboard's order of G and F, the same in every plot of a report."""
    cmap = _plt().get_cmap("tab10")
    return ({g: cmap(i % 10) for i, g in enumerate(_renders(rows))},
            {f: MARKERS[i % len(MARKERS)] for i, f in enumerate(_encodings(rows))})


def _key_legend(ax, rows, presets: list[str] | None = None) -> None:
    """One legend right of `ax`: colour = G, marker = F (and marker fill = preset when there are several), each
    group under its heading."""
    from matplotlib.lines import Line2D

    colors, markers = styles(rows)
    heading = lambda text: (Line2D([], [], ls="none"), text)  # noqa: E731
    entries = [heading("G (colour)")]
    entries += [(Line2D([], [], color=colors[g], lw=6), render_label(g)) for g in colors]
    entries += [heading("F (marker)")]
    entries += [(Line2D([], [], color="0.3", marker=markers[f], ls="none", ms=8), encoding_label(f)) for f in markers]
    if presets and len(presets) > 1:
        entries += [heading("preset (fill)")]
        entries += [(Line2D([], [], color="0.3", marker="o", ls="none", ms=8,
                            fillstyle=PRESET_FILLS[k % len(PRESET_FILLS)]), p or "(none)")
                    for k, p in enumerate(presets)]
    ax.legend([h for h, _ in entries], [t for _, t in entries], fontsize=7, **OUTSIDE)


def tradeoff_figure(rows: list[Row]):
    """The figure of `plot_tradeoff`, or None when no row has both a model size and an ATE."""
    pts = [r for r in rows if r.mean.get("model_mb") and r.mean.get("ate_cm") is not None]
    if not pts:
        return None
    plt = _plt()
    colors, markers = styles(rows)
    presets = list(dict.fromkeys(r.preset for r in rows))
    fig, ax = plt.subplots(figsize=(7, 5))
    for r in pts:
        x, y, sd = r.mean["model_mb"], r.mean["ate_cm"], r.std.get("ate_cm")
        fill = PRESET_FILLS[presets.index(r.preset) % len(PRESET_FILLS)]
        ax.plot(x, y, ls="none", marker=markers[r.encoding], color=colors[r.render], ms=9, fillstyle=fill)
        if sd is not None:  # a mean of two or more runs
            ax.errorbar(x, y, yerr=sd, fmt="none", ecolor=colors[r.render], capsize=3)
    ax.set_xscale("log")
    ax.set_xlabel("model size [MB] (log scale)")
    ax.set_ylabel("ATE RMSE [cm]")
    ax.set_title("Memory vs accuracy (lower left is better)")
    ax.grid(True, which="both", alpha=0.3)
    _key_legend(ax, rows, presets)
    return fig


def plot_tradeoff(rows: list[Row], out_dir: str | os.PathLike, stem: str = "tradeoff_memory_ate") -> list[Path]:
    """Model size (log x) vs ATE, one point per F x G (error bar = std over two or more runs). [] when no row has
    both."""
    fig = tradeoff_figure(rows)
    return [] if fig is None else _save(fig, Path(out_dir), stem)


def bars_figure(rows: list[Row], c: Column):
    """The figure of one column of `plot_bars`, or None when no row has a value."""
    if not any(r.mean.get(c.key) is not None for r in rows):
        return None
    plt = _plt()
    colors, _ = styles(rows)
    encodings = _encodings(rows)
    series = list(dict.fromkeys((r.render, r.preset) for r in rows))
    with_preset = len({r.preset for r in rows}) > 1
    fig, ax = plt.subplots(figsize=(max(5.0, 1.2 * len(encodings) + 2), 4))
    width = 0.8 / max(1, len(series))
    x = np.arange(len(encodings))
    for k, (ren, preset) in enumerate(series):
        by_f = {r.encoding: r for r in rows if (r.render, r.preset) == (ren, preset)}
        ok = [i for i, f in enumerate(encodings) if f in by_f and by_f[f].mean.get(c.key) is not None]
        if not ok:
            continue
        xs = x[ok] + (k - (len(series) - 1) / 2) * width
        means = [by_f[encodings[i]].mean[c.key] for i in ok]
        label = render_label(ren) + (f" [{preset}]" if with_preset and preset else "")
        ax.bar(xs, means, width, color=colors[ren], label=label,
               alpha=1.0 if k % 2 == 0 or not with_preset else 0.6)
        sds = [by_f[encodings[i]].std.get(c.key) for i in ok]
        with_sd = [j for j, sd in enumerate(sds) if sd is not None]  # means of two or more runs
        if with_sd:
            ax.errorbar(xs[with_sd], [means[j] for j in with_sd], yerr=[sds[j] for j in with_sd], fmt="none",
                        ecolor="0.15", capsize=3)
    ax.set_xticks(x, [encoding_label(f) for f in encodings], rotation=20, ha="right")
    ax.set_ylabel(c.title + (" (higher is better)" if c.higher_better else " (lower is better)"))
    if c.key == "model_mb":
        ax.set_yscale("log")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(title="G", fontsize=8, **OUTSIDE)
    return fig


def plot_bars(rows: list[Row], out_dir: str | os.PathLike, columns: tuple[Column, ...] = COLUMNS) -> list[Path]:
    """One grouped bar chart per column having any value: x = F, one bar per G (and preset), error bars = std
    over two or more runs."""
    paths = []
    for c in columns:
        fig = bars_figure(rows, c)
        if fig is not None:
            paths += _save(fig, Path(out_dir), f"bars_{c.key}")
    return paths


# ----------------------------------------------------------------------------------------------------------------
# ATE over frames


def ate_over_frames(run_dir: str | os.PathLike, align: str | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """(frame positions in trajectory.txt, per-frame ATE errors in metres) after aligning the whole trajectory.

    Uses `trajectory.txt` / `trajectory_gt.txt` (associated by timestamp) and `inrslam.eval.trajectory.ate` with the
    run's `eval.align` (se3 default); None when a file is missing or nothing associates.
    """
    d = Path(run_dir)
    try:
        ts_e, est = read_tum(RunDir(d).trajectory)
        ts_g, gt = read_tum(RunDir(d).trajectory_gt)
    except DataError:
        return None
    if align is None:
        try:
            cfg = load_yaml(RunDir(d).config) or {}
        except ConfigError:
            cfg = {}
        section = cfg.get("eval") if isinstance(cfg, dict) else None
        align = str((section.get("align") if isinstance(section, dict) else None) or "se3")
    if align not in {a.value for a in Alignment}:
        return None  # a written-over config.yaml: no curve rather than a guess
    ia, ib = associate(ts_e, ts_g, max_diff=1e-3)
    if len(ia) < 3:
        return None
    try:
        res = ate(est[ia], gt[ib], align=align)
    except ValueError:  # e.g. Sim(3) of an estimate that never moves
        return None
    return ia[res["used"]], np.asarray(res["errors"], dtype=np.float64)


def ate_frames_figure(records: list[RunRecord], scene: str):
    """The small multiples of `plot_ate_over_frames` for one scene, or None when no complete run of it has
    associated ground truth. Rows G, columns F (an empty panel says there is no such run); in a panel one line per
    run (seed; line style per preset), its colour the G's and its marker the F's; shared axes."""
    recs = [r for r in records if r.complete and r.scene == scene]
    curves = []
    for r in sorted(recs, key=lambda r: (r.preset, r.seed or 0)):
        got = ate_over_frames(r.run_dir)
        if got is not None and len(got[1]):
            curves.append((r, got))
    if not curves:
        return None
    plt = _plt()
    runs = [r for r, _ in curves]
    colors, markers = styles(runs)
    renders, encodings = _renders(runs), _encodings(runs)
    presets = list(dict.fromkeys(r.preset for r in runs))
    nr, nc = len(renders), len(encodings)
    fig, axes = plt.subplots(nr, nc, figsize=(2.6 * nc + 1.2, 2.1 * nr + 0.9), sharex=True, sharey=True,
                             squeeze=False)
    for i, g in enumerate(renders):
        for j, f in enumerate(encodings):
            ax = axes[i][j]
            mine = [(r, c) for r, c in curves if (r.render, r.encoding) == (g, f)]
            ax.set_title(f"{encoding_label(f)} / {render_label(g)}", fontsize=8)
            ax.grid(True, alpha=0.3)
            if not mine:
                ax.text(0.5, 0.5, "– no run", ha="center", va="center", transform=ax.transAxes, color="0.5")
            for r, (x, e) in mine:
                ax.plot(x, e * 100.0, color=colors[g], marker=markers[f], markevery=max(1, len(x) // 8),
                        markersize=3.5, linewidth=1.0, ls=PRESET_LINES[presets.index(r.preset) % len(PRESET_LINES)])
            if i == nr - 1:
                ax.set_xlabel("frame", fontsize=8)
            if j == 0:
                ax.set_ylabel("error [cm]", fontsize=8)
            ax.tick_params(labelsize=7)
    multi_seed = len({r.seed for r in runs}) > 1
    fig.suptitle(f"ATE over frames — {scene}: translational error after aligning the whole trajectory"
                 + (" (one line per seed)" if multi_seed else ""), fontsize=9)
    if len(presets) > 1:
        from matplotlib.lines import Line2D

        handles = [Line2D([], [], color="0.3", ls=PRESET_LINES[k % len(PRESET_LINES)]) for k in range(len(presets))]
        fig.legend(handles, [p or "(none)" for p in presets], title="preset", fontsize=7, loc="upper left",
                   bbox_to_anchor=(1.0, 0.95))
    fig.tight_layout()
    return fig


def plot_ate_over_frames(records: list[RunRecord], out_dir: str | os.PathLike) -> list[Path]:
    """Per scene, `ate_frames_figure` (small multiples of per-frame ATE [cm] vs frame). Files
    `ate_frames_<scene>.{png,svg}`."""
    paths = []
    for scene in sorted({r.scene for r in records if r.complete}):
        fig = ate_frames_figure(records, scene)
        if fig is not None:
            paths += _save(fig, Path(out_dir), f"ate_frames_{sanitize(scene)}")
    return paths
