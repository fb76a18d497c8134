"""The Python API: `import inrslam` stays light, `inrslam.run` -> `load_run` is read-only, the example runs."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import inrslam
from inrslam.errors import RunError

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "run_inspect_compare.py"
TINY = ["data.max_frames=6", "output.tensorboard=false", "seed=2"]


def test_import_inrslam_does_not_load_torch_and_exposes_the_api():
    code = "import sys, inrslam; print('torch' in sys.modules, sorted(inrslam.__all__))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split(" ", 1)
    assert out[0] == "False"
    for name in ("run", "load_config", "evaluate", "sweep", "report", "load_run"):
        assert name in out[1] and callable(getattr(inrslam, name))
    with pytest.raises(AttributeError):
        inrslam.no_such_function  # noqa: B018


def digest(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    return inrslam.run(tmp_path_factory.mktemp("api") / "run", preset="quick", overrides=TINY)


def test_run_returns_the_run_read_back(finished):
    r = finished
    assert r.est.shape == (6, 4, 4) and r.gt.shape == (6, 4, 4) and r.timestamps.shape == (6,)
    assert r.keyframes == json.loads((r.root / "keyframes.json").read_text())["keyframes"]
    assert r.metrics["frames"] == 6 and r.config.data.max_frames == 6
    assert np.allclose(r.est[0], r.gt[0], atol=1e-5)  # frame 0 starts at its GT pose
    assert r.mesh() is not None and len(r.mesh().vertices) > 0
    from PIL import Image

    frames = r.metrics["heldout_frames"]
    assert frames and sorted(p.name for p in (r.root / "renders").iterdir()) == [f"frame_{i:06d}.png" for i in frames]
    w, h = Image.open(r.root / "renders" / f"frame_{frames[0]:06d}.png").size
    assert (w, h) == (4 * r.intrinsics.width, r.intrinsics.height)
    assert Image.open(r.root / "trajectory.png").size[0] > 100  # the top-down trajectory picture
    from inrslam.eval.mesh_thumbnail import BACKGROUND, THUMBNAIL_SIZE

    mesh_png = np.asarray(Image.open(r.root / "mesh.png").convert("RGB"))  # the final mesh, drawn
    assert mesh_png.shape == (THUMBNAIL_SIZE[1], THUMBNAIL_SIZE[0], 3)
    assert (mesh_png != BACKGROUND).any(axis=2).mean() > 0.05


def test_load_run_is_read_only_and_renders_the_map(finished):
    before = digest(finished.root)
    r = inrslam.load_run(finished.root)
    rgb, depth = r.render(r.est[0])
    assert digest(finished.root) == before  # not a byte, not a timestamp changed (a resume would cut log.jsonl)
    intr = r.intrinsics
    assert rgb.shape == (intr.height, intr.width, 3) and depth.shape == (intr.height, intr.width)
    assert 0.0 <= rgb.min() and rgb.max() <= 1.0
    # the rendered depth of a trained view agrees with the sensor's where it measured
    from inrslam.datasets import open_dataset

    gt_depth = open_dataset(r.config.data)[0].depth
    valid = gt_depth > 0
    assert np.median(np.abs(depth[valid] - gt_depth[valid])) < 0.1


def test_load_run_of_a_folder_without_a_run_names_it(tmp_path):
    with pytest.raises(RunError, match="not a run directory"):
        inrslam.load_run(tmp_path)


def test_the_example_runs(tmp_path):
    res = subprocess.run([sys.executable, str(EXAMPLE), "--out", str(tmp_path), "--frames", "3"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-3000:]
    lines = res.stdout.splitlines()
    assert any(line.startswith("dense ") for line in lines) and any(line.startswith("hash ") for line in lines)
    assert (tmp_path / "dense" / "metrics.json").is_file() and (tmp_path / "hash" / "metrics.json").is_file()


@pytest.mark.parametrize("text", ["[0, 5]", '{"keyframes": "0,5"}', '{"keyframes": [0, "x", true, 5]}'])
def test_load_run_reads_a_written_over_keyframes_json(finished, tmp_path, text):
    copy = tmp_path / "run"
    shutil.copytree(finished.root, copy)
    (copy / "keyframes.json").write_text(text)
    assert inrslam.load_run(copy).keyframes == ([0, 5] if text.startswith('{"keyframes": [') else [])


@pytest.mark.parametrize("name", ["run_info.json", "metrics.json"])
def test_load_run_of_a_damaged_record_names_the_file(finished, tmp_path, name):
    copy = tmp_path / "run"
    shutil.copytree(finished.root, copy)
    (copy / name).write_text((copy / name).read_text()[:40])  # cut short
    with pytest.raises(RunError, match=rf"{name}: not a JSON object \(truncated or edited\?\)"):
        inrslam.load_run(copy)


def test_a_damaged_mesh_is_one_error_naming_it(finished, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(finished.root, copy)
    if not (copy / "mesh.ply").is_file():
        pytest.skip("the shared finished run has no mesh")
    (copy / "mesh.ply").write_bytes((copy / "mesh.ply").read_bytes()[:1000])  # cut short
    with pytest.raises(RunError, match=r"mesh\.ply: unreadable mesh \(") as e:
        inrslam.load_run(copy).mesh()
    assert "\n" not in str(e.value)
    assert inrslam.load_run(finished.root).mesh().vertices.shape[1] == 3  # the intact one reads


def test_load_run_of_a_record_without_the_camera_names_the_key(finished, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(finished.root, copy)
    info = json.loads((copy / "run_info.json").read_text())
    del info["bounds"]
    info["intrinsics"] = {"fx": 50}
    (copy / "run_info.json").write_text(json.dumps(info))
    r = inrslam.load_run(copy)
    with pytest.raises(RunError, match=r"run_info\.json: 'intrinsics' is \{'fx': 50\} \(expected fx, fy, cx, cy"):
        _ = r.intrinsics
    with pytest.raises(RunError, match=r"run_info\.json: no 'bounds' \(expected a run directory written by"):
        _ = r.model
