"""Package attributes loaded on first use (PEP 562), so importing a light module of a package does not pay for its
heavy siblings (a sweep worker or `inrslam.eval.trajectory` needs neither torch nor trimesh)."""

from __future__ import annotations

import importlib
from typing import Any, Callable


def lazy_attributes(package: str, namespace: dict[str, Any], sources: dict[str, tuple[str, ...]]
                    ) -> Callable[[str], Any]:
    """A module `__getattr__` for `package`, from `sources` (submodule -> the names it defines): name ->
    `getattr(import package.submodule, name)`, cached in `namespace` (the package's globals()); other names raise
    AttributeError as usual."""
    where = {name: module for module, names in sources.items() for name in names}

    def __getattr__(name: str) -> Any:
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{where[name]}"), name)
        namespace[name] = value
        return value

    return __getattr__
