"""Light modules stay light: a sweep worker and the trajectory maths load neither torch nor trimesh, while the
packages' public names still resolve (loaded on first use)."""

from __future__ import annotations

import subprocess
import sys

import pytest


def _loaded_after(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", f"{code}\nimport sys\nprint(' '.join(sorted(sys.modules)))"],
                         capture_output=True, text=True, check=True).stdout
    return set(out.split())


@pytest.mark.parametrize("code", ["import inrslam.bench.worker, inrslam.bench.testing",
                                  "import inrslam.eval.trajectory"])
def test_light_modules_do_not_load_torch_or_trimesh(code):
    loaded = _loaded_after(code)
    assert "torch" not in loaded and "trimesh" not in loaded


def test_package_names_resolve_on_first_use():
    import inrslam.bench as bench
    import inrslam.eval as ev
    from inrslam.eval import ate, psnr
    from inrslam.eval.image import psnr as psnr_direct
    from inrslam.eval.trajectory import ate as ate_direct

    assert psnr is psnr_direct and ate is ate_direct
    assert callable(bench.run_sweep) and bench.build_report.__module__ == "inrslam.bench.report"
    assert all(getattr(ev, n) is not None for n in ev.__all__) and all(getattr(bench, n) for n in bench.__all__)
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        ev.nope  # noqa: B018
