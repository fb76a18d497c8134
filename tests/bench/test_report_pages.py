"""The report page (index.html): each run's pictures with links to its folder, '–' cells and pictures that say why
they are missing, and the page in a real browser."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import yaml
from headless_browser import CHROMIUM, load_page
from PIL import Image

from inrslam.bench.leaderboard import COLUMN_BY_KEY, aggregate, collect_runs, read_run, to_html, to_markdown
from inrslam.bench.report import RENDERS_SHOWN, build_report, run_pictures
from inrslam.bench.testing import write_fake_run


def png(path: Path, color, size=(40, 30)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((size[1], size[0], 3), color, np.uint8)).save(path)


def set_config(run: Path, **sections) -> None:
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    cfg.update(sections)
    (run / "config.yaml").write_text(yaml.safe_dump(cfg))


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """full: every picture (3 renders); off: output.renders=false; nogt: no ground truth, mesh.enabled=false, no
    Acc (its evaluation note says why); broken: failed before writing anything."""
    root = tmp_path_factory.mktemp("report") / "runs"
    full = write_fake_run(root / "full", "dense", "density")
    png(full / "trajectory.png", (200, 30, 30))
    png(full / "mesh.png", (30, 200, 30))
    for frame in (3, 8, 13):
        png(full / "renders" / f"frame_{frame:06d}.png", (30, 30, 200), size=(160, 30))
    (full / "mesh.ply").write_text("ply\n")
    off = write_fake_run(root / "off", "hash", "density")
    set_config(off, output={"renders": False})
    (off / "mesh.ply").write_text("ply\n")
    nogt = write_fake_run(root / "nogt", "dense", "direct", metrics={
        "ate_rmse_m": None, "eval_notes": ["trajectory_gt.txt missing: no ATE/RPE", "GT mesh not given: no Acc/Comp"],
        "model_size_mb": 1.0})
    (nogt / "trajectory_gt.txt").unlink()
    set_config(nogt, mesh={"enabled": False})
    broken = root / "broken"
    broken.mkdir()
    (broken / "error.txt").write_text("RuntimeError: out of memory\n")
    return root


def test_run_pictures_or_the_reason_each_is_missing(runs):
    full = run_pictures(read_run(runs / "full"))
    assert full.trajectory == runs / "full" / "trajectory.png" and full.mesh == runs / "full" / "mesh.png"
    assert full.renders == [runs / "full" / "renders" / f"frame_{f:06d}.png" for f in (3, 8)][:RENDERS_SHOWN]
    off = run_pictures(read_run(runs / "off"))
    assert off.trajectory == off.mesh == off.renders == "output.renders=false"
    nogt = run_pictures(read_run(runs / "nogt"))
    assert nogt.trajectory == "no ground truth (trajectory_gt.txt)" and nogt.mesh == "mesh.enabled=false"
    assert nogt.renders.startswith("none (made by an older inrslam")
    broken = run_pictures(read_run(runs / "broken"))
    assert broken.trajectory == broken.mesh == broken.renders == "run failed"


def test_missing_cells_say_why(runs):
    rows = aggregate(collect_runs(runs))
    nogt = next(r for r in rows if r.render == "direct")
    assert nogt.why["ate_cm"] == "trajectory_gt.txt missing: no ATE/RPE"
    assert nogt.why["acc_cm"] == nogt.why["comp_pct"] == "GT mesh not given: no Acc/Comp"
    assert nogt.why["psnr_db"] == "metrics.json has no psnr_process_db" and nogt.why["model_mb"] == ""
    page = to_html(rows)
    notes = page[page.index("<ol class='notes'>"):].split("<li>")[1:]
    k = next(i + 1 for i, n in enumerate(notes) if n.startswith("–: GT mesh not given: no Acc/Comp"))
    assert f"title='GT mesh not given: no Acc/Comp'>–<sup>{k}</sup>" in page  # the cell points at its note
    assert "(Acc [cm], Comp [cm], Comp [%]: SDF(direct) / Dense)" in notes[k - 1]
    md = to_markdown(rows)
    assert "- –: trajectory_gt.txt missing: no ATE/RPE (ATE [cm], Drift [cm/100 fr]: SDF(direct) / Dense)" in md
    assert COLUMN_BY_KEY["ate_cm"].title in md


@pytest.fixture(scope="module")
def report(runs):
    return build_report(runs)


def test_index_html_shows_each_runs_pictures_and_links_its_folder(report):
    page = (report / "index.html").read_text()
    runs_part = page[page.index("<h2 id='runs'>"):]
    assert "<a href='../full/'>full</a>" in runs_part
    for name in ("trajectory.png", "mesh.png", "renders/frame_000003.png", "renders/frame_000008.png"):
        assert f"src='../full/{name}'" in runs_part and f"<a href='../full/{name}'>" in runs_part
    assert "frame_000013" not in runs_part  # the first RENDERS_SHOWN only
    assert runs_part.count("– output.renders=false") == 3 and "– no ground truth (trajectory_gt.txt)" in runs_part
    assert "– mesh.enabled=false" in runs_part and runs_part.count("– run failed") == 3
    assert "http" not in page.replace("https://", "")  # nothing outside the folders


@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium (apt-get install -y chromium) for the "
                                             "headless page test")
def test_the_report_renders_in_a_headless_browser(report):
    """Every picture loads (the relative links hold), the page draws something and logs no error."""
    loaded = ("(document.querySelectorAll('img').forEach(i => i.loading = 'eager'), document.images.length > 0 && "
              "Array.from(document.images).every(i => i.complete && i.naturalWidth > 0))")
    page = load_page((report / "index.html").as_uri(), loaded, size=(1100, 1400), timeout=30.0)
    assert page.ready, "some picture did not load: " + page.text[:300]
    assert not page.errors, page.errors
    assert "inrslam leaderboard" in page.text and "output.renders=false" in page.text
    img = np.asarray(Image.open(io.BytesIO(page.png)).convert("RGB"))
    assert img.shape[:2] == (1400, 1100) and len(np.unique(img.reshape(-1, 3), axis=0)) > 50  # not blank
