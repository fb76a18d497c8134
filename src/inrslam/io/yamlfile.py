"""YAML for configs, sweep specs and run directories: safe loading without YAML 1.1 timestamps (a value such as
2023-02-28, e.g. a folder name, stays the string it was written as), and file reads whose every failure is one
`ConfigError` naming the file."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from inrslam.errors import ConfigError

_TIMESTAMP = "tag:yaml.org,2002:timestamp"
_MERGE = "tag:yaml.org,2002:merge"


class _Loader(yaml.SafeLoader):
    """`yaml.SafeLoader` whose implicit resolvers leave out timestamps and whose mappings refuse a key given twice
    (PyYAML would keep the last silently)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        if not isinstance(node, yaml.MappingNode):  # (`!!map [1]`): the base class says what is wrong
            return super().construct_mapping(node, deep=deep)
        first: dict = {}  # key -> mark of its first appearance
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == _MERGE:
                continue
            key = self.construct_object(key_node)
            try:
                seen = key in first
            except TypeError:  # unhashable: the base class reports it
                continue
            if seen:
                problem = f"duplicate key {key!r} (first given on line {first[key].line + 1})"
                raise yaml.constructor.ConstructorError(None, None, problem, key_node.start_mark)
            first[key] = key_node.start_mark
        return super().construct_mapping(node, deep=deep)


_Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != _TIMESTAMP]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}


def parse_yaml(text: str) -> Any:
    """Python objects of a YAML text (safe tags only, no timestamps); `yaml.YAMLError` when it is not valid YAML
    (also for a value its tag cannot hold, e.g. `!!int x`, `!!bool maybe`, and for nesting too deep to read).
    Example: "path: 2023-02-28" -> {"path": "2023-02-28"}."""
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass
    except RecursionError:
        raise yaml.YAMLError("nested too deeply") from None
    except ValueError as e:  # a constructor's own error (bad explicit tag value, e.g. `!!int x`)
        raise yaml.YAMLError(str(e)) from None
    except (TypeError, KeyError, IndexError, AttributeError) as e:  # the same from other constructors (`!!bool x`)
        raise yaml.YAMLError(f"a value its explicit tag cannot hold ({type(e).__name__}: {e})") from None


def load_yaml(path: str | os.PathLike) -> Any:
    """`parse_yaml` of the UTF-8 file at `path`; a `ConfigError` naming the file when it cannot be read (missing,
    unreadable, not UTF-8) or is not valid YAML."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read ({type(e).__name__}: {e})") from None
    try:
        return parse_yaml(text)
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: invalid YAML: {yaml_error_line(e)}") from None


def yaml_error_line(e: yaml.YAMLError) -> str:
    """One line for a YAML error: its problem and where (1-based line and column), without PyYAML's multi-line
    snippet. Example: "mapping values are not allowed here (line 3, column 8)"."""
    if isinstance(e, yaml.MarkedYAMLError):
        mark = e.problem_mark or e.context_mark
        what = "; ".join(str(p) for p in (e.context, e.problem) if p) or type(e).__name__
        return f"{what} (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else what
    return " ".join(str(e).split())
