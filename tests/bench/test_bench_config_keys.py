"""Sweeps and the per-variant config sections: an override must apply to some run it reaches; run directories
written with the old flat keys are compared (and resumed) under the new names."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from inrslam.bench.spec import SceneSpec, SweepSpec, expand, load_spec, validate_runs
from inrslam.bench.sweep import config_differences, run_sweep
from inrslam.config.loader import load_config
from inrslam.errors import ConfigError, InrslamError

FAKE = "inrslam.bench.testing:fake_run"
OLD_PAPER = Path(__file__).parents[1] / "config" / "old_configs" / "paper_bb6d453.yaml"  # written at bb6d453


def _validate(spec: dict) -> dict:
    sp = load_spec(spec)
    return validate_runs(expand(sp), sp.source, check_paths=False, spec=sp)


def test_sweep_override_for_some_of_the_renders_applies_to_those_runs():
    spec = {"encodings": ["dense"], "renders": ["density", "neus"], "scenes": ["builtin:room"], "presets": ["quick"],
            "overrides": {"render.density.beta": 5, "render": {"neus_fd_eps": 0.01}}}
    cfgs = _validate(spec)
    density, neus = (cfgs[f"room__dense__{r}__quick__s0"] for r in ("density", "neus"))
    assert density.render.density.beta == 5.0 and neus.render.neus.fd_eps == 0.01
    assert neus.render.density.beta == 5.0  # unused by the neus run, as a preset's key would be


def test_sweep_override_that_applies_to_no_run_is_an_error():
    spec = {"encodings": ["dense", "hash"], "renders": ["density", "direct"], "scenes": ["builtin:room"],
            "presets": ["quick"], "overrides": ["render.neus_fd_eps=0.01"]}
    with pytest.raises(ConfigError, match=r"'render.neus.fd_eps' \(from <dict>: overrides, set as 'render.neus_fd_eps'"
                                          r"\) applies to render.name=neus, but no run of the sweep selects it "
                                          r"\(render.name is 'density'; render.name is 'direct'\)"):
        _validate(spec)
    scene = {"name": "room", "path": "builtin:room", "overrides": {"data.tum.max_dt_depth": 0.1}}
    with pytest.raises(ConfigError, match=r"'data.tum.max_dt_depth' \(from <dict>: scene 'room' overrides\) applies "
                                          r"to data.dataset=tum, but no run .*data.path is 'builtin:room'"):
        _validate({**spec, "overrides": {}, "scenes": [scene]})


def test_sweep_resumes_run_directories_written_with_old_keys(tmp_path):
    spec = {"encodings": ["dense"], "renders": ["density"], "scenes": ["builtin:room"], "presets": ["paper"]}
    out = tmp_path / "sweep"
    run_sweep(spec, out, run_fn=FAKE, quiet=True, report=False)
    run_dir = out / "room__dense__density__paper__s0"
    old = OLD_PAPER.read_text()
    assert "  beta: 10.0\n" in old and "keyframe_variant: false" in old
    (run_dir / "config.yaml").write_text(old)  # the same config, spelled the old way
    assert config_differences(run_dir, load_config(preset="paper")) == []
    assert run_sweep(spec, out, run_fn=FAKE, quiet=True, report=False).count("skipped") == 1
    # an old key with another value is a difference, reported under its new name
    (run_dir / "config.yaml").write_text(old.replace("  beta: 10.0\n", "  beta: 5.0\n"))
    with pytest.raises(ConfigError, match=r"different config \(render.density.beta: 5.0 -> 10.0\)"):
        run_sweep(spec, out, run_fn=FAKE, quiet=True, report=False)


def test_an_unknown_executor_fails_before_a_dry_run_says_anything(tmp_path):
    spec = {"encodings": ["dense"], "renders": ["density"], "scenes": ["builtin:room"], "presets": ["paper"]}
    with pytest.raises(InrslamError, match=r"unknown executor 'foo' \(choices: local, ray, slurm\)"):
        run_sweep(spec, tmp_path / "sweep", executor="foo", dry_run=True, quiet=True)
    assert not (tmp_path / "sweep").exists()


def test_sweep_spec_yaml_of_a_spec_made_in_code_runs_the_same_sweep(tmp_path):
    sp = SweepSpec(encodings=["dense"], renders=["density", "direct"], presets=["quick"], seeds=[0, 2], max_frames=5,
                   scenes=[SceneSpec("r", "builtin:room", {"data": {"stride": 2}})])
    out = tmp_path / "sweep"
    run_sweep(sp, out, run_fn=FAKE, quiet=True, report=False)
    again = load_spec(out / "sweep_spec.yaml")
    assert [r.to_dict() for r in expand(again)] == [r.to_dict() for r in expand(sp)]


def test_sweep_spec_yaml_of_a_shipped_spec_changed_in_code_is_the_changed_sweep(tmp_path):
    sp = dataclasses.replace(load_spec("tiny"), encodings=["dense"], renders=["density"], seeds=[7])
    out = tmp_path / "sweep"
    run_sweep(sp, out, run_fn=FAKE, quiet=True, report=False)
    again = [r.name for r in expand(load_spec(out / "sweep_spec.yaml"))]
    assert again == [r.name for r in expand(sp)] and len(again) == 1 and again[0].endswith("__s7")
