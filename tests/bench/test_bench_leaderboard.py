"""Leaderboards from hand-made run directories: aggregation, best marking, formats, plots, HTML."""

from __future__ import annotations

import csv
import io
import math
import statistics

import pytest

from inrslam.bench.leaderboard import COLUMN_BY_KEY, aggregate, collect_runs, to_csv, to_latex, to_markdown
from inrslam.bench.plots import ate_over_frames
from inrslam.bench.report import build_report, machines_note
from inrslam.bench.testing import write_fake_run


def M(ate_cm, psnr, model_mb, acc_cm=None, **extra):
    """metrics.json content in SI units (as runs write them)."""
    m = {"ate_rmse_m": ate_cm / 100, "psnr_process_db": psnr, "model_size_mb": model_mb,
         "comp_m": 0.05, "comp_ratio": 0.8, "depth_l1_process_m": 0.02, "track_ms_per_frame": 200.0,
         "map_ms_per_call": 400.0}
    if acc_cm is not None:
        m["acc_m"] = acc_cm / 100
    m.update(extra)
    return m


@pytest.fixture
def runs(tmp_path):
    """dense/density on 2 scenes x 2 seeds, hash/density on 1 scene, dense/direct on 1 scene, + 2 broken runs."""
    root = tmp_path / "runs"
    metrics = {
        ("room", "dense", "density", 0): M(1.0, 25.0, 40.0, acc_cm=2.0),
        ("room", "dense", "density", 1): M(2.0, 26.0, 40.0, acc_cm=3.0),
        ("thin", "dense", "density", 0): M(4.0, 27.0, 40.0, acc_cm=4.0),
        ("thin", "dense", "density", 1): M(5.0, 28.0, 40.0, acc_cm=5.0),
        ("room", "hash", "density", 0): M(1.5, 30.0, 0.5),  # no acc: shows as missing
        ("room", "dense", "direct", 0): M(0.5, 24.0, 40.0, acc_cm=1.0),
    }
    for (scene, enc, ren, seed), m in metrics.items():
        write_fake_run(root / f"{scene}__{enc}__{ren}__paper__s{seed}", enc, ren, scene, seed, metrics=m,
                       preset="paper", frames=12)
    write_fake_run(root / "room__mlp__density__paper__s0", "mlp", "density", "room", 0, metrics=M(9, 9, 9),
                   status="running")  # interrupted: not in the tables
    bad = root / "room__tensorf__density__paper__s0"
    bad.mkdir(parents=True)
    (bad / "error.txt").write_text("Traceback ...\nRuntimeError: out of memory\n")
    return root, metrics


def test_collect_and_aggregate_mean_std(runs):
    root, metrics = runs
    recs = collect_runs(root)
    assert len(recs) == 8
    assert sum(r.complete for r in recs) == 6
    failed = next(r for r in recs if r.name.startswith("room__tensorf"))
    assert failed.status == "failed" and failed.error == "RuntimeError: out of memory"
    rows = aggregate(recs)
    assert [(r.render, r.encoding) for r in rows] == [("direct", "dense"), ("density", "dense"), ("density", "hash")]
    dd = rows[1]
    ates = [metrics[k]["ate_rmse_m"] * 100 for k in metrics if k[1:3] == ("dense", "density")]
    assert len(dd.runs) == 4
    assert dd.mean["ate_cm"] == pytest.approx(statistics.mean(ates))
    assert dd.std["ate_cm"] == pytest.approx(statistics.stdev(ates))
    assert dd.mean["psnr_db"] == pytest.approx(26.5)
    hash_row = rows[2]
    assert hash_row.mean["acc_cm"] is None and hash_row.std["ate_cm"] is None  # missing metric; single run
    assert hash_row.mean["model_mb"] == pytest.approx(0.5)


def test_best_marking_respects_direction(runs):
    rows = aggregate(collect_runs(runs[0]))
    best = {k: [(r.render, r.encoding) for r in rows if r.best[k]] for k in COLUMN_BY_KEY}
    assert best["ate_cm"] == [("direct", "dense")]  # lower is better
    assert best["psnr_db"] == [("density", "hash")]  # higher is better
    assert best["model_mb"] == [("density", "hash")]
    assert best["acc_cm"] == [("direct", "dense")]
    assert len(best["comp_pct"]) == 3  # tie: all marked


