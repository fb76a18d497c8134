"""The report's plots: one colour per G and one marker per F everywhere, legends outside the axes, error bars only
for means of two or more runs, ATE over frames as small multiples (rows G, columns F)."""

from __future__ import annotations

import pytest
from matplotlib.container import ErrorbarContainer

from inrslam.bench.leaderboard import COLUMN_BY_KEY, aggregate, collect_runs
from inrslam.bench.plots import _plt, ate_frames_figure, bars_figure, styles, tradeoff_figure
from inrslam.bench.testing import write_fake_run


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """room: dense/density over 2 seeds (a std), hash/density and dense/direct once; thin: dense/density once."""
    root = tmp_path_factory.mktemp("plots")
    for scene, enc, ren, seed in (("room", "dense", "density", 0), ("room", "dense", "density", 1),
                                  ("room", "hash", "density", 0), ("room", "dense", "direct", 0),
                                  ("thin", "dense", "density", 0)):
        write_fake_run(root / f"{scene}__{enc}__{ren}__paper__s{seed}", enc, ren, scene, seed, preset="paper",
                       frames=12)
    records = collect_runs(root)
    return records, aggregate([r for r in records if r.scene == "room"])


def errorbars(ax) -> list:
    return [c for c in ax.containers if isinstance(c, ErrorbarContainer)]


def legend_is_outside(fig, ax, legend) -> bool:
    fig.canvas.draw()
    return legend.get_window_extent().x0 >= ax.get_window_extent().x1


def test_tradeoff_error_bars_only_for_means_of_several_runs(runs):
    _, rows = runs
    fig = tradeoff_figure(rows)
    ax = fig.axes[0]
    colors, markers = styles(rows)
    bars = errorbars(ax)
    caps = {id(c) for b in bars for c in b.lines[1]}
    points = [ln for ln in ax.lines if id(ln) not in caps]
    assert len(points) == 3
    assert len(bars) == 1  # dense/density: 2 runs; the two single runs have none
    two_runs = next(r for r in rows if len(r.runs) == 2)
    assert {(ln.get_marker(), tuple(ln.get_color())) for ln in points} == {
        (markers[r.encoding], tuple(colors[r.render])) for r in rows}
    seg = bars[0].lines[2][0].get_segments()[0]  # the vertical bar: mean +- std
    assert seg[1][1] - seg[0][1] == pytest.approx(2 * two_runs.std["ate_cm"])
    assert legend_is_outside(fig, ax, ax.get_legend())
    _plt().close(fig)


def test_bars_same_colours_error_bars_only_with_a_std(runs):
    _, rows = runs
    fig = bars_figure(rows, COLUMN_BY_KEY["ate_cm"])
    ax = fig.axes[0]
    colors, _ = styles(rows)
    bar_colors = {tuple(p.get_facecolor()[:3]) for p in ax.patches}
    assert bar_colors == {tuple(colors[g][:3]) for g in ("density", "direct")}
    bars = errorbars(ax)
    assert len(bars) == 1 and len(bars[0].lines[2][0].get_segments()) == 1  # one bar has a std
    assert legend_is_outside(fig, ax, ax.get_legend())
    _plt().close(fig)


def test_ate_over_frames_small_multiples(runs):
    records, rows = runs
    fig = ate_frames_figure(records, "room")
    colors, markers = styles(rows)
    axes = fig.axes
    assert len(axes) == 4  # rows G (direct, density) x columns F (dense, hash)
    titles = [ax.get_title() for ax in axes]
    assert titles == ["Dense / SDF(direct)", "Sparse (hash) / SDF(direct)", "Dense / SDF(density)",
                      "Sparse (hash) / SDF(density)"]
    lines = [len(ax.lines) for ax in axes]
    assert lines == [1, 0, 2, 1]  # two seeds of dense/density in one panel
    assert "no run" in axes[1].texts[0].get_text()
    for ax, (g, f) in zip(axes, [("direct", "dense"), ("direct", "hash"), ("density", "dense"), ("density", "hash")]):
        for ln in ax.lines:
            assert tuple(ln.get_color()) == tuple(colors[g]) and ln.get_marker() == markers[f]
    assert axes[0].get_shared_y_axes().joined(axes[0], axes[3])  # one scale across panels
    _plt().close(fig)
    assert ate_frames_figure(records, "nowhere") is None
