"""Sweep specs: a YAML grid of encodings F x renders G x scenes x presets x seeds, validated strictly.

    encodings: [dense, hash]            # field.encoding values (registry ENCODINGS)
    renders: [direct, density]          # render.name values (registry RENDERERS)
    scenes:                             # builtin:NAME, a dataset folder, or {name, path, overrides}
      - builtin:room
      - ${DATA_ROOT:-data}/Replica/room0
      - {name: kitchen, path: /data/ck, overrides: {data.max_frames: 100}}
    presets: [paper]                    # shipped presets (src/inrslam/configs/)
    seeds: [0]
    overrides: {slam: {track_iters: 10}}   # or [slam.track_iters=10, ...]; applied to every run
    max_frames: 50                      # optional, = data.max_frames

`expand(spec)` gives one `RunSpec` per combination, each with a stable readable run-directory name.
"""

from __future__ import annotations

import difflib
import itertools
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from inrslam.errors import ConfigError
from inrslam.io.yamlfile import load_yaml

SPEC_DIR = Path(__file__).resolve().parent / "specs"

SPEC_KEYS = ("name", "description", "encodings", "renders", "scenes", "presets", "seeds", "overrides", "max_frames")
SCENE_KEYS = ("name", "path", "overrides")
_ENV = re.compile(r"\$\{(\w+)(?::-([^}]*))?\}|\$(\w+)")
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


@dataclass
class SceneSpec:
    """One scene of a sweep: short `name` (used in run names), `path` given to `data.path`, extra overrides."""

    name: str
    path: str
    overrides: dict = field(default_factory=dict)


@dataclass
class SweepSpec:
    """A validated sweep spec (`load_spec`)."""

    encodings: list[str]
    renders: list[str]
    scenes: list[SceneSpec]
    presets: list[str] = field(default_factory=lambda: ["paper"])
    seeds: list[int] = field(default_factory=lambda: [0])
    overrides: dict = field(default_factory=dict)
    max_frames: int | None = None
    name: str = ""
    description: str = ""
    source: str = "<dict>"  # file the spec came from (for error messages)


@dataclass
class RunSpec:
    """One combination of a sweep. `overrides` is the full nested override dict given to `load_config`."""

    name: str
    scene: str
    scene_path: str
    encoding: str
    render: str
    preset: str
    seed: int
    overrides: dict

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "RunSpec":
        return RunSpec(**d)


# ----------------------------------------------------------------------------------------------------------------
# loading and validation


def _unknown(key: str, valid: tuple[str, ...], where: str) -> ConfigError:
    close = difflib.get_close_matches(key, valid, n=1, cutoff=0.5)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return ConfigError(f"unknown sweep-spec key {key!r} in {where}{hint} (valid keys: {', '.join(valid)})")


def _str_list(data: dict, key: str, source: str, required: bool, default: list | None = None) -> list:
    if key not in data:
        if required:
            raise ConfigError(f"{source}: sweep spec needs a {key!r} list")
        return list(default or [])
    value = data[key]
    if isinstance(value, (str, int)) and not isinstance(value, bool):
        value = [value]
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{source}: {key!r} must be a non-empty list, got {value!r}")
    if len(set(map(str, value))) != len(value):
        raise ConfigError(f"{source}: {key!r} lists a value twice: {value!r}")
    return value


def expand_env(text: str, where: str = "") -> str:
    """Expand `${VAR}`, `${VAR:-default}` and `$VAR` from the environment (unset without default -> ConfigError)."""

    def sub(m: re.Match) -> str:
        name = m.group(1) or m.group(3)
        if name in os.environ:
            return os.environ[name]
        if m.group(2) is not None:
            return m.group(2)
        raise ConfigError(f"{where}: environment variable {name!r} is not set (used in {text!r}); "
                          f"export it or write ${{{name}:-default}}")

    return os.path.expanduser(_ENV.sub(sub, text))


