import enum
import re
from dataclasses import dataclass, field
from typing import Optional

import pytest
import yaml

from inrslam.config.loader import build_config, config_to_dict, load_config, parse_overrides
from inrslam.config.schema import RunConfig
from inrslam.errors import ConfigError
from inrslam.io.yamlfile import parse_yaml


class Mode(str, enum.Enum):
    A = "a"
    B = "b"


@dataclass
class Inner:
    iters: int = 20
    lr: float = 1e-3
    mode: Mode = Mode.A


@dataclass
class Root:
    inner: Inner = field(default_factory=Inner)
    name: str = "x"
    bounds: Optional[list[list[float]]] = None
    flag: bool = False


def test_layers_merge_in_order_and_convert_types():
    cfg = build_config(Root, [({"inner": {"iters": 5}}, "a.yaml"), ({"inner": {"lr": "1e-2", "mode": "b"}}, "cli")])
    assert cfg.inner.iters == 5 and cfg.inner.lr == pytest.approx(1e-2) and cfg.inner.mode is Mode.B
    assert cfg.name == "x"


def test_unknown_key_names_key_source_and_closest():
    with pytest.raises(ConfigError) as e:
        build_config(Root, [({"inner": {"iter": 5}}, "my.yaml")])
    msg = str(e.value)
    assert "inner.iter" in msg and "my.yaml" in msg and "inner.iters" in msg


def test_wrong_type_names_key_and_source():
    with pytest.raises(ConfigError) as e:
        build_config(Root, [({"inner": {"iters": "many"}}, "file.yaml")])
    assert "inner.iters" in str(e.value) and "file.yaml" in str(e.value) and "integer" in str(e.value)
    with pytest.raises(ConfigError, match="flag"):
        build_config(Root, [({"flag": "yes please"}, "f")])
    with pytest.raises(ConfigError, match="'a', 'b'"):
        build_config(Root, [({"inner": {"mode": "c"}}, "f")])


def test_optional_and_nested_lists():
    cfg = build_config(Root, [({"bounds": [[0, 1], [0, 2], [0, 3]]}, "f")])
    assert cfg.bounds == [[0.0, 1.0], [0.0, 2.0], [0.0, 3.0]]
    assert isinstance(cfg.bounds[0][0], float)


def test_parse_overrides():
    ov = parse_overrides(["a.b=3", "a.c=hash+tri", "d=[1, 2]", "e=true"])
    assert ov == {"a": {"b": 3, "c": "hash+tri"}, "d": [1, 2], "e": True}
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        parse_overrides(["novalue"])


def test_inherit_from_chain_and_roundtrip(tmp_path):
    base = tmp_path / "base.yaml"
    base.write_text(yaml.safe_dump({"slam": {"track_iters": 7, "map_iters": 3}}))
    child = tmp_path / "child.yaml"
    child.write_text("inherit_from: base.yaml\nslam:\n  map_iters: 4\n")
    cfg = load_config(child, preset="paper", overrides=["slam.init_iters=11"])
    assert (cfg.slam.track_iters, cfg.slam.map_iters, cfg.slam.init_iters) == (7, 4, 11)
    # the resolved config fed back (no preset) reproduces it exactly
    dumped = tmp_path / "resolved.yaml"
    dumped.write_text(yaml.safe_dump(config_to_dict(cfg)))
    assert load_config(dumped, preset=None) == cfg


