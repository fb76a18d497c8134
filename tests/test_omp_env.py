"""The OpenMP wait policy set at `import inrslam` (fresh interpreters: the policy only counts before torch loads)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

PROBE = ("import json, os, sys\n{pre}import inrslam\nfrom inrslam.omp_env import wait_policy\n"
         "print(json.dumps([os.environ.get('OMP_WAIT_POLICY'), wait_policy()]))")


def probe(pre: str = "", **env: str) -> list:
    e = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "INRSLAM_OMP_WAIT")} | env
    out = subprocess.run([sys.executable, "-c", PROBE.format(pre=pre)], env=e, capture_output=True, text=True,
                         check=True).stdout
    return json.loads(out)


def test_import_sets_a_passive_wait_when_nobody_chose_one():
    env, info = probe()
    assert env == "PASSIVE" and info == {"policy": "PASSIVE", "set_by": "inrslam"}


def test_a_users_policy_is_kept():
    env, info = probe(OMP_WAIT_POLICY="ACTIVE")
    assert env == "ACTIVE" and info == {"policy": "ACTIVE", "set_by": "user"}


def test_torch_loaded_first_keeps_the_runtime_default_and_says_so():
    env, info = probe(pre="import torch\n")
    assert env is None and info["policy"] is None and "torch imported before inrslam" in info["set_by"]


def test_the_runtime_default_on_request():
    env, info = probe(INRSLAM_OMP_WAIT="runtime")
    assert env is None and info == {"policy": None, "set_by": "runtime default (INRSLAM_OMP_WAIT=runtime)"}
