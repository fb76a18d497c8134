"""What machine a run or benchmark ran on: CPU model, cores, last-level cache and memory.

Times in this project are compared across days and machines (README tables, docs/speed.md, docs/ehe.md). The same
code has measured 1.2-1.8x apart on "the same" 2-core machine two days apart (docs/ehe.md §7), so every
`run_info.json` records `machine()` and every benchmark's first line names the CPU (`cpu_line`). Read from Linux's
/proc and /sys; elsewhere the fields that cannot be read are None (the CPU model falls back to
`platform.processor()`).
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

from inrslam.omp_env import cpu_set

CPUINFO = Path("/proc/cpuinfo")
MEMINFO = Path("/proc/meminfo")
CACHE_DIR = Path("/sys/devices/system/cpu/cpu0/cache")


def _read(path: Path) -> str | None:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return None


def cpu_model(cpuinfo: str | None = None) -> str:
    """The first 'model name' of /proc/cpuinfo (`cpuinfo`: its text, for tests), else `platform.processor()` or
    `platform.machine()`."""
    text = _read(CPUINFO) if cpuinfo is None else cpuinfo
    for line in (text or "").splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() == "model name" and value.strip():
            return " ".join(value.split())
    return platform.processor() or platform.machine() or "unknown"


def last_level_cache(cache_dir: Path = CACHE_DIR) -> str | None:
    """Size of cpu0's highest cache level as the kernel writes it (e.g. '32768K'), or None."""
    best: tuple[int, str] | None = None
    for index in sorted(cache_dir.glob("index*")) if cache_dir.is_dir() else []:
        level, size = _read(index / "level"), _read(index / "size")
        if level and size and level.strip().isdigit() and (best is None or int(level) > best[0]):
            best = (int(level), size.strip())
    return best[1] if best else None


def memory_gib(meminfo: str | None = None) -> float | None:
    """MemTotal of /proc/meminfo (`meminfo`: its text, for tests) in GiB, rounded to 0.1, or None."""
    text = _read(MEMINFO) if meminfo is None else meminfo
    for line in (text or "").splitlines():
        if line.startswith("MemTotal:"):
            parts = line.split()
            if len(parts) >= 2 and parts[1].isdigit():
                return round(int(parts[1]) / 1024 ** 2, 1)
    return None


#: Names under which OpenBLAS builds export their kernel name (plain, and SciPy's / NumPy's prefixed wheels).
_CORENAME_SYMBOLS = ("openblas_get_corename", "scipy_openblas_get_corename", "scipy_openblas_get_corename64_",
                     "openblas_get_corename64_")


def openblas_core(maps: str | None = None) -> str | None:
    """The kernel set ('Haswell', 'SkylakeX', ...) of the OpenBLAS that the fused decoders' products run on (SciPy's,
    which numba's ``np.dot`` calls), or None where it cannot be read (no OpenBLAS, not Linux). It decides their
    speed: on a CPU with AVX-512 the SkylakeX kernels run the decoders' small products 2-4x faster than Haswell's,
    and ``OPENBLAS_CORETYPE`` overrides OpenBLAS's own choice (docs/speed.md, "Which BLAS kernels"). `maps`: the text
    of /proc/self/maps, for tests."""
    import ctypes

    try:
        import scipy.linalg.cython_blas  # noqa: F401  (loads SciPy's OpenBLAS, as numba does for np.dot)
    except ImportError:
        return None
    text = _read(Path("/proc/self/maps")) if maps is None else maps
    paths = sorted({line.split()[-1] for line in (text or "").splitlines()
                    if "openblas" in line.rsplit("/", 1)[-1].lower() and "/" in line})
    paths.sort(key=lambda p: "scipy.libs" not in p)  # SciPy's own first: the one numba calls
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _CORENAME_SYMBOLS:
            fn = getattr(lib, name, None)
            if fn is not None:
                fn.restype = ctypes.c_char_p
                core = fn()
                return core.decode(errors="replace").strip() if core else None
    return None


def machine() -> dict:
    """{"cpu": model, "cores": os.cpu_count(), "usable_cores", "last_level_cache", "memory_gib", "system",
    "openblas_core"}."""
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "usable_cores": len(cpu_set()),
            "last_level_cache": last_level_cache(), "memory_gib": memory_gib(), "system": platform.system(),
            "openblas_core": openblas_core()}


def cpu_line() -> str:
    """'<CPU model>, <n> cores[ (<k> usable)][, last-level cache <size>]', for a benchmark's '# machine:' line."""
    n, usable = os.cpu_count() or 1, len(cpu_set())
    cores = f"{n} cores" if usable >= n else f"{n} cores ({usable} usable)"
    cache = last_level_cache()
    return f"{cpu_model()}, {cores}" + (f", last-level cache {cache}" if cache else "")
