"""One registry for every pluggable variant (encodings, rendering functions, datasets, executors).

A variant is a name paired with a class (and optionally its typed config). Lookup errors name the
closest registered name.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import Any, Callable, Generic, TypeVar

from inrslam.errors import InrslamError

T = TypeVar("T")


class UnknownName(InrslamError, KeyError):
    """A name that is not registered (message names the closest registered one)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


@dataclass(frozen=True)
class Entry(Generic[T]):
    name: str
    obj: T
    help: str


class Registry(Generic[T]):
    """Name -> object map with helpful errors.

    >>> r = Registry("encoding")
    >>> @r.register("dense", help="multi-resolution dense grid")
    ... class Dense: ...
    >>> r.get("dense") is Dense
    True
    """

    def __init__(self, kind: str):
        self.kind = kind
        self._entries: dict[str, Entry[T]] = {}

    def register(self, name: str, help: str = "") -> Callable[[T], T]:
        def deco(obj: T) -> T:
            if name in self._entries:
                raise ValueError(f"{self.kind} {name!r} is registered twice")
            self._entries[name] = Entry(name, obj, help)
            return obj

        return deco

    def get(self, name: str) -> T:
        try:
            return self._entries[name].obj
        except KeyError:
            raise UnknownName(self.unknown_message(name)) from None

    def unknown_message(self, name: str) -> str:
        close = difflib.get_close_matches(name, list(self._entries), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        return f"unknown {self.kind} {name!r}{hint} (choices: {', '.join(self.names())})"

    def names(self) -> list[str]:
        return list(self._entries)

    def entries(self) -> list[Entry[T]]:
        return list(self._entries.values())

    def __contains__(self, name: Any) -> bool:
        return name in self._entries

    def describe(self) -> str:
        """One line per entry: 'name: help' (for --help texts)."""
        return "; ".join(f"{e.name}" + (f" ({e.help})" if e.help else "") for e in self._entries.values())