def _as_overrides(value: Any, where: str) -> dict:
    if value is None:
        return {}
    if isinstance(value, list):
        if not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{where}: overrides must be KEY=VALUE strings or a mapping, got {value!r}")
        from inrslam.config.loader import parse_overrides
        from inrslam.config.schema import RunConfig

        try:
            return parse_overrides(value, RunConfig)
        except ConfigError as e:
            raise ConfigError(f"{where}: {e}") from None
    if isinstance(value, dict):
        return _nest(value, where)
    raise ConfigError(f"{where}: overrides must be a mapping or a list of KEY=VALUE, got {value!r}")


def _nest(d: dict, where: str) -> dict:
    """Allow dotted keys in mappings: {'slam.track_iters': 5} -> {'slam': {'track_iters': 5}}."""
    out: dict = {}
    for k, v in d.items():
        parts = str(k).split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{where}: override {k!r}: {p!r} is set both as a value and as a section")
        v = _nest(v, where) if isinstance(v, dict) else v
        if isinstance(v, dict) and isinstance(node.get(parts[-1]), dict):
            node[parts[-1]] = deep_merge(node[parts[-1]], v)
        else:
            node[parts[-1]] = v
    return out


def deep_merge(base: dict, new: dict) -> dict:
    """Recursive dict merge; `new` wins."""
    out = dict(base)
    for k, v in new.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def scene_short_name(path: str) -> str:
    """'builtin:room' -> 'room'; '/data/Replica/room0/' -> 'room0'; '.' -> the current folder's name."""
    if path.startswith("builtin:"):
        return path[len("builtin:"):]
    name = Path(path.rstrip("/\\")).name
    if name in ("", ".", ".."):  # a relative path that names no folder itself: the folder it resolves to
        name = Path(path or ".").expanduser().resolve().name
    return name or path


def _scene(item: Any, source: str, i: int) -> SceneSpec:
    where = f"{source}: scenes[{i}]"
    if isinstance(item, str):
        item = {"path": item}
    if not isinstance(item, dict):
        raise ConfigError(f"{where}: expected builtin:NAME, a dataset path or a mapping {{name, path, overrides}}")
    for k in item:
        if k not in SCENE_KEYS:
            raise _unknown(str(k), SCENE_KEYS, where)
    if not isinstance(item.get("path"), str) or not item["path"]:
        raise ConfigError(f"{where}: a scene needs a 'path' (builtin:NAME or a dataset folder)")
    raw = item["path"]
    if raw.startswith("builtin:"):
        path = raw
    else:
        path = str(Path(expand_env(raw, where)).absolute())  # relative to the current directory
    name = str(item.get("name") or scene_short_name(path if raw.startswith("builtin:") else expand_env(raw, where)))
    return SceneSpec(name=name, path=path, overrides=_as_overrides(item.get("overrides"), where))


def load_spec(spec: str | os.PathLike | dict | SweepSpec) -> SweepSpec:
    """Read and validate a sweep spec (a YAML path, the name of a shipped spec such as 'tiny', or a dict)."""
    if isinstance(spec, SweepSpec):
        return spec
    if isinstance(spec, dict):
        data, source = spec, "<dict>"
    else:
        path = Path(spec)
        if not path.is_file() and (SPEC_DIR / f"{spec}.yaml").is_file():
            path = SPEC_DIR / f"{spec}.yaml"
        if not path.is_file():
            shipped = sorted(p.stem for p in SPEC_DIR.glob("*.yaml"))
            raise ConfigError(f"{spec}: sweep spec not found (shipped specs: {', '.join(shipped)})")
        data = load_yaml(path) or {}
        source = str(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level")
    for k in data:
        if k not in SPEC_KEYS:
            raise _unknown(str(k), SPEC_KEYS, source)
    encodings = [str(v) for v in _str_list(data, "encodings", source, True)]
    renders = [str(v) for v in _str_list(data, "renders", source, True)]
    presets = [str(v) for v in _str_list(data, "presets", source, False, ["paper"])]
    seeds = _str_list(data, "seeds", source, False, [0])
    if not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
        raise ConfigError(f"{source}: 'seeds' must be integers, got {seeds!r}")
    raw_scenes = _str_list(data, "scenes", source, True)
    scenes = [_scene(s, source, i) for i, s in enumerate(raw_scenes)]
    names = [s.name for s in scenes]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"{source}: several scenes are called {dup[0]!r}; give them distinct 'name's")
    max_frames = data.get("max_frames")
    if max_frames is not None and (not isinstance(max_frames, int) or isinstance(max_frames, bool) or max_frames < 0):
        raise ConfigError(f"{source}: 'max_frames' must be a non-negative integer, got {max_frames!r}")
    return SweepSpec(encodings=encodings, renders=renders, scenes=scenes, presets=presets,
                     seeds=[int(s) for s in seeds],
                     overrides=_as_overrides(data.get("overrides"), f"{source}: overrides"), max_frames=max_frames,
                     name=str(data.get("name") or (Path(source).stem if source != "<dict>" else "sweep")),
                     description=str(data.get("description") or ""), source=source)


