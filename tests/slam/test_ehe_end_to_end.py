"""`--preset ehe` end to end on a tiny built-in run: outputs and metrics, the map reloads and renders, a resumed
run equals an uninterrupted one, and the config errors of the ehe section."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from interrupted import run_interrupted

from inrslam.cli import main
from inrslam.config import load_config
from inrslam.datasets import open_dataset
from inrslam.errors import ConfigError
from inrslam.io.trajectory import read_tum
from inrslam.runner import resume_slam, run_slam
from inrslam.runner.loaded import load_run
from inrslam.slam.systems import system_class

FRAMES = 5
# 96 x 72 px: a 10 cm voxel at 2 m holds ~15 points, so allocate from 3; few iterations, light evaluation
TINY = [f"data.max_frames={FRAMES}", "data.builtin.width=96", "data.builtin.height=72", "ehe.min_points=2",
        "ehe.first_iters=30", "ehe.iters=4", "ehe.rays=512", "ehe.mesh_samples=4", "slam.checkpoint_every=2",
        "output.tensorboard=false", "eval.heldout_max=1",
        "eval.cull_every=2", "seed=2"]


def ehe_cfg(extra=()):
    return load_config(preset="ehe", overrides=TINY + list(extra))


@pytest.fixture(scope="module")
def ehe_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("ehe") / "a"
    run_slam(ehe_cfg(), out)
    return out


def test_an_ehe_run_writes_mesh_metrics_and_the_given_poses(ehe_run):
    cfg = ehe_cfg()
    gt = open_dataset(cfg.data).poses
    ts, est = read_tum(ehe_run / "trajectory.txt")
    assert len(ts) == FRAMES and np.allclose(est, gt, atol=1e-6)
    m = json.loads((ehe_run / "metrics.json").read_text())
    assert m["mapper"] == "ehe" and m["encoding"] == "ehe" and m["poses"] == "gt"
    assert m["ehe_voxels"] > 0 and m["ehe_priors_initialised"] > 0 and m["map_ms_per_frame"] > 0
    assert m["acc_m"] < 0.03 and m["psnr_db"] > 15  # 96 x 72 px, 5 frames, 30 + 4 iterations
    assert (ehe_run / "mesh.ply").stat().st_size > 0
    log = [json.loads(line) for line in (ehe_run / "log.jsonl").read_text().splitlines()]
    maps = [r for r in log if r["type"] == "map"]
    assert [r["frame"] for r in maps] == list(range(FRAMES)) and maps[0]["iters"] == 30
    assert all(1 <= r["iters"] <= 4 for r in maps[1:])


def test_the_run_reloads_as_an_ehe_model_that_renders(ehe_run):
    run = load_run(ehe_run)
    rgb, depth = run.render(run.est[1])
    assert rgb.shape == (72, 96, 3) and depth.shape == (72, 96)
    assert np.mean(depth > 0) > 0.5  # most rays hit the voxels of the frames seen


def test_a_resumed_ehe_run_equals_the_uninterrupted_one(ehe_run, tmp_path):
    out = tmp_path / "cut"

    run_interrupted(ehe_cfg(["eval.enabled=false"]), out, 2)  # evaluation off: it does not change the map
    assert (out / "checkpoints" / "latest.pt").exists() and not (out / "metrics.json").exists()
    resume_slam(out)
    a = json.loads((ehe_run / "metrics.json").read_text())
    b = json.loads((out / "metrics.json").read_text())
    for key in ("psnr_process_db", "depth_l1_process_m", "ehe_voxels", "ehe_priors_initialised", "ehe_keyframes"):
        assert a[key] == b[key], key
    assert (out / "mesh.ply").read_bytes() == (ehe_run / "mesh.ply").read_bytes()
    assert (out / "trajectory.txt").read_bytes() == (ehe_run / "trajectory.txt").read_bytes()


@pytest.mark.parametrize("scene,filtered", [("handheld", True), ("room", False)])
def test_the_ehe_loop_maps_noisy_depth_after_the_bilateral_filter_and_clean_depth_as_it_is(scene, filtered,
                                                                                          monkeypatch):
    from inrslam.slam.ehe.system import EheSystem
    from inrslam.slam.registration import filtered_depth

    mapped = []  # the depth each frame's mapping (allocation, priors, rays, keyframe store) received
    map_ehe = EheSystem._map_ehe
    monkeypatch.setattr(EheSystem, "_map_ehe",
                        lambda self, i, ft, c2w, *a: (mapped.append(ft.depth.numpy().copy()),
                                                      map_ehe(self, i, ft, c2w, *a))[1])
    for off in (False, True):
        cfg = ehe_cfg([f"data.path=builtin:{scene}", "ehe.first_iters=2", "ehe.iters=1"]
                      + ["slam.map_filtered_depth=false"] * off)
        ds = open_dataset(cfg.data)
        system = system_class(cfg)(cfg, ds)
        records = system.process(0) + system.process(1)
        maps = [r for r in records if r["type"] == "map"]
        assert [r["depth_filtered"] for r in maps] == [filtered and not off] * 2
        noise = [r["depth_noise"] for r in maps]  # judged per frame (not at all with the key off)
        if off:
            assert noise == [None, None]
        elif filtered:  # handheld: 4 mm at 1 m
            assert all(0.002 < n < 0.008 for n in noise), noise
        else:  # room: noise-free (no estimate, or below the gate)
            assert all(n is None or n < 0.002 for n in noise), noise
        for i in (0, 1):
            raw, got = ds[i].depth, mapped.pop(0).reshape(ds[i].depth.shape)
            if filtered and not off:  # handheld: 4 mm at 1 m, above the 2 mm gate
                assert np.array_equal(got, filtered_depth(raw, cfg.slam.gicp).astype(np.float32))
                true = ds.true_depth(i)
                v = (raw > 0) & (got > 0) & (true > 0)
                assert np.abs(got - true)[v].mean() < 0.8 * np.abs(raw - true)[v].mean()  # the noise is reduced
            else:  # noise-free depth below the gate, or the key off: the measured depth
                assert np.array_equal(got, raw)


@pytest.mark.parametrize("stride", [1, 3])
def test_frame_points_back_project_every_valid_strided_pixel(stride):
    from inrslam.geometry.camera import pixel_directions
    from inrslam.slam.frame_tensors import FrameTensors

    cfg = ehe_cfg([f"ehe.point_stride={stride}"])
    ds = open_dataset(cfg.data)
    system = system_class(cfg)(cfg, ds)
    for i in (0, 3):  # the second frame reuses the cached pixel grid
        frame = ds[i]
        ft = FrameTensors(frame, torch.device("cpu"))
        c2w = torch.as_tensor(frame.c2w, dtype=torch.float32)
        got = system._frame_points(ft, c2w)
        H, W = frame.depth.shape
        v, u = np.mgrid[0:H:stride, 0:W:stride]
        z = frame.depth[v, u]
        ok = (z > cfg.ehe.depth_min) & (z < cfg.ehe.depth_max)
        u, v, z = torch.from_numpy(u[ok]), torch.from_numpy(v[ok]), torch.from_numpy(z[ok]).float()
        cam = pixel_directions(frame.intrinsics, u.float(), v.float()) * z[:, None]
        # row-major pixel order; one rounding apart at most (equal to the bit here: geometry.backproject)
        torch.testing.assert_close(got, cam @ c2w[:3, :3].T + c2w[:3, 3], rtol=1e-6, atol=1e-6)
        assert got.shape[0] > 0.5 * H * W / stride**2


def test_ehe_config_errors_are_one_line(capsys, tmp_path):
    with pytest.raises(ConfigError, match="unknown config key 'ehe.voxel_sise'.*did you mean 'ehe.voxel_size'"):
        load_config(preset="ehe", overrides=["ehe.voxel_sise=0.1"])
    with pytest.raises(ConfigError, match=r"'ehe.margin'.*expected a number in \[0, 0.5\]"):
        load_config(preset="ehe", overrides=["ehe.margin=0.7"])
    with pytest.raises(ConfigError, match="applies to mapper=ehe"):
        load_config(preset="paper", overrides=["ehe.iters=3"])
    with pytest.raises(ConfigError, match="unknown mapper 'eh'; did you mean 'ehe'"):
        system_class(load_config(preset="ehe", overrides=["mapper=eh"], check_variants=False))
    cfg = load_config(preset="ehe", overrides=TINY + ["slam.poses="])
    with pytest.raises(ConfigError, match="maps with given poses"):
        system_class(cfg)(cfg, open_dataset(cfg.data))
    rc = main(["run", "--preset", "ehe", "--out", str(tmp_path / "r"), "--quiet", "ehe.rays=0"])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and len(err.splitlines()) == 1 and "ehe.rays" in err


def test_the_ehe_loops_config_protocol_names_run_config_sections():
    """`EheRunConfig` (slam may not import the config layer) names RunConfig's sections with their types."""
    import typing

    from inrslam.config import RunConfig
    from inrslam.slam.ehe.system import EheRunConfig

    wanted, run = typing.get_type_hints(EheRunConfig), typing.get_type_hints(RunConfig)
    assert {k: run[k] for k in wanted} == wanted


