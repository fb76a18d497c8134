"""Per-variant config sections (`render.neus.*`, `data.tum.*`, ...): old flat keys as aliases, old run config.yaml
files, and keys of a variant that is not selected."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from inrslam.config import loader
from inrslam.config.aliases import ALIASES
from inrslam.config.loader import dump_config, load_config
from inrslam.errors import ConfigError

OLD = Path(__file__).parent / "old_configs"  # config.yaml files written before the sections (commit bb6d453)

# one case per alias family: (old overrides, the same with the new keys, the selecting overrides)
FAMILIES = {
    "density": (["render.beta=5", "render.learn_beta=true"],
                ["render.density.beta=5", "render.density.learn_beta=true"], []),
    "neus": (["render.neus_init_log_inv_s=4", "render.neus_learn_s=false", "render.neus_normals=finite_difference",
              "render.neus_fd_eps=0.01", "render.neus_anneal_end=0.2"],
             ["render.neus.init_log_inv_s=4", "render.neus.learn_s=false", "render.neus.normals=finite_difference",
              "render.neus.fd_eps=0.01", "render.neus.anneal_end=0.2"], ["render.name=neus"]),
    "volsdf": (["render.volsdf_beta_init=0.02", "render.volsdf_learn_beta=false", "render.volsdf_beta_min=0.001"],
               ["render.volsdf.beta_init=0.02", "render.volsdf.learn_beta=false", "render.volsdf.beta_min=0.001"],
               ["render.name=volsdf"]),
    "nerf": (["render.nerf_activation=relu"], ["render.nerf.activation=relu"], ["render.name=nerf"]),
    "mlp": (["field.mlp_width=64", "field.mlp_depth=3"], ["field.mlp.width=64", "field.mlp.depth=3"],
            ["field.encoding=mlp"]),
    "tum": (["data.tum_max_dt_depth=0.05", "data.tum_max_dt_pose=0.04"],
            ["data.tum.max_dt_depth=0.05", "data.tum.max_dt_pose=0.04"], ["data.path=/d", "data.dataset=tum"]),
    "neuralrgbd": (["data.neuralrgbd_depth_dir=depth"], ["data.neuralrgbd.depth_dir=depth"],
                   ["data.path=/d", "data.dataset=neuralrgbd"]),
    "7scenes": (["data.sequence=seq-02"], ["data.sevenscenes.sequence=seq-02"],
                ["data.path=/d", "data.dataset=7scenes"]),
    "keyframe": (["slam.keyframe_variant=true"], ["slam.keyframe_fraction=0.005"], []),
}


def test_every_alias_has_a_family_case():
    old_keys = {item.split("=")[0] for old, _, _ in FAMILIES.values() for item in old}
    assert old_keys == {a.old for a in ALIASES}


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_old_keys_load_to_the_same_config_as_the_new_ones(family, tmp_path):
    old, new, select = FAMILIES[family]
    expected = load_config(overrides=select + new)
    assert expected != load_config(overrides=select)  # the new keys do change something
    assert load_config(overrides=select + old) == expected
    # in a --config file, and in a file it inherits from
    base = tmp_path / "base.yaml"
    base.write_text(yaml.safe_dump(loader.parse_overrides(old)))
    child = tmp_path / "child.yaml"
    child.write_text("inherit_from: base.yaml\n")
    assert load_config(child, overrides=select) == expected


def test_old_keys_in_a_preset(tmp_path, monkeypatch):
    monkeypatch.setattr(loader, "PRESET_DIR", tmp_path)
    (tmp_path / "old.yaml").write_text("render:\n  name: neus\n  neus_fd_eps: 0.02\n  beta: 4\n")
    cfg = load_config(preset="old")
    assert cfg.render.neus.fd_eps == 0.02 and cfg.render.density.beta == 4.0


@pytest.mark.parametrize("name", ["paper_bb6d453", "neus_tum_bb6d453"])
def test_old_run_config_yaml_loads_to_an_equal_config(name):
    path = OLD / f"{name}.yaml"
    if name == "paper_bb6d453":
        expected = load_config(preset="paper")
    else:
        expected = load_config(preset="paper", overrides=[
            "render.name=neus", "render.neus.fd_eps=0.01", "render.neus.normals=finite_difference",
            "render.neus.learn_s=false", "data.path=/data/tum/fr1_desk", "data.dataset=tum",
            "data.tum.max_dt_depth=0.03", "slam.keyframe_fraction=0.005", "field.encoding=mlp",
            "field.mlp.width=128"])
    assert load_config(path, preset=None) == expected  # as `inrslam run --resume` reads it
    assert load_config(path, preset=None, check_variants=False) == expected
    assert load_config(path) == expected  # `inrslam run --config <old run>/config.yaml` (on the paper preset)
    # the new dump writes the nested layout, which loads back to the same config
    text = dump_config(expected)
    assert "neus_fd_eps" not in text and "keyframe_variant" not in text
    assert yaml.safe_load(text)["render"]["neus"]["fd_eps"] == expected.render.neus.fd_eps


@pytest.mark.parametrize("overrides, key, variant, selected", [
    (["render.name=neus", "render.density.beta=5"], "render.density.beta", "render.name=density",
     "render.name is 'neus'"),
    (["render.name=neus", "render.beta=5"], "render.density.beta", "render.name=density", "render.name is 'neus'"),
    (["render.neus_fd_eps=0.01"], "render.neus.fd_eps", "render.name=neus", "render.name is 'density'"),
    (["render.name=direct", "render.volsdf.beta_min=0.001"], "render.volsdf.beta_min", "render.name=volsdf",
     "render.name is 'direct'"),
    (["render.nerf.activation=relu"], "render.nerf.activation", "render.name=nerf", "render.name is 'density'"),
    (["field.mlp.width=64"], "field.mlp.width", "field.encoding=mlp", "field.encoding is 'dense'"),
    (["data.tum.max_dt_depth=0.1"], "data.tum.max_dt_depth", "data.dataset=tum", "data.path is 'builtin:room'"),
    (["data.path=/d", "data.dataset=replica", "data.sequence=seq-01"], "data.sevenscenes.sequence",
     "data.dataset=7scenes", "data.dataset is 'replica'"),
    (["data.path=/d", "data.builtin.frames=50"], "data.builtin.frames", "data.path=builtin:NAME",
     "data.path is '/d'"),
])
def test_a_user_key_of_another_variant_is_an_error(overrides, key, variant, selected):
    with pytest.raises(ConfigError) as e:
        load_config(overrides=overrides)
    msg = str(e.value)
    assert f"config key {key!r} (from command-line overrides" in msg
    assert f"applies to {variant}, but {selected}" in msg


def test_other_variant_key_in_a_config_file_names_the_file_and_the_old_spelling(tmp_path):
    f = tmp_path / "mine.yaml"
    f.write_text("render:\n  beta: 5\n")
    with pytest.raises(ConfigError, match=r"'render.density.beta' \(from .*mine.yaml, set as 'render.beta'\) "
                                          r"applies to render.name=density, but render.name is 'neus'"):
        load_config(f, overrides=["render.name=neus"])  # as `--config mine.yaml --render neus`
    assert load_config(f, overrides=["render.name=density"]).render.density.beta == 5.0


def test_unknown_reader_is_not_checked_before_the_folder_is_read():
    cfg = load_config(overrides=["data.path=/d", "data.tum.max_dt_depth=0.1"])  # data.dataset auto
    assert cfg.data.tum.max_dt_depth == 0.1


def test_other_variant_keys_from_a_preset_are_unused_not_errors(tmp_path, monkeypatch):
    monkeypatch.setattr(loader, "PRESET_DIR", tmp_path)
    (tmp_path / "sharp.yaml").write_text("render:\n  density:\n    beta: 20\n  neus:\n    fd_eps: 0.01\n")
    cfg = load_config(preset="sharp", overrides=["render.name=neus"])  # --preset sharp --render neus
    assert cfg.render.name == "neus" and cfg.render.density.beta == 20.0 and cfg.render.neus.fd_eps == 0.01
    assert load_config(preset="sharp", overrides=["render.name=direct"]).render.density.beta == 20.0
    # also through a user file inheriting from the preset
    f = tmp_path / "user" / "mine.yaml"
    f.parent.mkdir()
    f.write_text("inherit_from: preset:sharp\nrender:\n  name: volsdf\n")
    assert load_config(f, preset=None).render.name == "volsdf"
    # the user may set a key to the value it has anyway (a run's full config.yaml does)
    assert load_config(preset="sharp", overrides=["render.name=neus", "render.density.beta=20"]) == cfg
    with pytest.raises(ConfigError, match="render.density.beta"):
        load_config(preset="sharp", overrides=["render.name=neus", "render.density.beta=21"])


def test_faithful_layer_and_the_resume_switch():
    cfg = load_config(overrides=["faithful=true", "render.name=neus"])
    assert cfg.render.faithful and cfg.render.name == "neus"
    # check_variants=False (resume of a run's own config.yaml): the key is kept, unused
    assert load_config(overrides=["render.name=neus", "render.beta=5"], check_variants=False).render.density.beta == 5


def test_old_and_new_key_in_one_layer_is_an_error(tmp_path):
    with pytest.raises(ConfigError, match=r"'render.neus_fd_eps' and 'render.neus.fd_eps' in command-line overrides"):
        load_config(overrides=["render.name=neus", "render.neus_fd_eps=0.01", "render.neus.fd_eps=0.02"])
    f = tmp_path / "both.yaml"
    f.write_text("data:\n  tum_max_dt_pose: 0.1\n  tum:\n    max_dt_pose: 0.2\n")
    with pytest.raises(ConfigError, match=r"'data.tum_max_dt_pose' and 'data.tum.max_dt_pose' in .*both.yaml"):
        load_config(f)
    # in different layers the later one wins, as for any key
    g = tmp_path / "old.yaml"
    g.write_text("render:\n  name: neus\n  neus_fd_eps: 0.01\n")
    assert load_config(g, overrides=["render.neus.fd_eps=0.03"]).render.neus.fd_eps == 0.03


def test_keyframe_variant_alias():
    assert load_config(overrides=["slam.keyframe_variant=false"]).slam.keyframe_fraction == 0.05
    assert load_config(overrides=["slam.keyframe_variant=false", "slam.keyframe_fraction=0.1"]).slam.keyframe_fraction \
        == 0.1
    # as before, the variant replaces the fraction set beside it (an old config.yaml lists both)
    assert load_config(overrides=["slam.keyframe_variant=true", "slam.keyframe_fraction=0.1"]).slam.keyframe_fraction \
        == 0.005
    with pytest.raises(ConfigError, match="slam.keyframe_variant.*true or false"):
        load_config(overrides=["slam.keyframe_variant=0.005"])


def test_misplaced_key_suggests_its_section():
    with pytest.raises(ConfigError, match=r"unknown config key 'render.fd_eps'.*did you mean 'render.neus.fd_eps'"):
        load_config(overrides=["render.fd_eps=0.01"])
    with pytest.raises(ConfigError, match=r"did you mean 'data.tum.max_dt_depth'"):
        load_config(overrides=["data.max_dt_depth=0.01"])


def test_inrslam_config_shows_the_nested_keys(capsys):
    from inrslam.cli import main

    assert main(["config", "render.name=neus", "render.neus_fd_eps=0.01"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["render"]["name"] == "neus" and shown["render"]["neus"]["fd_eps"] == 0.01
    assert shown["render"]["density"] == {"beta": 10.0, "learn_beta": False}
    assert set(shown["data"]["tum"]) == {"max_dt_depth", "max_dt_pose"} and shown["field"]["mlp"]["width"] == 256
    assert "keyframe_variant" not in shown["slam"] and "beta" not in shown["render"]
    assert main(["config", "render.density.beta=5", "render.name=neus"]) == 2
    assert "applies to render.name=density" in capsys.readouterr().err