# ----------------------------------------------------------------------------------------------------------------
# expansion


def sanitize(text: str) -> str:
    """Make a string safe as (part of) a folder name, never hidden: 'hash+tri' -> 'hash-tri', '.x' -> 'x'."""
    return _UNSAFE.sub("-", text).strip("-").lstrip(".") or "x"


def run_name(scene: str, encoding: str, render: str, preset: str, seed: int) -> str:
    """Stable run-directory name `{scene}__{encoding}__{render}__{preset}__s{seed}` (sanitised)."""
    return "__".join(sanitize(p) for p in (scene, encoding, render, preset)) + f"__s{seed}"


def expand(spec: SweepSpec | dict | str | os.PathLike) -> list[RunSpec]:
    """Grid product scenes x encodings x renders x presets x seeds -> RunSpecs (that order)."""
    spec = load_spec(spec)
    runs = []
    for scene, enc, ren, preset, seed in itertools.product(spec.scenes, spec.encodings, spec.renders, spec.presets,
                                                           spec.seeds):
        ov = dict(spec.overrides)
        if spec.max_frames is not None:
            ov = deep_merge(ov, {"data": {"max_frames": spec.max_frames}})
        ov = deep_merge(ov, scene.overrides)
        ov = deep_merge(ov, {"data": {"path": scene.path}, "field": {"encoding": enc}, "render": {"name": ren},
                             "seed": seed})
        ov = _absolute_files(ov)
        runs.append(RunSpec(name=run_name(scene.name, enc, ren, preset, seed), scene=scene.name,
                            scene_path=scene.path, encoding=enc, render=ren, preset=preset, seed=seed, overrides=ov))
    names = [r.name for r in runs]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ConfigError(f"{spec.source}: two combinations map to the run directory {dup!r} after sanitising names; "
                          "rename a scene or drop a duplicate value")
    return runs


def resolve_config(run: RunSpec):
    """The `RunConfig` of one run (preset + overrides), with registry names checked. An override in the section of a
    variant this run does not select is unused here (`check_sweep_variants` checks it applies to some run)."""
    from inrslam.config.loader import load_config

    cfg = load_config(None, preset=run.preset, overrides=run.overrides, check_variants=False,
                      overrides_source="sweep overrides")
    check_registry_names(cfg)
    return cfg