def test_table_formats(runs):
    rows = aggregate(collect_runs(runs[0]))
    md = to_markdown(rows)
    assert "| SDF(direct) | Dense | 1 | **1.00** |" in md  # acc 1 cm best
    assert "3.00 ± 1.83" in md  # dense/density ATE over 4 runs: mean 3, sample std 1.83
    assert "| SDF(density) | Sparse (hash) | 1 | – |" in md
    tex = to_latex(rows)
    assert r"\textbf{0.50}" in tex and r"3.00 $\pm$ 1.83" in tex and r"\begin{tabular}" in tex
    assert tex.count(r"\midrule") == 2  # header + one G change
    table = list(csv.DictReader(io.StringIO(to_csv(rows))))
    assert len(table) == 3
    h = table[2]
    assert (h["render"], h["encoding"], h["acc_cm_mean"], h["acc_cm_n"]) == ("density", "hash", "", "0")
    assert h["psnr_db_best"] == "1" and "psnr_db" in h["best"].split(";") and "model_mb" in h["best"].split(";")
    assert table[0]["ate_cm_best"] == "1" and table[1]["ate_cm_best"] == "0"


def test_build_report_writes_everything_and_values_match_metrics(runs, tmp_path):
    root, metrics = runs
    out = build_report(root)
    assert out == root / "report"
    for stem in ("leaderboard", "leaderboard_room", "leaderboard_thin"):
        for ext in ("md", "csv", "tex"):
            assert (out / f"{stem}.{ext}").stat().st_size > 0
    plots = out / "plots"
    for stem in ("tradeoff_memory_ate", "bars_ate_cm", "bars_psnr_db", "bars_model_mb", "ate_frames_room",
                 "ate_frames_thin"):
        for ext in ("png", "svg"):
            assert (plots / f"{stem}.{ext}").stat().st_size > 1000, stem
    assert (plots / "tradeoff_memory_ate.png").read_bytes()[:4] == b"\x89PNG"
    # per-scene table of a single-run group equals that run's metrics.json exactly
    room = {(r["render"], r["encoding"]): r for r in csv.DictReader(open(out / "leaderboard_room.csv"))}
    for (scene, enc, ren, seed), m in metrics.items():
        if scene == "room" and seed == 0 and enc == "hash":
            row = room[(ren, enc)]
            assert float(row["ate_cm_mean"]) == m["ate_rmse_m"] * 100
            assert float(row["psnr_db_mean"]) == m["psnr_process_db"]
            assert float(row["model_mb_mean"]) == m["model_size_mb"]
            assert float(row["track_ms_mean"]) == m["track_ms_per_frame"]
    runs_table = list(csv.DictReader(open(out / "runs.csv")))
    assert len(runs_table) == 8
    html = (out / "index.html").read_text()
    assert "<img src='plots/tradeoff_memory_ate.png'" in html and "plots/ate_frames_thin.png" in html
    assert "RuntimeError: out of memory" in html and "room__mlp__density__paper__s0" in html
    assert "http" not in html.replace("https://", "")  # no external resources
    # a second report elsewhere reads the same runs, never the report folder itself
    out2 = build_report(root, tmp_path / "elsewhere")
    assert (out2 / "leaderboard.csv").read_text() == (out / "leaderboard.csv").read_text()


def test_report_with_presets_and_no_complete_runs(tmp_path):
    root = tmp_path / "r"
    write_fake_run(root / "a", "dense", "density", "room", 0, preset="paper")
    write_fake_run(root / "b", "dense", "density", "room", 0, preset="quick")
    rows = aggregate(collect_runs(root))
    assert [r.preset for r in rows] == ["paper", "quick"]
    assert "| preset |" in to_markdown(rows)
    empty = tmp_path / "empty"
    empty.mkdir()
    out = build_report(empty)
    assert "| – |" in (out / "leaderboard.md").read_text()
    assert not any((out / "plots").glob("*.png")) if (out / "plots").exists() else True


def test_ate_over_frames_matches_rmse_of_alignment(tmp_path):
    d = write_fake_run(tmp_path / "run", "dense", "density", "room", 0, frames=30, noise=0.02)
    x, e = ate_over_frames(d)
    assert list(x) == list(range(30))
    from inrslam.eval.trajectory import ate
    from inrslam.io.trajectory import read_tum

    _, est = read_tum(d / "trajectory.txt")
    _, gt = read_tum(d / "trajectory_gt.txt")
    assert math.sqrt((e ** 2).mean()) == pytest.approx(ate(est, gt, "se3")["rmse"])
    assert ate_over_frames(tmp_path / "nothing") is None


