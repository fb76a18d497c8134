"""Old config keys still accepted: the one table of renamed keys, applied to every layer before validation.

Presets, `--config` files (and their `inherit_from` chains), overrides, sweep specs and the `config.yaml` of runs
made before the per-variant sections all go through `apply_aliases`, so an old file loads to the same config.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Callable, Optional

from inrslam.errors import ConfigError

KEYFRAME_VARIANT_FRACTION = 0.005
"""`slam.keyframe_fraction` of Table 3's keyframe variant (the old `slam.keyframe_variant: true`)."""


def _keyframe_variant(value: Any, source: str) -> Optional[float]:
    if not isinstance(value, bool):
        raise ConfigError(f"config key 'slam.keyframe_variant' in {source}: expected true or false, got {value!r} "
                          f"(it is now slam.keyframe_fraction: {KEYFRAME_VARIANT_FRACTION} for true)")
    return KEYFRAME_VARIANT_FRACTION if value else None


@dataclass(frozen=True)
class Alias:
    """`old` (dotted key) now spelled `new`. `convert(value, source)` maps the old value to the new one (None = the
    old key is dropped); `wins`: the old key overrides the new one in the same layer (it did so before: the old
    `keyframe_variant` replaced `keyframe_fraction`), else setting both in one layer is an error."""

    old: str
    new: str
    convert: Optional[Callable[[Any, str], Any]] = None
    wins: bool = False


ALIASES: tuple[Alias, ...] = (
    Alias("render.beta", "render.density.beta"),
    Alias("render.learn_beta", "render.density.learn_beta"),
    Alias("render.neus_init_log_inv_s", "render.neus.init_log_inv_s"),
    Alias("render.neus_learn_s", "render.neus.learn_s"),
    Alias("render.neus_normals", "render.neus.normals"),
    Alias("render.neus_fd_eps", "render.neus.fd_eps"),
    Alias("render.neus_anneal_end", "render.neus.anneal_end"),
    Alias("render.volsdf_beta_init", "render.volsdf.beta_init"),
    Alias("render.volsdf_learn_beta", "render.volsdf.learn_beta"),
    Alias("render.volsdf_beta_min", "render.volsdf.beta_min"),
    Alias("render.nerf_activation", "render.nerf.activation"),
    Alias("data.tum_max_dt_depth", "data.tum.max_dt_depth"),
    Alias("data.tum_max_dt_pose", "data.tum.max_dt_pose"),
    Alias("data.neuralrgbd_depth_dir", "data.neuralrgbd.depth_dir"),
    Alias("data.sequence", "data.sevenscenes.sequence"),
    Alias("field.mlp_width", "field.mlp.width"),
    Alias("field.mlp_depth", "field.mlp.depth"),
    Alias("slam.keyframe_variant", "slam.keyframe_fraction", convert=_keyframe_variant, wins=True),
)


def apply_aliases(data: dict, source: str, renamed: Optional[dict[str, str]] = None) -> dict:
    """A copy of the nested layer `data` with every old key moved to its new place.

    Args:
        data: one layer (nested mapping, as read from YAML or `parse_overrides`); not modified.
        source: where the layer came from, for error messages.
        renamed: filled with {new key: old key} for the keys this layer spelled the old way.
    Raises:
        ConfigError: the layer sets both an old key and its new spelling.
    """
    out = copy.deepcopy(data)
    for alias in ALIASES:
        *old_path, old_leaf = alias.old.split(".")
        parent: Any = out
        for part in old_path:
            parent = parent.get(part) if isinstance(parent, dict) else None
        if not isinstance(parent, dict) or old_leaf not in parent:
            continue
        value = parent.pop(old_leaf)
        if alias.convert is not None:
            value = alias.convert(value, source)
            if value is None:
                continue
        *new_path, new_leaf = alias.new.split(".")
        node = out
        for depth, part in enumerate(new_path):
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ConfigError(f"config key {'.'.join(new_path[:depth + 1])!r} in {source}: expected a section "
                                  f"(it holds {alias.new!r}, set there as {alias.old!r}), got {child!r}")
            node = child
        if new_leaf in node and not alias.wins:
            raise ConfigError(f"config keys {alias.old!r} and {alias.new!r} in {source} are the same setting (old "
                              f"and new name); keep only {alias.new!r}")
        node[new_leaf] = value
        if renamed is not None:
            renamed[alias.new] = alias.old
    return out
