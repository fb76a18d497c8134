"""inrslam.malloc_env: which glibc malloc settings a run applies, when it leaves them alone, and that they do what
they are for (fewer minor page faults for repeatedly allocated large buffers). Byte-identical results with and
without them: tests/slam/test_end_to_end.py."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from inrslam import malloc_env


class FakeLibc:
    """Records mallopt calls; answers `ok` (glibc: 1 = accepted, 0 = refused)."""

    def __init__(self, ok: int = 1):
        self.calls: list[tuple[int, int]] = []
        self.ok = ok

    def mallopt(self, param: int, value: int) -> int:
        self.calls.append((param, value))
        return self.ok


@pytest.fixture
def fresh(monkeypatch):
    """A process in which tune_malloc has not run yet, with a fake glibc."""
    libc = FakeLibc()
    monkeypatch.setattr(malloc_env, "_state", None)
    monkeypatch.setattr(malloc_env, "_glibc", lambda: libc)
    monkeypatch.delenv(malloc_env.ENV, raising=False)
    return libc


def test_tuned_by_default_with_glibc_and_only_once(fresh):
    state = malloc_env.tune_malloc()
    assert sorted(fresh.calls) == sorted([(-3, 32 * 1024 * 1024), (-1, 1024 ** 3), (-2, 64 * 1024 * 1024)])
    assert state == {"tuned": True, "reason": None, "mmap_threshold": 32 * 1024 * 1024,
                     "trim_threshold": 1024 ** 3, "top_pad": 64 * 1024 * 1024}
    assert malloc_env.tune_malloc() is state and len(fresh.calls) == 3  # once per process
    assert malloc_env.malloc_state() is state


def test_default_leaves_glibc_alone(fresh, monkeypatch):
    monkeypatch.setenv(malloc_env.ENV, "default")
    assert malloc_env.tune_malloc() == {"tuned": False, "reason": "INRSLAM_MALLOC=default"}
    assert fresh.calls == []


def test_unknown_choice_warns_and_tunes(fresh, monkeypatch):
    monkeypatch.setenv(malloc_env.ENV, "fastest")
    with pytest.warns(UserWarning, match="INRSLAM_MALLOC='fastest' is not one of 'default', 'tuned'"):
        assert malloc_env.tune_malloc()["tuned"] is True
    assert len(fresh.calls) == 3


def test_other_c_libraries_and_refusals_are_reported_not_raised(monkeypatch):
    monkeypatch.delenv(malloc_env.ENV, raising=False)
    monkeypatch.setattr(malloc_env, "_state", None)
    monkeypatch.setattr(malloc_env, "_glibc", lambda: None)
    assert malloc_env.tune_malloc() == {"tuned": False, "reason": "the C library is not glibc"}
    monkeypatch.setattr(malloc_env, "_state", None)
    monkeypatch.setattr(malloc_env, "_glibc", lambda: FakeLibc(ok=0))
    assert malloc_env.tune_malloc() == {"tuned": False, "reason": "mallopt refused every setting"}


def test_state_before_any_run(monkeypatch):
    monkeypatch.setattr(malloc_env, "_state", None)
    assert malloc_env.malloc_state() == {"tuned": False, "reason": "not applied"}


PROBE = r"""
import json, resource, sys
import torch
from inrslam.malloc_env import tune_malloc
state = tune_malloc()
def once():  # 25 tensors of 8 MiB written and freed together, as an iteration's (samples, features) buffers
    ts = [torch.empty(8 * 262144).fill_(1.0) for _ in range(25)]
    del ts
once()
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    once()
print(json.dumps({"state": state, "faults": resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0}))
"""


def _huge_pages_always() -> bool:
    try:
        with open("/sys/kernel/mm/transparent_hugepage/enabled") as f:
            return "[always]" in f.read()
    except OSError:
        return False


@pytest.mark.skipif(malloc_env._glibc() is None, reason="the settings apply to glibc's malloc only")
@pytest.mark.skipif(_huge_pages_always(), reason="transparent huge pages 'always': 512x fewer faults either way")
def test_freed_buffers_are_reused_instead_of_faulted_in_again():
    """What the settings are for, counted in minor page faults (not time): 20 rounds of 200 MiB written and freed
    touch 1,024,000 pages; with glibc's own settings it trims the freed heap and faults many of them in again."""
    out = {}
    for mode in ("default", "tuned"):
        env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
        env["INRSLAM_MALLOC"] = mode
        res = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
        out[mode] = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["tuned"]["state"]["tuned"] is True and out["default"]["state"]["tuned"] is False
    assert out["default"]["faults"] > 20_000  # glibc's own settings: freed memory goes back to the OS
    assert out["tuned"]["faults"] * 4 < out["default"]["faults"], out