def test_drift_column_averages_over_seeds_and_is_explained_where_missing(tmp_path):
    """The drift (growth of the unaligned position error, `drift_m_per_100`) is a column in cm per 100 frames: the
    mean and std over seeds, lower is better, and a run without ground truth names the evaluation's note."""
    from inrslam.bench.leaderboard import missing_notes

    root = tmp_path / "runs"
    drifts = [1.2, 1.6, 1.1]
    for seed, d in enumerate(drifts):
        write_fake_run(root / f"s7__dense__direct__accurate__s{seed}", "dense", "direct", "s7", seed, preset="accurate",
                       metrics=M(2.0 + seed / 10, 20.0, 46.0, drift_m_per_100=d / 100), frames=12)
    nogt = M(1.0, 20.0, 46.0, eval_notes=["trajectory_gt.txt missing: no ATE/RPE"])
    del nogt["ate_rmse_m"]
    write_fake_run(root / "s7__hash__direct__accurate__s0", "hash", "direct", "s7", 0, preset="accurate",
                   metrics=nogt, frames=12)
    rows = aggregate(collect_runs(root))
    dense = next(r for r in rows if r.encoding == "dense")
    assert dense.mean["drift_cm"] == pytest.approx(statistics.mean(drifts))
    assert dense.std["drift_cm"] == pytest.approx(statistics.stdev(drifts))
    assert dense.best["drift_cm"] and COLUMN_BY_KEY["drift_cm"].title in to_markdown(rows)
    notes = dict(missing_notes(rows))
    assert notes["trajectory_gt.txt missing: no ATE/RPE"] == ("ATE [cm], Drift [cm/100 fr]: "
                                                                   "SDF(direct) / Sparse (hash) [accurate]")


# files of a run written over with well-formed JSON / YAML of the wrong type (or bytes): the report reads them as empty
WRONG_TYPES = {
    "config_list": lambda d: (d / "config.yaml").write_text("- a\n- b\n"),
    "config_data_str": lambda d: (d / "config.yaml").write_text("data: foo\nfield: {encoding: dense}\n"),
    "bench_list": lambda d: (d / "bench.json").write_text("[1, 2]\n"),
    "info_dataset_str": lambda d: ((d / "config.yaml").unlink(),
                                   (d / "run_info.json").write_text('{"status": "complete", "dataset": "x"}')),
    "align_bogus": lambda d: (d / "config.yaml").write_text("data: {path: builtin:room}\neval: {align: bogus}\n"),
    "seed_str": lambda d: (d / "config.yaml").write_text("data: {path: builtin:room}\nseed: abc\n"),
    "error_bytes": lambda d: (d / "error.txt").write_bytes(b"\xff\xfe\x00bad"),
    "metric_bigint": lambda d: (d / "metrics.json").write_text('{"ate_rmse_m": 1' + "0" * 400 + "}"),
}


@pytest.mark.parametrize("status", ["[1]", '{"counts": [1, 2]}'])
def test_report_reads_files_of_the_wrong_type_as_empty(tmp_path, status):
    for k, (name, damage) in enumerate(WRONG_TYPES.items()):
        damage(write_fake_run(tmp_path / "runs" / name, "dense", "direct", "room", k))
    (tmp_path / "runs" / "sweep_status.json").write_text(status)
    out = build_report(tmp_path / "runs", tmp_path / "report")
    records = {r.name: r for r in collect_runs(tmp_path / "runs", exclude=out)}
    assert set(records) == set(WRONG_TYPES)
    assert records["seed_str"].seed is None and records["config_list"].seed is None
    assert records["metric_bigint"].value(COLUMN_BY_KEY["ate_cm"]) is None
    assert records["error_bytes"].error == "\ufffd\ufffd\x00bad"
    assert ate_over_frames(records["align_bogus"].run_dir) is None
    assert "metric_bigint" in (out / "index.html").read_text()


def test_latex_escapes_every_special_character_once():
    from inrslam.bench.leaderboard import _tex_escape

    assert _tex_escape("a\\b") == r"a\textbackslash{}b"  # its braces are not escaped again
    assert _tex_escape("x_1 & 50% #2 $y {z} ^ ~") == r"x\_1 \& 50\% \#2 \$y \{z\} \textasciicircum{} \textasciitilde{}"