def check_sweep_variants(spec: SweepSpec, runs: list[RunSpec], cfgs: dict[str, Any]) -> None:
    """ConfigError when an override of the sweep (or of one scene) sets a key in the section of a variant that no run
    it reaches selects, e.g. `render.neus.fd_eps` in a sweep over renders density and direct.

    Args:
        spec: the sweep spec (its `overrides` and each scene's).
        runs: `expand(spec)`.
        cfgs: {run name: resolved RunConfig} (`validate_runs`).
    """
    from inrslam.config.aliases import apply_aliases
    from inrslam.config.variants import leaf_keys, variant_error, variant_of

    groups = [(f"{spec.source}: overrides", spec.overrides, runs)]
    groups += [(f"{spec.source}: scene {sc.name!r} overrides", sc.overrides, [r for r in runs if r.scene == sc.name])
               for sc in spec.scenes]
    for where, overrides, reached in groups:
        renamed: dict[str, str] = {}
        for key in sorted(leaf_keys(apply_aliases(overrides, where, renamed))):
            variant = variant_of(key)
            states = [variant.applies(cfgs[r.name]) for r in reached if r.name in cfgs] if variant else []
            if variant and states and all(active is False for active, _ in states):
                selected = "; ".join(sorted({what for _, what in states}))
                raise variant_error(key, where, variant, f"no run of the sweep selects it ({selected})",
                                    renamed.get(key))


def check_registry_names(cfg) -> None:
    """ConfigError when `field.encoding` or `render.name` is not registered (closest name suggested)."""
    from inrslam.fields.registry import ENCODINGS
    from inrslam.rendering import RENDERERS

    if cfg.field.encoding not in ENCODINGS:
        raise ConfigError(f"config key 'field.encoding': {ENCODINGS.unknown_message(cfg.field.encoding)}")
    if cfg.render.name not in RENDERERS:
        raise ConfigError(f"config key 'render.name': {RENDERERS.unknown_message(cfg.render.name)}")


FILE_KEYS = (("slam", "poses"), ("eval", "virtual_cameras"))
"""Override keys naming a file: made absolute when the sweep is expanded (as `inrslam run` does), checked to exist."""


def _absolute_files(ov: dict) -> dict:
    """`ov` with the FILE_KEYS it sets absolute (relative to the current directory, like scene folders)."""
    for section, key in FILE_KEYS:
        value = ov.get(section, {}).get(key) if isinstance(ov.get(section), dict) else None
        if isinstance(value, str) and value and value != "gt":
            ov = deep_merge(ov, {section: {key: str(Path(os.path.expanduser(value)).absolute())}})
    return ov


def validate_runs(runs: list[RunSpec], source: str = "sweep spec", check_paths: bool = True,
                  spec: SweepSpec | None = None) -> dict[str, Any]:
    """Resolve every run's config up-front (a typo fails before anything runs). Returns {run name: RunConfig}.

    Built-in scene names must be known; with `check_paths`, dataset folders must exist too; with `spec` (the spec
    `runs` were expanded from), its overrides must apply to some run (`check_sweep_variants`).
    """
    cfgs = {}
    for run in runs:
        try:
            cfgs[run.name] = resolve_config(run)
        except ConfigError as e:
            raise ConfigError(f"{source}: run {run.name}: {e}") from None
    if spec is not None:
        check_sweep_variants(spec, runs, cfgs)
    for scene_path in sorted({r.scene_path for r in runs}):
        if scene_path.startswith("builtin:"):
            _check_builtin(scene_path, source)
        elif check_paths and not Path(scene_path).is_dir():
                raise ConfigError(f"{source}: scene folder {scene_path} does not exist (relative paths are taken from "
                                  "the current directory; ${DATA_ROOT}-style variables are expanded)")
    for run in runs if check_paths else ():
        for section, key in FILE_KEYS:
            value = getattr(getattr(cfgs[run.name], section), key)
            if value and value != "gt" and not Path(value).is_file():
                raise ConfigError(f"{source}: run {run.name}: {section}.{key}: file {value} does not exist (relative "
                                  "paths are taken from the current directory)")
    return cfgs


def _check_builtin(path: str, source: str) -> None:
    from inrslam.scenes import list_scenes

    names = [s[0] for s in list_scenes()]
    name = path[len("builtin:"):]
    if name not in names:
        close = difflib.get_close_matches(name, names, n=1)
        hint = f"; did you mean 'builtin:{close[0]}'?" if close else ""
        raise ConfigError(f"{source}: unknown built-in scene {name!r}{hint} (choices: {', '.join(names)})")
