"""The registry of SLAM loops (`mapper` config key): which system class a run builds."""

from __future__ import annotations

from inrslam.errors import ConfigError
from inrslam.registry import Registry
from inrslam.slam.ehe.system import EheSystem
from inrslam.slam.model import SceneModel
from inrslam.slam.system import SlamSystem

SYSTEMS: Registry[type[SlamSystem]] = Registry("mapper")
SYSTEMS.register("neural", help="the F x G SLAM loop (tracking or given poses; field / render sections)")(SlamSystem)
SYSTEMS.register("ehe", help="Explicit Hybrid Encoding mapper, given poses only (ehe section; docs/ehe.md)")(EheSystem)


def system_class(cfg) -> type[SlamSystem]:
    """The loop class `cfg.mapper` names (ConfigError naming the closest one when unknown)."""
    name = getattr(cfg, "mapper", "neural")
    if name not in SYSTEMS:
        raise ConfigError(f"config key 'mapper': {SYSTEMS.unknown_message(name)}")
    return SYSTEMS.get(name)


def model_class(cfg) -> type:
    """The scene-model class of `cfg.mapper`'s loop (what `LoadedRun.model` rebuilds from a checkpoint)."""
    return getattr(system_class(cfg), "model_class", SceneModel)
