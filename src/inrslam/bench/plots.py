"""Leaderboard plots (matplotlib, Agg backend), each saved as PNG and SVG.

- `plot_tradeoff`: model size [MB] (log x) vs ATE [cm], one labelled point per F x G (supplementary Fig. 3).
- `plot_bars`: one grouped-bar chart per metric, F on the x axis, one bar per G, error bars = std.
- `plot_ate_over_frames`: per scene, translational error of every frame after aligning the whole trajectory.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from inrslam.bench.leaderboard import (
    COLUMNS,
    ENCODING_LABELS,
    Column,
    Row,
    RunRecord,
    _order,
    encoding_label,
    render_label,
)
from inrslam.bench.spec import sanitize
from inrslam.errors import DataError
from inrslam.eval.trajectory import associate, ate
from inrslam.io.atomic import atomic_path
from inrslam.io.rundir import RunDir
from inrslam.io.trajectory import read_tum

MARKERS = "osD^v<>pPX*h"


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


def _styles(rows: list[Row]) -> tuple[dict, dict]:
    plt = _plt()
    renders = list(dict.fromkeys(r.render for r in rows))
    encodings = sorted(dict.fromkeys(r.encoding for r in rows), key=lambda e: _order(e, ENCODING_LABELS))
    cmap = plt.get_cmap("tab10")
    return ({g: cmap(i % 10) for i, g in enumerate(renders)}, {f: MARKERS[i % len(MARKERS)]
                                                              for i, f in enumerate(encodings)})


def _label(r: Row, with_preset: bool) -> str:
    text = f"{encoding_label(r.encoding)} / {render_label(r.render)}"
    return f"{text} [{r.preset}]" if with_preset and r.preset else text


def plot_tradeoff(rows: list[Row], out_dir: str | os.PathLike, stem: str = "tradeoff_memory_ate") -> list[Path]:
    """Model size (log x) vs ATE, one labelled point per F x G with std error bars. [] when no row has both."""
    pts = [r for r in rows if r.mean.get("model_mb") and r.mean.get("ate_cm") is not None]
    if not pts:
        return []
    plt = _plt()
    colors, markers = _styles(rows)
    with_preset = len({r.preset for r in rows}) > 1
    fig, ax = plt.subplots(figsize=(7, 5))
    for r in pts:
        x, y = r.mean["model_mb"], r.mean["ate_cm"]
        ax.errorbar(x, y, yerr=r.std.get("ate_cm") or 0.0, fmt=markers[r.encoding], color=colors[r.render],
                    markersize=8, capsize=3, label=_label(r, with_preset))
        ax.annotate(_label(r, with_preset), (x, y), textcoords="offset points", xytext=(6, 4), fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel("model size [MB] (log scale)")
    ax.set_ylabel("ATE RMSE [cm]")
    ax.set_title("Memory vs accuracy (lower left is better)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return _save(fig, Path(out_dir), stem)


def plot_bars(rows: list[Row], out_dir: str | os.PathLike, columns: tuple[Column, ...] = COLUMNS) -> list[Path]:
    """One grouped bar chart per column having any value: x = F, one bar per G (and preset), error bars = std."""
    plt = _plt()
    colors, _ = _styles(rows)
    encodings = sorted(dict.fromkeys(r.encoding for r in rows), key=lambda e: _order(e, ENCODING_LABELS))
    series = list(dict.fromkeys((r.render, r.preset) for r in rows))
    with_preset = len({r.preset for r in rows}) > 1
    paths = []
    for c in columns:
        if not any(r.mean.get(c.key) is not None for r in rows):
            continue
        fig, ax = plt.subplots(figsize=(max(5.0, 1.2 * len(encodings) + 2), 4))
        width = 0.8 / max(1, len(series))
        x = np.arange(len(encodings))
        for k, (ren, preset) in enumerate(series):
            by_f = {r.encoding: r for r in rows if (r.render, r.preset) == (ren, preset)}
            means = [by_f[f].mean.get(c.key) if f in by_f else None for f in encodings]
            stds = [by_f[f].std.get(c.key) if f in by_f else None for f in encodings]
            ok = [i for i, m in enumerate(means) if m is not None]
            if not ok:
                continue
            label = render_label(ren) + (f" [{preset}]" if with_preset and preset else "")
            ax.bar(x[ok] + (k - (len(series) - 1) / 2) * width, [means[i] for i in ok], width,
                   yerr=[stds[i] or 0.0 for i in ok], capsize=3, color=colors[ren], label=label,
                   alpha=1.0 if k % 2 == 0 or not with_preset else 0.6)
        ax.set_xticks(x, [encoding_label(f) for f in encodings], rotation=20, ha="right")
        ax.set_ylabel(c.title + (" (higher is better)" if c.higher_better else " (lower is better)"))
        if c.key == "model_mb":
            ax.set_yscale("log")
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=8)
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
        import yaml

        try:
            cfg = yaml.safe_load(RunDir(d).config.read_text()) or {}
        except (OSError, yaml.YAMLError):
            cfg = {}
        align = str((cfg.get("eval") or {}).get("align") or "se3")
    ia, ib = associate(ts_e, ts_g, max_diff=1e-3)
    if len(ia) < 3:
        return None
    res = ate(est[ia], gt[ib], align=align)
    return ia[res["used"]], np.asarray(res["errors"], dtype=np.float64)


def plot_ate_over_frames(records: list[RunRecord], out_dir: str | os.PathLike) -> list[Path]:
    """Per scene, one curve per complete run: per-frame ATE [cm] vs frame. Files `ate_frames_<scene>.{png,svg}`."""
    plt = _plt()
    paths = []
    scenes = sorted({r.scene for r in records if r.complete})
    for scene in scenes:
        recs = [r for r in records if r.complete and r.scene == scene]
        recs.sort(key=lambda r: (_order(r.render, {}), _order(r.encoding, ENCODING_LABELS), r.preset, r.seed or 0))
        multi_seed = len({r.seed for r in recs}) > 1
        multi_preset = len({r.preset for r in recs}) > 1
        curves = []
        for r in recs:
            got = ate_over_frames(r.run_dir)
            if got is not None and len(got[1]):
                curves.append((r, got))
        if not curves:
            continue
        rows_like = [Row(render=r.render, encoding=r.encoding, preset=r.preset, runs=[], values={}) for r, _ in curves]
        colors, markers = _styles(rows_like)
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for r, (x, e) in curves:
            label = f"{encoding_label(r.encoding)} / {render_label(r.render)}"
            label += f" [{r.preset}]" if multi_preset and r.preset else ""
            label += f" s{r.seed}" if multi_seed else ""
            ax.plot(x, e * 100.0, color=colors[r.render], marker=markers[r.encoding], markevery=max(1, len(x) // 10),
                    markersize=4, linewidth=1.2, label=label)
        ax.set_xlabel("frame (position in trajectory.txt)")
        ax.set_ylabel("translational error after alignment [cm]")
        ax.set_title(f"ATE over frames — {scene}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
        paths += _save(fig, Path(out_dir), f"ate_frames_{sanitize(scene)}")
    return paths