def test_a_mean_leaving_out_runs_is_shown_with_its_count_and_never_best(tmp_path):
    """What the review found: a row that failed on the hard scene (or whose seed diverged to a null metric) was
    averaged over the rest and came out best; now its cells say k/n and the rows over all their runs rank."""
    root = tmp_path / "runs"
    for scene, ate in (("easy", 1.0), ("hard", 10.0)):
        write_fake_run(root / f"{scene}__dense__direct__paper__s0", "dense", "direct", scene, 0, metrics=M(ate, 25, 40),
                       preset="paper", frames=12)
    write_fake_run(root / "easy__hash__direct__paper__s0", "hash", "direct", "easy", 0, metrics=M(0.5, 26, 1),
                   preset="paper", frames=12)
    failed = write_fake_run(root / "hard__hash__direct__paper__s0", "hash", "direct", "hard", 0, preset="paper",
                            status="failed", frames=12)  # what a sweep leaves of a failed run: its config, the error
    (failed / "metrics.json").unlink()
    (failed / "error.txt").write_text("RuntimeError: out of memory\n")
    write_fake_run(root / "easy__tri__direct__paper__s0", "triplane", "direct", "easy", 0,
                   metrics=M(0.2, 20, 5, ate_rmse_m=None), preset="paper", frames=12)  # a diverged seed: null
    write_fake_run(root / "hard__tri__direct__paper__s0", "triplane", "direct", "hard", 0, metrics=M(3.0, 21, 5),
                   preset="paper", frames=12)
    rows = {r.encoding: r for r in aggregate(collect_runs(root))}
    dense, hash_row, tri = rows["dense"], rows["hash"], rows["triplane"]
    assert hash_row.total == 2 and hash_row.partial("ate_cm") and hash_row.partial("psnr_db")
    assert tri.total == 2 and tri.partial("ate_cm") and not tri.partial("psnr_db")
    assert not dense.partial("ate_cm") and dense.mean["ate_cm"] == pytest.approx(5.5)
    assert dense.best["ate_cm"] and not hash_row.best["ate_cm"] and not tri.best["ate_cm"]  # 0.5 and 3.0 left out
    assert tri.best["model_mb"] and not hash_row.best["model_mb"]  # hash's 1 MB is over 1 run of 2
    md = to_markdown(list(rows.values()))
    assert "0.50 (1/2)" in md and "3.00 (1/2)" in md and "**5.50 ± 6.36**" in md
    assert "(k/n): mean over k of the row's n runs" in md
    assert "(1/2)" in to_latex(list(rows.values()))
    table = {t["encoding"]: t for t in csv.DictReader(io.StringIO(to_csv(list(rows.values()))))}
    assert table["hash"]["runs"] == "1" and table["hash"]["runs_total"] == "2" and table["hash"]["ate_cm_best"] == "0"
    report = build_report(root, tmp_path / "report")
    assert "0.50 (1/2)" in (report / "leaderboard.md").read_text()
    assert "(1/2)" not in (report / "leaderboard_easy.md").read_text().split("Sparse (hash)")[1].splitlines()[0]


def test_report_names_each_runs_machine_and_warns_when_times_mix_machines(tmp_path):
    """runs.csv carries each run's CPU model and thread count (run_info.json); the page says so when the complete
    runs' Track / Map times come from more than one machine or thread count, and stays quiet when they do not."""
    root = tmp_path / "r"
    epyc, xeon = {"cpu": "AMD EPYC", "cores": 2}, {"cpu": "Intel Xeon Gold 5218R", "cores": 64}
    write_fake_run(root / "a", "dense", "density", "room", 0, machine=epyc, threads=2)
    write_fake_run(root / "b", "hash", "density", "room", 0, machine=epyc, threads=2)
    write_fake_run(root / "c", "hash", "density", "room", 1, machine=xeon, threads=2, status="running")
    records = collect_runs(root)
    assert [(r.cpu, r.threads) for r in records] == [("AMD EPYC", 2), ("AMD EPYC", 2), ("Intel Xeon Gold 5218R", 2)]
    assert machines_note(records) == ""  # the Xeon run is not complete: its times are in no table
    out = build_report(root)
    assert "Times mix machines" not in (out / "index.html").read_text()
    table = {r["name"]: r for r in csv.DictReader(open(out / "runs.csv"))}
    assert (table["c"]["cpu"], table["c"]["threads"]) == ("Intel Xeon Gold 5218R", "2")

    write_fake_run(root / "c", "hash", "density", "room", 1, machine=xeon, threads=2)  # now complete
    write_fake_run(root / "d", "mlp", "density", "room", 0, machine=epyc, threads=1)
    note = machines_note(collect_runs(root))
    assert note.startswith("Times mix machines or thread counts (AMD EPYC, 2 thread(s): 2 run(s); ")
    assert "AMD EPYC, 1 thread(s): 1 run(s)" in note and "Intel Xeon Gold 5218R, 2 thread(s): 1 run(s)" in note
    assert "Times mix machines or thread counts" in (build_report(root) / "index.html").read_text()


def test_runs_without_a_readable_machine_record_read_as_not_recorded(tmp_path):
    """Runs written before run_info.json recorded the machine, or with a damaged record, give '' / None."""
    root = tmp_path / "r"
    write_fake_run(root / "old", "dense", "density")
    write_fake_run(root / "odd", "hash", "density", machine={"cpu": 7}, threads=True)
    records = collect_runs(root)
    assert [(r.name, r.cpu, r.threads) for r in records] == [("odd", "", None), ("old", "", None)]
    assert machines_note(records) == ""  # both 'not recorded, ?': one group