def test_touched_rows_is_an_ablation_key_of_the_dense_level(tmp_path):
    """`ehe.touched_rows` reaches the dense level; "read" and "gradient" map the same frames to different maps
    (rows read only by samples without gradient keep their momentum steps or not), each deterministic."""
    from inrslam.fields.config import TouchedRows
    from inrslam.slam.ehe.model import EheModel

    bounds = np.array([[-1.0, 1.0], [-1.0, 1.0], [0.0, 2.0]])
    assert EheModel(ehe_cfg(), bounds).field.grid.touched == TouchedRows.GRADIENT  # the preset's setting
    assert EheModel(ehe_cfg(["ehe.touched_rows=read"]), bounds).field.grid.touched == TouchedRows.READ
    with pytest.raises(ConfigError, match="ehe.touched_rows"):
        ehe_cfg(["ehe.touched_rows=all"])
    tables = {}
    for touched in ("read", "gradient", "gradient"):
        out = tmp_path / f"{touched}{len(tables)}"
        run_slam(ehe_cfg([f"ehe.touched_rows={touched}", "data.max_frames=3", "eval.enabled=false",
                          "mesh.enabled=false"]), out)
        tables[out.name] = load_run(out).model.field.grid.table.detach().clone()
    assert torch.equal(tables["gradient1"], tables["gradient2"])
    assert not torch.equal(tables["read0"], tables["gradient1"])
