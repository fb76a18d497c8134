"""inrslam.machine: the CPU model, cache and memory a run records in run_info.json and benchmarks print."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from inrslam import machine

CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC   7B13 64-Core Processor
flags\t\t: fpu vme

processor\t: 1
model name\t: something else
"""


def test_cpu_model_is_the_first_model_name_with_its_spaces_collapsed():
    assert machine.cpu_model(CPUINFO) == "AMD EPYC 7B13 64-Core Processor"


def test_cpu_model_without_a_model_name_falls_back_to_the_platform():
    # an ARM /proc/cpuinfo has no 'model name'; an empty value counts as missing too
    expected = platform.processor() or platform.machine() or "unknown"
    assert machine.cpu_model("processor\t: 0\nBogoMIPS\t: 50.00\n") == expected
    assert machine.cpu_model("model name\t:   \n") == expected


def test_memory_gib_reads_memtotal_in_kib():
    assert machine.memory_gib("MemFree: 1 kB\nMemTotal:       24641536 kB\n") == 23.5
    assert machine.memory_gib("MemFree: 1 kB\n") is None
    assert machine.memory_gib("MemTotal: lots kB\n") is None


def test_last_level_cache_is_the_highest_level(tmp_path):
    for name, level, size in (("index0", "1", "32K"), ("index1", "1", "32K"), ("index2", "2", "512K"),
                              ("index3", "3", "32768K")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "level").write_text(level + "\n")
        (tmp_path / name / "size").write_text(size + "\n")
    (tmp_path / "index4").mkdir()  # an entry the kernel left without files is skipped
    assert machine.last_level_cache(tmp_path) == "32768K"
    assert machine.last_level_cache(tmp_path / "absent") is None


def test_machine_and_cpu_line_describe_this_process():
    info = machine.machine()
    assert set(info) == {"cpu", "cores", "usable_cores", "last_level_cache", "memory_gib", "system", "openblas_core"}
    assert info["cores"] == os.cpu_count() and 1 <= info["usable_cores"] <= info["cores"]
    assert info["system"] == platform.system() and info["cpu"]
    line = machine.cpu_line()
    assert line.startswith(f"{info['cpu']}, {info['cores']} cores")
    if info["last_level_cache"]:
        assert line.endswith(f"last-level cache {info['last_level_cache']}")


def _openblas_core_in_child(env: dict) -> str:
    code = "from inrslam.machine import openblas_core; print(openblas_core())"
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          check=True).stdout.strip()


def test_openblas_core_names_the_kernel_set_openblas_coretype_forces():
    """OpenBLAS reads OPENBLAS_CORETYPE when it loads: a child process started with it set reports that kernel set.
    Only x86 kernel sets older than any AVX-512 one are forced (a machine may pin them because newer ones fail with
    its OpenBLAS), and the pin is never removed here."""
    core_here = machine.openblas_core()
    if core_here is None or platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("needs an x86 OpenBLAS whose kernel name can be read (SciPy's wheels bring one)")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_VERBOSE"}
    for core in ("Haswell", "Sandybridge"):
        assert _openblas_core_in_child({**env, "OPENBLAS_CORETYPE": core}) == core
    if os.environ.get("OPENBLAS_CORETYPE"):  # this process's own pin is what it reports
        assert core_here.lower() == os.environ["OPENBLAS_CORETYPE"].lower()


def test_openblas_core_reads_none_without_a_loaded_openblas():
    maps = "7f00-7f01 r-xp 00000000 00:00 0 /usr/lib/x86_64-linux-gnu/libc.so.6\n"
    assert machine.openblas_core(maps) is None
