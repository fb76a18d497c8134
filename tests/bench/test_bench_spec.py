"""Sweep specs: strict validation, expansion, names, environment variables, shipped specs."""

from __future__ import annotations

import pytest
import yaml

from inrslam.bench.spec import SPEC_DIR, expand, expand_env, load_spec, resolve_config, run_name, sanitize
from inrslam.errors import ConfigError

BASE = {"encodings": ["dense", "hash+tri"], "renders": ["density", "direct", "neus"], "scenes": ["builtin:room"]}


def write(tmp_path, data, name="spec.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


def test_unknown_top_level_key_names_key_file_and_closest(tmp_path):
    p = write(tmp_path, {**BASE, "encoding": ["dense"]})
    with pytest.raises(ConfigError) as e:
        load_spec(p)
    msg = str(e.value)
    assert "'encoding'" in msg and str(p) in msg and "did you mean 'encodings'" in msg


def test_unknown_scene_key_and_missing_path(tmp_path):
    p = write(tmp_path, {**BASE, "scenes": [{"name": "a", "pth": "builtin:room"}]})
    with pytest.raises(ConfigError, match=r"'pth'.*scenes\[0\].*did you mean 'path'"):
        load_spec(p)
    with pytest.raises(ConfigError, match="needs a 'path'"):
        load_spec({**BASE, "scenes": [{"name": "a"}]})


@pytest.mark.parametrize("bad, match", [
    ({"encodings": []}, "non-empty list"),
    ({"seeds": ["zero"]}, "integers"),
    ({"max_frames": -3}, "non-negative"),
    ({"renders": ["direct", "direct"]}, "twice"),
    ({"overrides": 3}, "mapping or a list"),
])
def test_bad_values(bad, match):
    with pytest.raises(ConfigError, match=match):
        load_spec({**BASE, **bad})


def test_missing_required_list():
    data = dict(BASE)
    del data["renders"]
    with pytest.raises(ConfigError, match="'renders'"):
        load_spec(data)


def test_expansion_count_order_and_names():
    spec = {**BASE, "scenes": ["builtin:room", "builtin:thin"], "presets": ["quick", "paper"], "seeds": [0, 1]}
    runs = expand(spec)
    assert len(runs) == 2 * 2 * 3 * 2 * 2
    names = [r.name for r in runs]
    assert len(set(names)) == len(names)
    assert names[0] == "room__dense__density__quick__s0"
    assert "thin__hash-tri__neus__paper__s1" in names
    r = next(r for r in runs if r.name == "thin__hash-tri__neus__paper__s1")
    assert (r.scene, r.encoding, r.render, r.preset, r.seed) == ("thin", "hash+tri", "neus", "paper", 1)
    assert r.overrides == {"data": {"path": "builtin:thin"}, "field": {"encoding": "hash+tri"},
                           "render": {"name": "neus"}, "seed": 1}
    assert expand(spec) == runs  # stable


def test_sanitize_and_run_name():
    assert sanitize("hash+tri") == "hash-tri"
    assert sanitize("a b/c") == "a-b-c"
    assert run_name("room0", "dense+tri", "density", "paper", 3) == "room0__dense-tri__density__paper__s3"
    assert sanitize(".hidden") == "hidden" and sanitize("..") == "x"  # run folders are never hidden


def test_a_scene_given_as_the_current_folder_is_named_after_it(tmp_path, monkeypatch):
    (tmp_path / "room0").mkdir()
    monkeypatch.chdir(tmp_path / "room0")
    for scene in (".", "./"):
        spec = {**BASE, "encodings": ["dense"], "renders": ["density"], "scenes": [scene]}
        assert [(r.scene, r.name.split("__")[0]) for r in expand(spec)] == [("room0", "room0")]


def test_overrides_merge_order_dotted_keys_and_max_frames():
    spec = {**BASE, "encodings": ["dense"], "renders": ["density"], "max_frames": 7,
            "overrides": {"slam.track_iters": 3, "slam": {"map_iters": 2}, "data": {"stride": 2}},
            "scenes": [{"name": "r", "path": "builtin:room", "overrides": {"data": {"max_frames": 5}}}]}
    (run,) = expand(spec)
    assert run.name == "r__dense__density__paper__s0"
    assert run.overrides["slam"] == {"track_iters": 3, "map_iters": 2}
    assert run.overrides["data"] == {"stride": 2, "max_frames": 5, "path": "builtin:room"}  # scene beats max_frames


def test_list_overrides_use_the_config_parser():
    (run,) = expand({**BASE, "encodings": ["dense"], "renders": ["density"], "overrides": ["slam.track_iters=4"]})
    assert run.overrides["slam"] == {"track_iters": 4}


def test_env_expansion_in_scene_paths(tmp_path, monkeypatch):
    monkeypatch.setenv("DATA_ROOT", str(tmp_path))
    monkeypatch.delenv("NOPE_ROOT", raising=False)
    assert expand_env("${DATA_ROOT}/Replica/room0") == f"{tmp_path}/Replica/room0"
    assert expand_env("$DATA_ROOT/x") == f"{tmp_path}/x"
    assert expand_env("${NOPE_ROOT:-data}/x") == "data/x"
    with pytest.raises(ConfigError, match="NOPE_ROOT"):
        expand_env("${NOPE_ROOT}/x", where="spec.yaml")
    spec = load_spec({**BASE, "scenes": ["${DATA_ROOT}/Replica/room0", {"name": "k", "path": "$DATA_ROOT/ck"}]})
    assert [s.name for s in spec.scenes] == ["room0", "k"]
    assert spec.scenes[0].path == str(tmp_path / "Replica" / "room0")


def test_relative_scene_paths_are_made_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    spec = load_spec({**BASE, "scenes": ["data/Replica/office3/"]})
    assert spec.scenes[0].path == str(tmp_path / "data" / "Replica" / "office3")
    assert spec.scenes[0].name == "office3"


def test_duplicate_scene_names_rejected():
    with pytest.raises(ConfigError, match="room0"):
        load_spec({**BASE, "scenes": ["/a/room0", "/b/room0"]})


def test_shipped_specs_load_and_use_registered_names():
    from inrslam.fields.registry import ENCODINGS
    from inrslam.rendering import RENDERERS

    counts = {"tiny": 4, "builtin_small": 7 * 2 * 3, "room_fxg": 5 * 2, "room_fxg_gt": 5 * 2, "builtin_fxg": 5 * 2 * 2,
              "7scenes_fxg": 5 * 2, "7scenes_accurate_seeds": 10, "replica": 5 * 3 * 8, "neuralrgbd": 6 * 3 * 7,
              "presets_builtin": 2 * 1 * 4 * 3}
    assert sorted(p.stem for p in SPEC_DIR.glob("*.yaml")) == sorted(counts)
    for name, n in counts.items():
        spec = load_spec(name)
        assert len(expand(spec)) == n, name
        assert all(e in ENCODINGS for e in spec.encodings), name
        assert all(g in RENDERERS for g in spec.renders), name
    assert load_spec("builtin_small").encodings == ENCODINGS.names()  # all 7 encodings
    first = expand(load_spec("presets_builtin"))[:3]  # room x dense x direct x {paper, accurate, gicp}
    inits = {r.preset: resolve_config(r).slam.init.value for r in first}
    assert inits == {"paper": "const_velocity", "accurate": "gicp", "gicp": "gicp"}
    gt = [resolve_config(r) for r in expand(load_spec("room_fxg_gt"))]
    assert {c.slam.poses for c in gt} == {"gt"} and {(c.field.encoding, c.render.name) for c in gt} == {
        (resolve_config(r).field.encoding, resolve_config(r).render.name) for r in expand(load_spec("room_fxg"))}
    tiny = load_spec("tiny")
    assert tiny.presets == ["quick"] and len(tiny.scenes) == 1 and tiny.scenes[0].path.startswith("builtin:")


def test_config_typo_fails_before_anything_runs(tmp_path):
    from inrslam.bench.sweep import run_sweep

    spec = write(tmp_path, {**BASE, "overrides": {"slam": {"track_iter": 3}}})
    with pytest.raises(ConfigError, match="track_iter"):
        run_sweep(spec, tmp_path / "out", run_fn="inrslam.bench.testing:fake_run", quiet=True)
    assert not (tmp_path / "out").exists()
    with pytest.raises(ConfigError, match="dens"):
        run_sweep({**BASE, "encodings": ["dens"]}, tmp_path / "out", quiet=True)
    with pytest.raises(ConfigError, match="does not exist"):
        run_sweep({**BASE, "scenes": [str(tmp_path / "missing")]}, tmp_path / "out", quiet=True)
    with pytest.raises(ConfigError, match="built-in scene"):
        run_sweep({**BASE, "scenes": ["builtin:rooom"]}, tmp_path / "out", quiet=True)


def test_pose_and_camera_files_in_overrides_are_made_absolute_and_checked(tmp_path, monkeypatch):
    """`slam.poses` / `eval.virtual_cameras` in a sweep's overrides resolve like `inrslam run`'s (from the current
    directory, written absolute into each run's config) and a missing file fails before anything runs."""
    from inrslam.bench.spec import validate_runs

    monkeypatch.chdir(tmp_path)
    (tmp_path / "poses.txt").write_text("0 0 0 0 0 0 0 1\n")
    runs = expand({**BASE, "overrides": ["slam.poses=poses.txt", "eval.virtual_cameras=poses.txt"]})
    cfg = resolve_config(runs[0])
    assert cfg.slam.poses == str(tmp_path / "poses.txt") == cfg.eval.virtual_cameras
    validate_runs(runs)
    assert resolve_config(expand({**BASE, "overrides": {"slam": {"poses": "gt"}}})[0]).slam.poses == "gt"
    missing = expand({**BASE, "overrides": ["slam.poses=nonexist_poses.txt"]})
    with pytest.raises(ConfigError, match=r"slam\.poses: file .*nonexist_poses\.txt does not exist"):
        validate_runs(missing)


def test_spec_override_errors_name_the_spec_and_its_overrides(tmp_path):
    from inrslam.bench.spec import validate_runs

    spec = write(tmp_path, {**BASE, "overrides": {"slam": {"track_itrs": 3}}})
    with pytest.raises(ConfigError, match=r"unknown config key 'slam\.track_itrs' in sweep overrides"):
        validate_runs(expand(spec), str(spec))
    with pytest.raises(ConfigError, match=r"spec\.yaml: overrides: override 'slam\.track_iters': expected KEY=VALUE"):
        load_spec(write(tmp_path, {**BASE, "overrides": ["slam.track_iters"]}))
