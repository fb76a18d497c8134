"""Load a `RunConfig` from presets, YAML files and `key.sub=value` overrides, with strict validation.

Precedence (later wins): dataclass defaults < preset < `--config` file (and its `inherit_from` chain) < overrides.
Old key names are accepted in every layer (`inrslam.config.aliases`). Unknown keys and wrong types raise
`ConfigError` naming the key, where it came from and the closest valid key; so does a key the user set in the
section of a variant that is not selected (`render.neus.*` with render.name=density, `inrslam.config.variants`).
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import types
import typing
from pathlib import Path
from typing import Any, Union

import yaml

from inrslam.config.ranges import check_ranges
from inrslam.errors import ConfigError
from inrslam.io.yamlfile import load_yaml, parse_yaml

PRESET_DIR = Path(__file__).resolve().parent.parent / "configs"


def preset_names() -> list[str]:
    """Names of the shipped presets (`src/inrslam/configs/*.yaml`)."""
    return sorted(p.stem for p in PRESET_DIR.glob("*.yaml"))


def _preset_path(name: str) -> Path:
    path = PRESET_DIR / f"{name}.yaml"
    if not path.is_file():
        close = difflib.get_close_matches(name, preset_names(), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ConfigError(f"unknown preset {name!r}{hint} (choices: {', '.join(preset_names())})")
    return path


def _read_yaml(path: Path) -> dict:
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    data = load_yaml(path) or {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def _load_chain(path: Path, seen: tuple[Path, ...] = ()) -> list[tuple[dict, str]]:
    """[(dict, source), ...] from the root of the `inherit_from` chain down to `path`."""
    path = path.resolve()
    if path in seen:
        raise ConfigError(f"{path}: circular inherit_from chain")
    data = _read_yaml(path)
    parent = data.pop("inherit_from", None)
    chain: list[tuple[dict, str]] = []
    if parent:
        if not isinstance(parent, str):
            raise ConfigError(f"{path}: inherit_from must be a path or 'preset:NAME'")
        if parent.startswith("preset:"):
            ppath = _preset_path(parent[len("preset:"):])
        else:
            ppath = Path(parent) if Path(parent).is_absolute() else path.parent / parent
        chain = _load_chain(ppath, seen + (path,))
    return chain + [(data, str(path))]


_NULLS = {"null", "Null", "NULL", "~"}


def _leaf_type(cls: type | None, parts: list[str]) -> Any:
    """Schema type of the dotted key `parts` under dataclass `cls` (None when it is not a known leaf)."""
    tp: Any = cls
    for p in parts:
        sec = _section_type(tp) if tp is not None else None
        if sec is None or p not in {f.name for f in dataclasses.fields(sec)}:
            return None
        tp = _hints(sec)[p]
    return tp


def parse_overrides(items: list[str], schema: type | None = None) -> dict:
    """['slam.track_iters=10', 'field.encoding=hash'] -> nested dict (values parsed as YAML scalars/lists).

    With `schema` (a config dataclass), a key whose type there is a string keeps the text as typed
    (`data.path=0001` stays '0001', not the number 1), except a YAML null for an optional one and a quoted text."""
    out: dict = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"override {item!r}: expected KEY=VALUE, e.g. slam.track_iters=10")
        key, _, raw = item.partition("=")
        key = key.strip().lstrip("-")
        tp, optional = _unwrap_optional(_leaf_type(schema, key.split(".")))
        text = raw.strip()
        if tp is str and not (optional and text in _NULLS) and text[:1] not in ("'", '"'):
            value = text  # (surrounding spaces dropped, as YAML does: `key = value` in a sweep spec's list)
        else:
            try:
                value = parse_yaml(raw) if text else ""
            except yaml.YAMLError:
                value = raw
        node = out
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {item!r}: {p!r} is set both as a value and as a section")
        node[parts[-1]] = value
    return out


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0], True
    return tp, False


def _section_type(tp: Any) -> type | None:
    tp, _ = _unwrap_optional(tp)
    return tp if isinstance(tp, type) and dataclasses.is_dataclass(tp) else None


def _validate_keys(cls: type, data: dict, source: str, prefix: str = "") -> None:
    """Raise on keys of `data` that are not fields of dataclass `cls` (recursively)."""
    hints = _hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    for key, value in data.items():
        full = f"{prefix}{key}"
        if key not in names:
            valid = [f"{prefix}{n}" for n in names]
            nested = [f"{prefix}{n}.{key}" for n in names if (sub := _section_type(hints[n])) is not None
                      and key in {f.name for f in dataclasses.fields(sub)}]  # `render.fd_eps` -> render.neus.fd_eps
            close = nested[:1] or difflib.get_close_matches(full, valid, n=1, cutoff=0.5)
            hint = f"; did you mean {close[0]!r}?" if close else f" (valid keys here: {', '.join(names)})"
            raise ConfigError(f"unknown config key {full!r} in {source}{hint}")
        tp, _ = _unwrap_optional(hints[key])
        if isinstance(tp, type) and dataclasses.is_dataclass(tp) and isinstance(value, dict):
            _validate_keys(tp, value, source, prefix=f"{full}.")


def _merge(base: dict, new: dict, sources: dict, source: str, prefix: str = "") -> dict:
    out = dict(base)
    for k, v in new.items():
        full = f"{prefix}{k}"
        if isinstance(v, dict):
            prev = out.get(k)
            out[k] = _merge(prev if isinstance(prev, dict) else {}, v, sources, source, prefix=f"{full}.")
            sources[full] = source  # a mapping given to a leaf key is reported where it was given
        else:
            out[k] = v
            sources[full] = source
    return out


def _convert(tp: Any, value: Any, key: str, sources: dict) -> Any:
    src = sources.get(key) or sources.get(key.split("[")[0], "defaults")  # a list element: where its list was set
    tp, optional = _unwrap_optional(tp)

    def fail(expected: str) -> ConfigError:
        return ConfigError(f"config key {key!r} in {src}: expected {expected}, got {value!r} ({type(value).__name__})")

    if value is None:
        if optional:
            return None
        raise fail(getattr(tp, "__name__", str(tp)))
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise fail(f"a section (mapping) of {tp.__name__}")
        hints = _hints(tp)
        kwargs = {}
        for f in dataclasses.fields(tp):
            if f.name in value:
                kwargs[f.name] = _convert(hints[f.name], value[f.name], f"{key}.{f.name}" if key else f.name, sources)
        return tp(**kwargs)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        if isinstance(value, tp):
            return value
        try:
            return tp(value)
        except ValueError:
            raise fail("one of " + ", ".join(repr(m.value) for m in tp)) from None
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise fail("true or false")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise fail("an integer")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value)  # YAML reads '1e-3' as a string
            except ValueError:
                pass
        raise fail("a number")
    if tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)
        raise fail("a string")
    origin = typing.get_origin(tp)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise fail("a list")
        args = typing.get_args(tp)
        inner = args[0] if args else Any
        return [_convert(inner, v, f"{key}[{i}]", sources) for i, v in enumerate(value)]
    if tp is Any:
        return value
    raise ConfigError(f"config key {key!r}: unsupported type {tp!r} in the schema")


def build_config(cls: type, layers: list[tuple[dict, str]], check: Any = None):
    """Validate each (dict, source) layer against `cls`, merge in order and convert to a `cls` instance;
    `check(cfg, sources)` then validates values (sources: dotted key -> the layer that set it)."""
    merged: dict = {}
    sources: dict[str, str] = {}
    for data, source in layers:
        _validate_keys(cls, data, source)
        merged = _merge(merged, data, sources, source)
    cfg = _convert(cls, merged, "", sources)
    if check is not None:
        check(cfg, sources)
    return cfg


def _is_preset(source: str) -> bool:
    return Path(source).parent == PRESET_DIR


def load_config(
    config: str | Path | None = None,
    preset: str | None = "paper",
    overrides: list[str] | dict | None = None,
    check_variants: bool = True,
    overrides_source: str = "command-line overrides",
):
    """Resolve a `RunConfig`.

    Args:
        config: YAML file (may use `inherit_from: other.yaml` or `inherit_from: preset:NAME`).
        preset: preset applied first (None = dataclass defaults only).
        overrides: `['a.b=1', ...]` or a nested dict, applied last.
        check_variants: a key that `config` (its chain, presets excepted) or `overrides` set in the section of a
            variant the result does not select (`render.density.beta` with render.name=neus) is a ConfigError
            unless it keeps the value it would have anyway. False: such keys are unused (a run's own config.yaml
            on resume; sweeps, which check that each key applies to some run of the sweep).
        overrides_source: what error messages call `overrides` (a sweep's: "sweep overrides").
    """
    from inrslam.config.aliases import apply_aliases
    from inrslam.config.schema import FAITHFUL_LAYER, RunConfig
    from inrslam.config.variants import check_variant_keys, leaf_keys

    layers: list[tuple[dict, str, bool]] = []  # (data, source, written by the user)
    if preset:
        layers += [(data, source, False) for data, source in _load_chain(_preset_path(preset))]
    n_preset = len(layers)
    if config:
        layers += [(data, source, not _is_preset(source)) for data, source in _load_chain(Path(config))]
    if overrides:
        ov = parse_overrides(overrides, RunConfig) if isinstance(overrides, list) else overrides
        layers.append((ov, overrides_source, True))
    faithful = [layer["faithful"] for layer, _, _ in layers if "faithful" in layer]
    if faithful and faithful[-1] is True:  # the last layer that sets it decides
        layers.insert(n_preset, (FAITHFUL_LAYER, "faithful=true", False))
    normalised: list[tuple[dict, str]] = []
    user_keys: dict[str, str] = {}  # dotted key -> the last user layer setting it
    renamed: dict[str, str] = {}  # dotted key -> its old spelling, when that layer used it
    for data, source, by_user in layers:
        layer_renamed: dict[str, str] = {}
        data = apply_aliases(data, source, layer_renamed)
        normalised.append((data, source))
        for key in leaf_keys(data) if by_user else ():
            user_keys[key] = source
            if key in layer_renamed:
                renamed[key] = layer_renamed[key]
            else:
                renamed.pop(key, None)
    cfg = build_config(RunConfig, normalised, check=check_ranges)
    if check_variants and user_keys:
        baseline = build_config(RunConfig, [n for n, (_, _, by_user) in zip(normalised, layers) if not by_user])
        check_variant_keys(cfg, baseline, user_keys, renamed)
    return cfg


def config_to_dict(cfg: Any) -> Any:
    """Dataclass config -> plain dict of YAML scalars (enums become their values)."""
    if dataclasses.is_dataclass(cfg):
        return {f.name: config_to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, enum.Enum):
        return cfg.value
    if isinstance(cfg, (list, tuple)):
        return [config_to_dict(v) for v in cfg]
    return cfg


def dump_config(cfg: Any) -> str:
    """Resolved config as plain YAML (feeding it back with `--config` and no preset reproduces `cfg`)."""
    return yaml.safe_dump(config_to_dict(cfg), sort_keys=False, default_flow_style=False)
