"""Config sections that belong to one variant: a renderer (`render.neus.*`), a dataset reader (`data.tum.*`), the
built-in scenes (`data.builtin.*`) or an encoding (`field.mlp.*`).

A key the user set in another variant's section would be silently unused, so `load_config` makes it an error
(`check_variant_keys`); keys a preset sets there are simply unused.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator, Optional

from inrslam.data.open import BUILTIN_PREFIX
from inrslam.errors import ConfigError


@dataclass(frozen=True)
class Variant:
    """`section` (dotted) applies only when the key `selector` is `value`."""

    section: str
    selector: str
    value: str

    def applies(self, cfg: Any) -> tuple[Optional[bool], str]:
        """(True / False / None = not known before the data folder is read (data.dataset auto), what `cfg` selects
        instead, e.g. "render.name is 'neus'")."""
        if self.selector == "data.path":  # data.builtin: built-in scenes only
            path = str(cfg.data.path)
            return path.startswith(BUILTIN_PREFIX), f"data.path is {path!r}"
        if self.selector == "data.dataset":  # reader sections: the reader named or detected
            path, dataset = str(cfg.data.path), str(cfg.data.dataset)
            if path.startswith(BUILTIN_PREFIX):
                return False, f"data.path is {path!r}"
            if dataset == "auto":
                return None, "data.dataset is 'auto'"
            return dataset == self.value, f"data.dataset is {dataset!r}"
        selected = str(get_key(cfg, self.selector))
        return selected == self.value, f"{self.selector} is {selected!r}"


VARIANTS: tuple[Variant, ...] = (
    Variant("render.density", "render.name", "density"),
    Variant("render.neus", "render.name", "neus"),
    Variant("render.volsdf", "render.name", "volsdf"),
    Variant("render.nerf", "render.name", "nerf"),
    Variant("field.mlp", "field.encoding", "mlp"),
    Variant("data.builtin", "data.path", "builtin:NAME"),
    Variant("data.tum", "data.dataset", "tum"),
    Variant("data.neuralrgbd", "data.dataset", "neuralrgbd"),
    Variant("data.sevenscenes", "data.dataset", "7scenes"),
    Variant("ehe", "mapper", "ehe"),
)


def get_key(cfg: Any, key: str) -> Any:
    """Value of the dotted `key` in a config object."""
    for part in key.split("."):
        cfg = getattr(cfg, part)
    return cfg


def leaf_keys(data: dict, prefix: str = "") -> Iterator[str]:
    """Dotted keys of the non-mapping values of a nested mapping."""
    for k, v in data.items():
        if isinstance(v, dict):
            yield from leaf_keys(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}"


def variant_of(key: str) -> Optional[Variant]:
    """The variant whose section holds the dotted `key`, or None for a shared key."""
    return next((v for v in VARIANTS if key.startswith(v.section + ".")), None)


def variant_error(key: str, source: str, variant: Variant, selected: str, old: Optional[str] = None) -> ConfigError:
    """'config key K (from S) applies to render.name=density, but render.name is 'neus''."""
    spelled = f", set as {old!r}" if old else ""
    return ConfigError(f"config key {key!r} (from {source}{spelled}) applies to {variant.selector}={variant.value}, "
                       f"but {selected}")


def check_variant_keys(cfg: Any, baseline: Any, user_keys: dict[str, str], renamed: dict[str, str]) -> None:
    """Raise when a key the user set lies in a section of a variant `cfg` does not select and changes its value.

    Args:
        cfg: the resolved config (every layer).
        baseline: the config of the layers the user did not write (dataclass defaults, presets, faithful layer); a
            key set to the value it has there changes nothing (a run's full `config.yaml` lists every key).
        user_keys: {dotted key: source} of the keys set by the user's files and overrides.
        renamed: {new key: old key} of keys spelled the old way (`aliases.apply_aliases`), for the message.
    """
    for key in sorted(user_keys):
        variant = variant_of(key)
        if variant is None:
            continue
        active, selected = variant.applies(cfg)
        if active is False and get_key(cfg, key) != get_key(baseline, key):
            raise variant_error(key, user_keys[key], variant, selected, renamed.get(key))
