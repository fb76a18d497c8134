"""Typed configuration: dataclass schema, YAML files with `inherit_from`, presets, command-line overrides."""

from inrslam.config.loader import config_to_dict, dump_config, load_config, parse_overrides
from inrslam.config.schema import RunConfig

__all__ = ["RunConfig", "load_config", "config_to_dict", "dump_config", "parse_overrides"]
