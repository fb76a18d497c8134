"""Imports only go down the data flow: a package may import only packages of a lower layer (and itself)."""

from __future__ import annotations

import ast
from pathlib import Path

import inrslam

SRC = Path(inrslam.__file__).parent

# lowest first; packages in one layer are siblings and may not import each other
LAYERS = [
    {"errors", "omp_env", "malloc_env", "interrupts", "status", "lazy"},
    {"registry", "io", "machine"},
    {"geometry"},
    {"data"},
    {"scenes"},
    {"fields"},
    {"rendering"},
    {"slam", "eval"},
    {"config"},
    {"datasets"},
    {"runner"},
    {"bench", "viewer"},
    {"api"},
    {"cli"},
    {"__main__"},
]
RANK = {name: i for i, layer in enumerate(LAYERS) for name in layer}


def package_of(path: Path) -> str | None:
    rel = path.relative_to(SRC)
    return None if rel.parts == ("__init__.py",) else rel.parts[0].removesuffix(".py")


def imported_packages(path: Path) -> set[str]:
    """First component under `inrslam` of every import in the file, at any depth (function-level ones too)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + ([f"{node.module}.{a.name}" for a in node.names] if node.module == "inrslam"
                                     else [])
        for name in names:
            parts = name.split(".")
            if parts[0] == "inrslam" and len(parts) > 1 and parts[1] != "__version__":
                out.add(parts[1])
    return out


def test_every_package_has_a_layer():
    packages = {package_of(p) for p in SRC.rglob("*.py")} - {None}
    assert packages <= set(RANK), f"add to LAYERS: {sorted(packages - set(RANK))}"


def test_the_check_sees_imports_inside_functions(tmp_path):
    mod = tmp_path / "m.py"
    mod.write_text("def f():\n    from inrslam.scenes import load_scene\n    import inrslam.bench.sweep\n"
                   "from inrslam import cli\n")
    assert imported_packages(mod) == {"scenes", "bench", "cli"}


def test_imports_only_go_down():
    bad = []
    for path in sorted(SRC.rglob("*.py")):
        pkg = package_of(path)
        if pkg is None:
            continue
        for dep in imported_packages(path) - {pkg}:
            if dep not in RANK or RANK[dep] >= RANK[pkg]:
                bad.append(f"{path.relative_to(SRC)} ({pkg}) imports inrslam.{dep}")
    assert not bad, "imports that do not go down:\n" + "\n".join(bad)
