"""Command-line interface: `inrslam.cli.main` on tiny inputs (no SLAM run)."""

from __future__ import annotations

import json
import os

import pytest
import yaml

from inrslam.bench.testing import write_fake_run
from inrslam.cli import main
from inrslam.fields.registry import ENCODINGS
from inrslam.rendering import RENDERERS


def _fake_run(tmp_path, eval_section: dict):
    """A finished run directory whose config.yaml carries a non-default evaluation protocol."""
    rd = write_fake_run(tmp_path / "run", "hash", "direct", frames=12)
    cfg = yaml.safe_load((rd / "config.yaml").read_text())
    cfg["eval"] = eval_section
    (rd / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return rd


def test_eval_run_dir_uses_the_runs_protocol(tmp_path, capsys):
    rd = _fake_run(tmp_path, {"align": "sim3", "n_samples": 1234, "icp": True, "max_time_diff": 0.005})
    assert main(["eval", str(rd), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    proto = json.loads((rd / "metrics.json").read_text())["protocol"]
    assert printed["protocol"] == proto
    assert proto["n_samples"] == 1234
    assert proto["alignment"] == "sim3" and proto["icp"] is True
    assert proto["association"]["max_diff_s"] == 0.005
    assert json.loads((rd / "metrics.json").read_text())["ate_rmse_m"] is not None


def test_eval_run_dir_explicit_flags_override_the_run(tmp_path, capsys):
    rd = _fake_run(tmp_path, {"align": "sim3", "n_samples": 1234, "icp": True})
    assert main(["eval", str(rd), "--align", "none", "--max-diff", "0.01", "--json"]) == 0
    proto = json.loads((rd / "metrics.json").read_text())["protocol"]
    assert proto["alignment"] == "none" and proto["association"]["max_diff_s"] == 0.01
    assert proto["n_samples"] == 1234 and proto["icp"] is True  # not given: the run's values
    assert main(["eval", str(rd), "--cull-gt", "--json"]) == 0
    proto = json.loads((rd / "metrics.json").read_text())["protocol"]
    assert proto["culling"]["culled"] == "reconstructed and ground-truth meshes"


def test_eval_run_dir_without_config_uses_defaults(tmp_path, capsys):
    rd = _fake_run(tmp_path, {})
    (rd / "config.yaml").unlink()
    assert main(["eval", str(rd), "--icp", "--json"]) == 0
    proto = json.loads((rd / "metrics.json").read_text())["protocol"]
    assert proto["n_samples"] == 200_000 and proto["alignment"] == "se3" and proto["icp"] is True


def test_eval_traj_defaults(tmp_path, capsys):
    rd = write_fake_run(tmp_path / "run", "hash", "direct", frames=12)
    assert main(["eval", "--traj", str(rd / "trajectory.txt"), "--gt", str(rd / "trajectory_gt.txt"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["protocol"]["alignment"] == "se3"
    assert out["protocol"]["association"]["max_diff_s"] == 0.02


def test_scenes_lists_builtin_scenes(capsys):
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in ("room", "cluttered", "thin"):
        assert name in out


def test_run_unknown_key_is_a_config_error(tmp_path, capsys):
    assert main(["run", "--out", str(tmp_path / "run"), "--quiet", "slam.trak_iters=3"]) == 2
    err = capsys.readouterr().err
    assert "slam.trak_iters" in err and "slam.track_iters" in err
    assert not (tmp_path / "run" / "trajectory.txt").exists()


def test_config_prints_loadable_yaml(capsys):
    assert main(["config", "--preset", "quick"]) == 0
    cfg = yaml.safe_load(capsys.readouterr().out)
    assert isinstance(cfg, dict)
    assert set(cfg) >= {"data", "field", "render", "sampling", "loss", "slam", "mesh", "eval", "output", "seed",
                        "device", "faithful"}
    assert "track_iters" in cfg["slam"] and "n_samples" in cfg["eval"]


def test_run_help_lists_every_encoding_and_renderer(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["run", "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())  # undo argparse's line wrapping
    for name in list(ENCODINGS.names()) + list(RENDERERS.names()):
        assert f"{name} (" in text, name


def test_eval_run_dir_reads_only_the_eval_section(tmp_path, capsys):
    """A run written by another version (a key this version does not know outside `eval`) still evaluates; an
    unknown key inside `eval` is still an error naming the file."""
    rd = _fake_run(tmp_path, {"n_samples": 999})
    cfg = yaml.safe_load((rd / "config.yaml").read_text())
    cfg.setdefault("sampling", {})["retired_key"] = 1
    (rd / "config.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["eval", str(rd), "--json"]) == 0
    assert json.loads((rd / "metrics.json").read_text())["protocol"]["n_samples"] == 999
    cfg["eval"]["n_sample"] = 5
    (rd / "config.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["eval", str(rd)]) == 2
    err = capsys.readouterr().err
    assert "eval.n_sample" in err or "n_sample" in err
    assert "config.yaml" in err


def test_overrides_anywhere_on_the_command_line(capsys):
    assert main(["config", "slam.track_iters=7", "--preset", "quick", "field.levels=3", "mesh.resolution=0.05"]) == 0
    cfg = yaml.safe_load(capsys.readouterr().out)
    assert cfg["slam"]["track_iters"] == 7 and cfg["field"]["levels"] == 3 and cfg["mesh"]["resolution"] == 0.05


def test_a_stray_word_among_the_flags_is_still_unrecognised(capsys):
    with pytest.raises(SystemExit) as e:
        main(["config", "--preset", "quick", "slam.track_iters=7", "--preset", "quick", "stray"])
    assert e.value.code == 2
    assert "unrecognized arguments: stray" in capsys.readouterr().err


def test_config_shows_each_keys_help_and_still_loads(capsys):
    from inrslam.config import load_config
    from inrslam.config.loader import config_to_dict

    assert main(["config", "--preset", "fast"]) == 0
    text = capsys.readouterr().out
    assert yaml.safe_load(text) == config_to_dict(load_config(preset="fast"))
    lines = text.splitlines()
    assert "  track_iters: 20  # pose iterations per frame" in lines
    assert "    max_iterations: 15  # Gauss-Newton iterations" in lines  # nested section, preset value
    keys = [line for line in lines if line.startswith("  ") and not line.rstrip().endswith(":")]
    assert all("  # " in line for line in keys)  # every key has its help
    assert main(["config", "--plain"]) == 0
    assert "#" not in capsys.readouterr().out


@pytest.mark.parametrize("key", ["field.kernel", "field.decoder_kernel", "loss.kernel", "render.kernel"])
def test_a_cpu_only_kernel_on_a_gpu_device_is_a_one_line_config_error(monkeypatch, key):
    import re

    import torch

    import inrslam.slam.system as system_mod
    from inrslam.cli import _check_device
    from inrslam.config import load_config
    from inrslam.errors import ConfigError

    monkeypatch.setattr(system_mod, "resolve_device", lambda name: torch.device("cuda"))  # as on a GPU machine
    with pytest.raises(ConfigError, match=rf"config key '{re.escape(key)}': 'numba' runs on CPU tensors only.*cuda"):
        _check_device(load_config(preset="quick", overrides=[f"{key}=numba"]))
    _check_device(load_config(preset="quick", overrides=[f"{key}=auto"]))  # auto picks torch there: fine
    monkeypatch.setattr(system_mod, "resolve_device", lambda name: torch.device("cpu"))
    _check_device(load_config(preset="quick", overrides=[f"{key}=numba"]))  # and numba on the CPU


@pytest.mark.parametrize("args,message", [
    (["--mesh", "a.ply", "--gt-mesh", "b.ply", "--intrinsics", "1,2,x,4,5,6"], "--intrinsics expects fx,fy,cx,cy"),
    (["--mesh", "a.ply", "--gt-mesh", "b.ply", "--intrinsics", "50,50,32,24,64.5,48"], "whole pixels"),
    (["--mesh", "a.ply", "--gt-mesh", "b.ply", "--intrinsics", "0,50,32,24,64,48"], "fx, fy > 0"),
    (["--traj", "a.txt", "--gt", "b.txt", "--max-diff", "-1"], "expected a number of seconds >= 0, got '-1'"),
])
def test_eval_arguments_are_checked_in_one_line(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) if "--max-diff" in args else _no_raise():
        assert main(["eval", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and message in err.splitlines()[-1]  # one error line (argparse: after its usage)


def test_eval_run_dir_with_a_written_over_config_is_one_line(tmp_path, capsys):
    rd = write_fake_run(tmp_path / "run", "hash", "direct", frames=12)
    (rd / "config.yaml").write_text("eval: [1, 2]\n")
    assert main(["eval", str(rd)]) == 2
    assert "config.yaml: eval: expected a mapping, got list" in capsys.readouterr().err


def _no_raise():
    import contextlib

    return contextlib.nullcontext()


@pytest.mark.parametrize("flags", [["--preset", "paper"], ["--preset", "accurate"], ["--overwrite"]])
def test_resume_refuses_a_preset_or_overwrite_it_would_ignore(tmp_path, capsys, flags):
    run = write_fake_run(tmp_path / "runs", "dense", "density", frames=4)
    assert main(["run", "--resume", str(run), *flags]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"do not combine it with {flags[0]}" in err


def test_ctrl_c_in_export_leaves_nothing_and_says_so(tmp_path, capsys, monkeypatch):
    import inrslam.scenes.export as export

    real = export._save_image
    calls = []

    def interrupted(path, img, **kw):  # Ctrl-C at the fourth picture
        calls.append(path)
        if len(calls) == 4:
            raise KeyboardInterrupt
        real(path, img, **kw)

    monkeypatch.setattr(export, "_save_image", interrupted)
    out = tmp_path / "room_tum"
    assert main(["export", "room", "--layout", "tum", "--out", str(out), "--frames", "3", "--width", "32",
                 "--height", "24"]) == 130
    err = capsys.readouterr().err
    assert err == f"inrslam export: interrupted; nothing was exported to {out} (an export is written as a whole)\n"
    assert len(calls) == 4 and not out.exists() and os.listdir(tmp_path) == []


def test_ctrl_c_in_bench_prints_the_command_that_resumes_it(tmp_path):
    """The resume line keeps the executor flags (a SLURM sweep must not go on locally on the login node) and
    quotes paths with spaces, so it can be pasted as printed."""
    import shlex

    from inrslam.cli import _interrupted_message, build_parser

    argv = ["bench", "my spec.yaml", "--out", "runs/my sweep", "--executor", "slurm", "--partition", "gpu",
            "--time", "90", "--jobs", "3"]
    line = _interrupted_message(build_parser().parse_args(argv))
    command = line.split("resume the sweep with ", 1)[1]
    assert shlex.split(command) == ["inrslam", "bench", "my spec.yaml", "--out", "runs/my sweep", "--jobs", "3",
                                    "--executor", "slurm", "--partition", "gpu", "--time", "90"]
    plain = _interrupted_message(build_parser().parse_args(["bench", "s.yaml", "--out", "o"]))
    assert plain.endswith("resume the sweep with inrslam bench s.yaml --out o")


def test_a_failed_write_is_one_line_naming_the_file(monkeypatch, capsys):
    """Disk full, a file-size limit, a read-only folder: the OSError of a write is one line, not a traceback."""
    import errno

    from inrslam import cli

    def too_large(args):
        raise OSError(errno.EFBIG, "File too large", "runs/x/metrics.json")

    monkeypatch.setitem(cli.COMMANDS, "scenes", too_large)
    assert cli.main(["scenes"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("inrslam scenes: error: runs/x/metrics.json: File too large")


def test_outputs_line_lists_only_files_the_run_wrote(tmp_path):
    """A run whose map held no surface writes no mesh.ply: the closing line must not list one."""
    from rich.console import Console

    from inrslam.cli import _print_metrics

    rd = write_fake_run(tmp_path / "run", "dense", "density", frames=4)
    for name in ("trajectory.txt", "config.yaml"):
        assert (rd / name).exists()
    (rd / "mesh.ply").unlink(missing_ok=True)
    console = Console(record=True, width=400)
    _print_metrics(console, rd)
    line = next(ln for ln in console.export_text().splitlines() if ln.startswith("Outputs in"))
    assert "trajectory.txt" in line and "config.yaml" in line and "mesh.ply" not in line
    (rd / "mesh.ply").write_text("ply\n")
    console = Console(record=True, width=400)
    _print_metrics(console, rd)
    assert "mesh.ply" in next(ln for ln in console.export_text().splitlines() if ln.startswith("Outputs in"))