def test_unknown_key_in_file_names_file(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("slam:\n  trak_iters: 3\n")
    with pytest.raises(ConfigError) as e:
        load_config(f)
    assert "bad.yaml" in str(e.value) and "slam.track_iters" in str(e.value)


def test_presets_and_unknown_preset():
    paper = load_config(preset="paper")
    quick = load_config(preset="quick")
    assert paper.slam.init_iters == 500 and paper.slam.track_pixels == 1024 and paper.slam.map_pixels == 2048
    assert paper.sampling.n_free == 48 and paper.sampling.n_surface == 12
    assert quick.slam.init_iters < paper.slam.init_iters
    with pytest.raises(ConfigError, match="did you mean 'paper'"):
        load_config(preset="papr")


def _leaves(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_leaves(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def test_paper_fused_is_the_paper_loop_with_every_fused_kernel():
    """`paper_fused` changes nothing of `paper` but the three kernel switches (the same maths, rounded otherwise)."""
    paper = _leaves(config_to_dict(load_config(preset="paper")))
    fused = _leaves(config_to_dict(load_config(preset="paper_fused")))
    assert set(paper) == set(fused)
    assert {k: (paper[k], fused[k]) for k in paper if paper[k] != fused[k]} == {
        "field.decoder_kernel": ("torch", "auto"), "loss.kernel": ("torch", "auto"), "render.kernel": ("torch", "auto")}


def test_missing_and_circular_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    a.write_text("inherit_from: b.yaml\n")
    b.write_text("inherit_from: a.yaml\n")
    with pytest.raises(ConfigError, match="circular"):
        load_config(a)


def test_faithful_switch_reaches_every_section():
    cfg = load_config(preset="paper", overrides=["faithful=true"])
    assert cfg.field.faithful and cfg.render.faithful and cfg.data.faithful_intrinsics
    assert cfg.sampling.band == 1.5 and cfg.loss.reduction.value == "global"
    explicit = load_config(preset="paper", overrides=["faithful=true", "sampling.band=1.0", "loss.reduction=per_ray"])
    assert explicit.field.faithful and explicit.sampling.band == 1.0 and explicit.loss.reduction.value == "per_ray"
    assert not cfg.slam.eval_final_pose and cfg.slam.faithful_relative and cfg.slam.max_pose_jump == 0
    default = load_config(preset="paper")
    assert not default.field.faithful and default.sampling.band == 1.0 and default.loss.reduction.value == "per_ray"


def test_date_like_values_stay_strings(tmp_path):
    # YAML 1.1 reads 2023-02-28 as a date (and 2023-02-29 as an error): a folder named so must stay its name
    assert parse_overrides(["data.path=2023-02-29", "slam.track_iters=10"]) == {
        "data": {"path": "2023-02-29"}, "slam": {"track_iters": 10}}
    assert load_config(overrides=["data.path=2023-02-28"]).data.path == "2023-02-28"
    (tmp_path / "c.yaml").write_text("data:\n  path: 2023-02-29\n")
    assert load_config(tmp_path / "c.yaml").data.path == "2023-02-29"


def test_config_file_that_is_not_utf8_names_the_file(tmp_path):
    (tmp_path / "c.yaml").write_bytes(b"data:\n  path: \xff\xfe\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: cannot read \(UnicodeDecodeError"):
        load_config(tmp_path / "c.yaml")
    (tmp_path / "d.yaml").write_text("seed: !!int x\n")  # a tag its value cannot hold
    with pytest.raises(ConfigError, match=r"d\.yaml: invalid YAML: invalid literal for int"):
        load_config(tmp_path / "d.yaml")


def test_yaml_syntax_errors_are_one_line_with_their_position(tmp_path):
    (tmp_path / "c.yaml").write_text("seed: 1\ndata:\n  path: a: b\n")
    with pytest.raises(ConfigError) as e:
        load_config(tmp_path / "c.yaml")
    assert "\n" not in str(e.value)
    assert str(e.value).endswith("c.yaml: invalid YAML: mapping values are not allowed here (line 3, column 10)")


def test_a_mapping_given_to_a_leaf_key_names_where_it_was_given():
    with pytest.raises(ConfigError, match=r"config key 'slam.track_iters' in command-line overrides: expected an int"):
        load_config(overrides=["slam.track_iters=x: y"])
    # a string key keeps the text as typed, colon included (a folder may be named so)
    assert load_config(overrides=["data.path=/tmp/x: y"]).data.path == "/tmp/x: y"


def test_string_keys_from_the_command_line_keep_the_text_typed(tmp_path):
    # data.path=0001 is a folder named 0001, not the number 1; a quoted text and null are still read as YAML
    cfg = load_config(overrides=["data.path=0001", "data.sevenscenes.sequence=2023.10", "slam.track_iters=10"],
                      check_variants=False)
    assert cfg.data.path == "0001" and cfg.data.sevenscenes.sequence == "2023.10" and cfg.slam.track_iters == 10
    quoted = load_config(overrides=['data.sevenscenes.sequence="seq-01"'], check_variants=False)
    assert quoted.data.sevenscenes.sequence == "seq-01"
    assert parse_overrides(["data.path = 0001 "], RunConfig) == {"data": {"path": "0001"}}  # spaces dropped
    # without a schema every value is a YAML scalar, as before
    assert parse_overrides(["data.path=0001"]) == {"data": {"path": 1}}


def test_duplicate_yaml_key_names_key_and_line(tmp_path):
    (tmp_path / "c.yaml").write_text("seed: 1\nslam:\n  track_iters: 3\nseed: 2\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: invalid YAML: duplicate key 'seed' \(first given on line 1\) "
                                          r"\(line 4, column 1\)"):
        load_config(tmp_path / "c.yaml")
    # a merge key (<<) may be overridden by the mapping's own key, as YAML intends
    assert parse_yaml("b: &b {x: 3}\ns:\n  <<: *b\n  x: 4\n") == {"b": {"x": 3}, "s": {"x": 4}}


def test_faithful_decided_by_the_last_layer_setting_it(tmp_path):
    (tmp_path / "c.yaml").write_text("faithful: true\n")
    off = load_config(tmp_path / "c.yaml", overrides=["faithful=false"])
    on = load_config(tmp_path / "c.yaml")
    assert on.field.faithful and on.sampling.band == 1.5
    assert not off.faithful and not off.field.faithful and off.sampling.band == 1.0


def test_list_element_error_names_where_the_list_was_set(tmp_path):
    (tmp_path / "c.yaml").write_text("data:\n  intrinsics: [500, x, 320, 240]\n")
    with pytest.raises(ConfigError, match=r"'data\.intrinsics\[1\]' in .*c\.yaml: expected a number"):
        load_config(tmp_path / "c.yaml")


@pytest.mark.parametrize("key,bad", [("seed", -1), ("eval.seed", 2**63), ("data.builtin.seed", -5),
                                     ("data.builtin.missing_depth", 1.0)])
def test_seed_and_hole_fraction_ranges(key, bad):
    with pytest.raises(ConfigError, match=re.escape(key) + r".*in \[0, "):
        load_config(overrides=[f"{key}={bad}"])
    load_config(overrides=[f"{key}=0"])


@pytest.mark.parametrize("text", ["seed: !!timestamp garbage\n", "seed: !!bool maybe\n", 'seed: !!int ""\n',
                                  "data: !!set [1]\n", "data: !!map [1]\n", "x: " + "[" * 2000 + "]" * 2000 + "\n"])
def test_tags_a_value_cannot_hold_and_deep_nesting_are_one_line_errors(tmp_path, text):
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(ConfigError, match=r"c\.yaml: invalid YAML: ") as e:
        load_config(tmp_path / "c.yaml")
    assert "\n" not in str(e.value)
    if text.startswith("seed: "):  # the same value as a KEY=VALUE override: a ConfigError too, not a traceback
        with pytest.raises(ConfigError, match="'seed'"):
            load_config(overrides=["seed=" + text[len("seed: "):].strip()])
