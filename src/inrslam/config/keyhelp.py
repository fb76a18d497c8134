"""Each config key's help, read from the comment after its field in the dataclass source
(`track_iters: int = 20  # pose iterations per frame`), and the resolved config as YAML with that help beside
every key (`inrslam config`)."""

from __future__ import annotations

import dataclasses
import inspect
import re
from functools import lru_cache
from typing import Any

import yaml

from inrslam.config.loader import config_to_dict

_FIELD = re.compile(r"^(\s+)(\w+)\s*:[^#]*#\s*(.+?)\s*$")


@lru_cache(maxsize=None)
def field_comments(cls: type) -> dict[str, str]:
    """{field name: its trailing comment} of a dataclass, from its source (fields of the class body only)."""
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return {}
    names = {f.name for f in dataclasses.fields(cls)}
    start = next((k + 1 for k, line in enumerate(lines) if line.lstrip().startswith("class ")), len(lines))
    body = None  # indentation of the class body's statements
    out: dict[str, str] = {}
    for line in lines[start:]:
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        body = indent if body is None else body
        m = _FIELD.match(line)
        if m and len(m.group(1)) == body and m.group(2) in names:
            out[m.group(2)] = m.group(3)
    return out


def _scalar(value: Any) -> str:
    return yaml.safe_dump(value, default_flow_style=True, width=10**6).strip().removesuffix("\n...").strip()


def _emit(obj: Any, plain: dict, indent: int, lines: list[str]) -> None:
    helps = field_comments(type(obj))  # type: ignore[arg-type]
    pad = " " * indent
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        note = f"  # {helps[f.name]}" if f.name in helps else ""
        if dataclasses.is_dataclass(value):
            lines.append(f"{pad}{f.name}:{note}")
            _emit(value, plain[f.name], indent + 2, lines)
        else:
            lines.append(f"{pad}{f.name}: {_scalar(plain[f.name])}{note}")


def commented_config(cfg: Any) -> str:
    """The resolved config as YAML with each key's help as a comment (loads to the same values as `dump_config`)."""
    lines: list[str] = []
    _emit(cfg, config_to_dict(cfg), 0, lines)
    return "\n".join(lines) + "\n"
