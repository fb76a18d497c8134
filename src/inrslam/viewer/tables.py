"""Metrics as markdown for the viewer's panel: one run's table, and the comparison of several runs (the best value of
each column in bold)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Column:
    """A metrics.json key shown as `label` [unit], stored value x `factor`, with `digits` decimals."""

    key: str
    label: str
    factor: float = 1.0
    digits: int = 2
    higher_is_better: bool = False


# the comparison table of `inrslam view RUN_A RUN_B`
COMPARE = (
    Column("ate_rmse_m", "ATE [cm]", 100.0),
    Column("acc_m", "Acc [cm]", 100.0),
    Column("comp_ratio", "Comp [%]", 100.0, 1, higher_is_better=True),
    Column("psnr_db", "PSNR [dB]", 1.0, 2, higher_is_better=True),
    Column("depth_l1_m", "Depth L1 [cm]", 100.0),
    Column("wall_time_s", "Time [s]", 1.0, 0),
)
# one run's panel: the comparison columns and more
DETAIL = (
    *COMPARE[:2],
    Column("comp_m", "Comp [cm]", 100.0),
    COMPARE[2],
    Column("rpe_trans_m", "RPE [cm]", 100.0),
    Column("drift_m_per_100", "Drift [cm / 100 frames]", 100.0),
    *COMPARE[3:5],
    Column("ssim", "SSIM", 1.0, 3, higher_is_better=True),
    Column("psnr_process_db", "PSNR process [dB]", 1.0),
    Column("track_ms_per_frame", "Tracking [ms / frame]", 1.0, 0),
    Column("map_ms_per_call", "Mapping [ms / call]", 1.0, 0),
    Column("model_size_mb", "Model [MiB]", 1.0),
    Column("frames", "Frames", 1.0, 0),
    COMPARE[5],
)
MISSING = "–"


def value(metrics: dict | None, col: Column) -> float | None:
    """The column's value in display units, or None when the run lacks it (or it is not a finite number)."""
    v: Any = (metrics or {}).get(col.key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        return None
    return float(v) * col.factor


def cell(v: float | None, col: Column) -> str:
    return MISSING if v is None else f"{v:.{col.digits}f}"


def metrics_markdown(metrics: dict | None, columns: Sequence[Column] = DETAIL) -> str:
    """A two-column markdown table (metric, value) of the columns the run has; a line when it has none."""
    rows = [(c.label, cell(value(metrics, c), c)) for c in columns if value(metrics, c) is not None]
    if not rows:
        return "*no metrics (metrics.json missing or empty)*"
    return "\n".join(["| metric | value |", "|:--|--:|", *(f"| {k} | {v} |" for k, v in rows)])


def comparison_rows(labels: Sequence[str], metrics: Sequence[dict | None],
                    columns: Sequence[Column] = COMPARE) -> list[list[str]]:
    """Rows [label, cell, ...] of the comparison table; with two or more values in a column the best is **bold**."""
    vals = [[value(m, c) for c in columns] for m in metrics]
    best: list[float | None] = []
    for j, c in enumerate(columns):
        present = [v for row in vals if (v := row[j]) is not None]
        best.append((max(present) if c.higher_is_better else min(present)) if len(present) >= 2 else None)
    rows = []
    for label, row in zip(labels, vals):
        cells = [cell(v, c) for v, c in zip(row, columns)]
        cells = [f"**{s}**" if v is not None and v == b else s for s, v, b in zip(cells, row, best)]
        rows.append([label, *cells])
    return rows


def comparison_markdown(labels: Sequence[str], metrics: Sequence[dict | None],
                        columns: Sequence[Column] = COMPARE) -> str:
    """Markdown table comparing runs: one row per run, the columns of `COMPARE`."""
    head = "| run | " + " | ".join(c.label for c in columns) + " |"
    rule = "|:--|" + "--:|" * len(columns)
    return "\n".join([head, rule, *("| " + " | ".join(r) + " |" for r in comparison_rows(labels, metrics, columns))])
