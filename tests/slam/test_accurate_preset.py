"""The `accurate` and `gicp` presets end to end on a tiny built-in run: each ablation key changes what runs (seen in
log.jsonl), GICP keyframes and the map's fallback, and an interrupted run resumes to the uninterrupted result."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("small_gicp", reason="the accurate / gicp presets need small_gicp (pip install small_gicp)")

from interrupted import run_interrupted  # noqa: E402

from inrslam.config import load_config  # noqa: E402
from inrslam.io.trajectory import read_tum  # noqa: E402
from inrslam.runner import resume_slam, run_slam  # noqa: E402

FRAMES = 8
# a coarse map (6 cm finest cells) and small batches: these tests check which stages run, not the map's quality
LIGHT_MAP = ["slam.init_pixels=512", "field.block_fine=0.06", "field.block_coarse=0.24"]
SMALL = [f"data.max_frames={FRAMES}", "data.builtin.width=96", "data.builtin.height=72", "slam.init_iters=60",
         *LIGHT_MAP, "slam.track_pixels=256", "slam.map_iters=5", "slam.map_pixels=512", "slam.checkpoint_every=2",
         "slam.gicp.pixel_stride=1", "slam.sdf_track.points=2048", "eval.enabled=false", "mesh.enabled=false",
         "output.tensorboard=false", "seed=1"]
# every piece on, on every frame (not only when GICP fails)
ALL_ON = ["slam.sdf_track.only_on_init_failure=false", "slam.track_only_on_init_failure=false",
          "slam.track_iters=4", "slam.bundle_adjust=true"]


def tracks(run_dir) -> list[dict]:
    recs = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]
    return [r for r in recs if r["type"] == "track"]


def run(tmp_path_factory, name, preset, extra=()):
    out = tmp_path_factory.mktemp(name) / "run"
    run_slam(load_config(preset=preset, overrides=SMALL + list(extra)), out)
    return out


@pytest.fixture(scope="module")
def all_on(tmp_path_factory):
    return run(tmp_path_factory, "all_on", "accurate", ALL_ON)


def test_every_piece_runs_when_switched_on(all_on):
    recs = tracks(all_on)
    assert [r["frame"] for r in recs] == list(range(1, FRAMES))
    for r in recs:
        assert 0.0 <= r["gicp_fitness"] <= 1.0 and r["gicp_degeneracy"] >= 0.0  # GICP ran
        assert r["sdf_iters"] >= 1 and r["sdf_points"] > 0  # point-to-surface Gauss-Newton ran
        assert r["iters"] >= 1 and r["loss"] is not None  # rendered refinement ran
    info = json.loads((all_on / "run_info.json").read_text())
    assert info["status"] == "complete"
    # loop closure is on in accurate; a short sequence has no revisit (no keyframe 100 frames older): nothing logged
    assert '"loop_' not in (all_on / "log.jsonl").read_text()
    m = json.loads((all_on / "metrics.json").read_text())
    assert (m["loop_candidates"], m["loop_edges"], m["loops_closed"]) == (0, 0, 0)
    ts, est = read_tum(all_on / "trajectory.txt")
    _, gt = read_tum(all_on / "trajectory_gt.txt")
    # the tracked camera follows the motion (at 96x72 px and 60 initialisation steps the map is coarse)
    motion = np.linalg.norm(gt[:, :3, 3] - gt[0, :3, 3], axis=1).max()
    assert np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1).max() < 0.5 * motion


def test_gicp_keyframe_target_is_renewed_and_previous_target_is_the_last_frame(all_on, tmp_path_factory):
    targets = [r["gicp_target"] for r in tracks(all_on)]  # accurate: slam.gicp.target = local_map (its last keyframe)
    assert targets[0] == 0 and all(t < f for t, f in zip(targets, range(1, FRAMES)))
    baseline = run(tmp_path_factory, "gicp", "gicp")
    recs = tracks(baseline)
    assert [r["gicp_target"] for r in recs] == list(range(0, FRAMES - 1))  # frame-to-frame
    for r in recs:  # the baseline runs no neural tracking at all
        assert r["iters"] == 0 and r["loss"] is None and "sdf_iters" not in r
    _, est = read_tum(baseline / "trajectory.txt")
    _, gt = read_tum(baseline / "trajectory_gt.txt")
    assert np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1).max() < 0.003  # clean synthetic depth: millimetres


def test_neural_tracking_runs_only_where_gicp_failed(tmp_path_factory):
    # an impossible conditioning requirement (smallest / largest eigenvalue >= 2) makes every registration fail:
    # the map takes over on every frame
    out = run(tmp_path_factory, "fallback", "accurate", ["slam.gicp.degeneracy_ratio=2"])
    recs = tracks(out)
    for r in recs:
        assert r["fallback"].startswith("gicp_degenerate")
        assert r["sdf_iters"] >= 1 and r["iters"] >= 1
    events = json.loads((out / "metrics.json").read_text())["fallbacks"]
    assert events == FRAMES - 1


def test_const_velocity_init_skips_gicp(tmp_path_factory):
    out = run(tmp_path_factory, "cv", "accurate", ALL_ON + ["slam.init=const_velocity", "slam.sdf_track.iters=0"])
    for r in tracks(out):
        assert "gicp_fitness" not in r and "sdf_iters" not in r and r["iters"] >= 1


def test_without_gicp_the_only_on_failure_stages_track_every_frame(tmp_path_factory):
    """`--preset accurate slam.init=const_velocity` (the ablation docs/accurate.md shows) kept both neural stages
    for GICP failures that could not happen: no frame was tracked and every pose stayed at frame 0's."""
    out = run(tmp_path_factory, "cv_only", "accurate", ["slam.init=const_velocity", "slam.track_iters=4"])
    recs = tracks(out)
    assert recs and all(r["sdf_iters"] >= 1 and r["iters"] >= 1 and "gicp_fitness" not in r for r in recs)
    est = read_tum(out / "trajectory.txt")[1]
    assert np.linalg.norm(est[-1][:3, 3] - est[0][:3, 3]) > 0.01  # the camera moves (it stood still before)


@pytest.mark.parametrize("target", ["keyframe", "previous"])
def test_a_frame_without_depth_never_becomes_the_gicp_target(target):
    """A depthless frame failed GICP (too few points) and still became the keyframe / previous-frame target: the
    next frame, full depth, then registered onto an empty cloud and failed too. The target before it is kept, and a
    target read again after a resume is the same one."""
    import dataclasses

    from inrslam.datasets import open_dataset
    from inrslam.slam.system import SlamSystem

    cfg = load_config(preset="gicp", overrides=SMALL + [f"slam.gicp.target={target}"])
    ds = open_dataset(cfg.data)

    class HoleAt3:
        name, root, intrinsics, bounds, gt_mesh = ds.name, ds.root, ds.intrinsics, ds.bounds, ds.gt_mesh

        def __len__(self):
            return 6

        def __getitem__(self, i):
            f = ds[i]
            return dataclasses.replace(f, depth=np.zeros_like(f.depth)) if i == 3 else f

    def tracked(forget_target_after: int | None = None):
        system = SlamSystem(cfg, HoleAt3())
        recs = []
        for i in range(6):
            recs += [r for r in system.process(i) if r["type"] == "track"]
            if i == forget_target_after:
                system._target_cloud = None  # what a resume starts from: targets are read again from the dataset
        return system, recs

    system, recs = tracked()
    assert recs[2]["fallback"].startswith("gicp_too_few_points")  # frame 3
    assert 3 not in system.state.gicp_kfs and recs[3]["gicp_target"] != 3  # frame 4 registers onto an older one
    assert "fallback" not in recs[3] and recs[3]["gicp_fitness"] > 0.5
    if target == "previous":
        assert recs[3]["gicp_target"] == 2 and recs[4]["gicp_target"] == 4
    _, again = tracked(forget_target_after=3)
    def same(r):  # a record without its timing, NaN losses comparable
        return json.dumps({k: v for k, v in r.items() if k != "track_ms"}, sort_keys=True)

    assert [same(r) for r in again] == [same(r) for r in recs]
    assert np.array_equal(system.est.numpy(), tracked(forget_target_after=3)[0].est.numpy())


def test_interrupted_accurate_run_resumes_to_the_uninterrupted_result(all_on, tmp_path):
    out = tmp_path / "interrupted"

    # after the checkpoint of frame 3 (checkpoint_every = 2)
    run_interrupted(load_config(preset="accurate", overrides=SMALL + ALL_ON), out, 4)
    assert (out / "checkpoints" / "latest.pt").is_file() and not (out / "trajectory.txt").exists()
    resume_slam(out)
    assert (out / "trajectory.txt").read_text() == (all_on / "trajectory.txt").read_text()
    strip = lambda recs: [{k: v for k, v in r.items() if not k.endswith("_ms")} for r in recs]
    assert strip(tracks(out)) == strip(tracks(all_on))


def test_resume_after_bundle_adjustment_moved_local_map_keyframes(tmp_path):
    # mapping (with bundle adjustment) on frames 3 and 6, GICP keyframes 0, 3, 5: bundle adjustment on frame 6 moves
    # keyframe 3 of the local map that frame 7 registers onto; a run resumed from the checkpoint of frame 6 builds that
    # map at the moved poses, so the uninterrupted run must too
    extra = SMALL + ALL_ON + ["slam.map_every=3", "slam.checkpoint_every=1", "slam.gicp.kf_dist=0.02"]
    full, out = tmp_path / "full", tmp_path / "interrupted"
    run_slam(load_config(preset="accurate", overrides=extra), full)
    assert [r["gicp_target"] for r in tracks(full)][-2:] == [5, 5]  # frame 7 keeps frame 6's local map

    run_interrupted(load_config(preset="accurate", overrides=extra), out, 7)
    resume_slam(out)
    assert (out / "trajectory.txt").read_text() == (full / "trajectory.txt").read_text()


def test_local_map_target_registers_onto_merged_keyframes(tmp_path_factory):
    out = run(tmp_path_factory, "local_map", "accurate", ["slam.gicp.target=local_map", "slam.gicp.kf_dist=0.01"])
    recs = tracks(out)
    targets = [r["gicp_target"] for r in recs]
    assert len(set(targets)) > 1  # keyframes renewed (1 cm of motion)
    _, est = read_tum(out / "trajectory.txt")
    _, gt = read_tum(out / "trajectory_gt.txt")
    assert np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1).max() < 0.003


def test_fast_preset_tracks_like_accurate_with_a_lighter_map(tmp_path_factory):
    fast, acc = load_config(preset="fast"), load_config(preset="accurate")
    for key in ("init", "track_only_on_init_failure", "bundle_adjust", "pose_param"):
        assert getattr(fast.slam, key) == getattr(acc.slam, key), key
    assert fast.slam.gicp.target == acc.slam.gicp.target
    work = lambda s: s.map_iters * s.map_pixels / s.map_every  # rays mapped per frame  # noqa: E731
    assert work(fast.slam) < work(acc.slam) / 5 and fast.slam.init_iters < acc.slam.init_iters
    out = tmp_path_factory.mktemp("fast") / "run"
    run_slam(load_config(preset="fast", overrides=["data.max_frames=12", "data.builtin.width=96",
                                                   "data.builtin.height=72", "eval.enabled=false",
                                                   "mesh.enabled=false", "output.tensorboard=false", *LIGHT_MAP]), out)
    recs = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in recs if r["type"] == "map"] == [10]
    assert all("gicp_fitness" in r for r in recs if r["type"] == "track")


def test_gicp_tracked_poses_stay_rigid_frame_after_frame(tmp_path_factory):
    """Constant-velocity predictions of float32 poses are a little off orthonormal, and GICP keeps its start's
    scale / shear: without `slam.gicp.rigid_init` the error compounds (measured: ~1e-5 after 30 frames, 1e-3 after
    400 on 7-Scenes); with it every pose stays within float32 rounding of a rotation."""
    from inrslam.runner.checkpoint import load_checkpoint

    over = ["data.max_frames=30", "data.builtin.width=96", "data.builtin.height=72", "slam.init_iters=5",
            "slam.init_pixels=256", "slam.map_iters=1", "slam.map_pixels=256", "slam.gicp.pixel_stride=1",
            "eval.enabled=false", "mesh.enabled=false", "output.tensorboard=false", *LIGHT_MAP[1:]]
    worst = {}
    for rigid in ("true", "false"):
        out = tmp_path_factory.mktemp(f"rigid_{rigid}") / "run"
        run_slam(load_config(preset="gicp", overrides=over + [f"slam.gicp.rigid_init={rigid}"]), out)
        R = np.asarray(load_checkpoint(out / "checkpoints" / "latest.pt")["est"], dtype=np.float64)[:, :3, :3]
        worst[rigid] = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max()
    assert worst["true"] < 1e-6 < worst["false"]


NOISY = ["data.path=builtin:handheld", "data.max_frames=5"]  # depth noise 4 mm at 1 m, 5 % holes


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    return run(tmp_path_factory, "noisy", "accurate", NOISY)


def test_photometric_refinement_and_depth_filter_run_on_noisy_depth_only(noisy, all_on, tmp_path_factory):
    for r in tracks(noisy):
        assert r["depth_noise"] == pytest.approx(0.004, rel=0.15)  # estimated per frame
        assert r["photo_iters"] >= 1 and r["photo_points"] >= 300 and r["photo_target"] < r["frame"]
    for r in tracks(all_on):  # noise-free synthetic depth: neither the filter nor the refinement runs
        assert r["depth_noise"] < 1e-4 and "photo_iters" not in r
    off = run(tmp_path_factory, "photo_off", "accurate", NOISY + ["slam.photo.enabled=false"])
    assert all("photo_iters" not in r for r in tracks(off))
    assert (off / "trajectory.txt").read_text() != (noisy / "trajectory.txt").read_text()


def test_photometric_refinement_takes_over_where_gicp_fails(tmp_path_factory):
    out = run(tmp_path_factory, "rescue", "accurate", NOISY + ["slam.gicp.degeneracy_ratio=2"])
    for r in tracks(out):
        assert r["fallback"] == "gicp_degenerate" and r["photo_rescued"]  # the event is still logged ...
        assert "sdf_iters" not in r and r["iters"] == 0  # ... but the neural map did not track
    out = run(tmp_path_factory, "no_rescue", "accurate", NOISY + ["slam.gicp.degeneracy_ratio=2",
                                                                  "slam.photo.rescue=false"])
    for r in tracks(out):
        assert "photo_rescued" not in r and r["sdf_iters"] >= 1 and r["iters"] >= 1


def test_interrupted_noisy_accurate_run_resumes_to_the_uninterrupted_result(noisy, tmp_path):
    out = tmp_path / "interrupted"

    # after the checkpoint of frame 3: the photometric reference is rebuilt
    run_interrupted(load_config(preset="accurate", overrides=SMALL + NOISY), out, 4)
    resume_slam(out)
    assert (out / "trajectory.txt").read_text() == (noisy / "trajectory.txt").read_text()


REFINE = ["slam.refine.enabled=true", "slam.refine.gaps=[1,2]"]


@pytest.fixture(scope="module")
def refined(tmp_path_factory):
    return run(tmp_path_factory, "refined", "accurate", NOISY + REFINE)


def test_a_final_pose_graph_moves_the_trajectory_after_the_last_frame_only_when_asked(noisy, refined):
    recs = [json.loads(line) for line in (refined / "log.jsonl").read_text().splitlines()]
    ref = [r for r in recs if r["type"] == "refine"]
    assert len(ref) == 1 and ref[0]["frame"] == 4  # once, after the last frame
    assert ref[0]["links"] + ref[0]["links_dropped"] == 4 + 3  # frames 1-4 aligned onto 1 back, 2-4 onto 2 back
    assert ref[0]["links"] >= 4 and 0 < ref[0]["moved_max_m"] < 0.01
    assert '"refine"' not in (noisy / "log.jsonl").read_text()

    def tracking(r):  # a record without its timings
        return {k: v for k, v in r.items() if not k.endswith("_ms")}

    # every frame was tracked as without the key; only the written trajectory moved
    assert [tracking(r) for r in tracks(refined)] == [tracking(r) for r in tracks(noisy)]
    _, est = read_tum(refined / "trajectory.txt")
    _, est0 = read_tum(noisy / "trajectory.txt")
    assert np.allclose(est[0], est0[0], atol=1e-6) and not np.allclose(est, est0, atol=1e-6)


def test_an_interrupted_refined_run_resumes_to_the_uninterrupted_result(refined, tmp_path):
    out = tmp_path / "interrupted"

    # after the graph: the resumed run tracks frame 4 and builds it again
    run_interrupted(load_config(preset="accurate", overrides=SMALL + NOISY + REFINE), out, 4)
    resume_slam(out)
    assert (out / "trajectory.txt").read_text() == (refined / "trajectory.txt").read_text()


def test_a_photometric_refinement_moving_a_gicp_pose_too_far_is_rejected(tmp_path_factory):
    # every view counts as well conditioned (weak_degeneracy 0), so the 1 nm bound applies to every frame
    out = run(tmp_path_factory, "photo_jump", "accurate", NOISY + ["slam.photo.max_step=1e-9",
                                                                   "slam.photo.weak_degeneracy=0"])
    for r in tracks(out):
        assert r["fallback"] == "photo_jump" and r["photo_shift_mm"] > 0  # logged, GICP's pose kept
        assert r["photo_target"] == r["frame"] - 1  # a failed refinement renews the photometric keyframe


def test_map_learns_filtered_depth_only_when_asked_and_only_on_noisy_depth():
    from inrslam.datasets import open_dataset
    from inrslam.slam.registration import filtered_depth
    from inrslam.slam.system import SlamSystem

    for scene, noisy_depth in (("handheld", True), ("room", False)):
        for on in (True, False):
            cfg = load_config(preset="accurate", overrides=SMALL + [f"data.path=builtin:{scene}", "data.max_frames=2",
                                                                    f"slam.map_filtered_depth={str(on).lower()}"])
            system = SlamSystem(cfg, open_dataset(cfg.data))
            frame = system.dataset[1]
            mapped = system._map_frame(frame, filtered_depth(frame.depth, cfg.slam.gicp))  # as _process gives it
            if on and noisy_depth:
                want = filtered_depth(frame.depth, cfg.slam.gicp)
                np.testing.assert_allclose(mapped.depth, want, rtol=1e-6, atol=0)
                assert not np.array_equal(mapped.depth, frame.depth)
                assert ((mapped.depth > 0) == (frame.depth > 0)).all()  # holes stay holes
            else:
                assert mapped is frame


RENEW = NOISY + ["slam.photo.kf_rms_factor=0.5"]  # a photometric keyframe on every frame (kf_rms_factor < 1)


@pytest.fixture(scope="module")
def renew(tmp_path_factory):
    """A photometric keyframe on every frame: every refinement's RMS exceeds 0.5 times the first one onto its
    reference (one run for the two tests reading it)."""
    return run(tmp_path_factory, "renew", "accurate", RENEW)


def test_photometric_keyframe_is_renewed_when_its_residual_grows(noisy, renew):
    # default (kf_rms_factor 0): 5 frames of `handheld` stay on the first photometric keyframe (< 30 cm, < 25 deg)
    assert [r["photo_target"] for r in tracks(noisy)] == [0, 0, 0, 0]
    # a factor below 1: every refinement's RMS exceeds it times the first one onto the reference -> renewed each frame
    recs = tracks(renew)
    assert [r["photo_target"] for r in recs] == [r["frame"] - 1 for r in recs]
    assert all("fallback" not in r for r in recs)


def test_gicp_prior_changes_the_photometric_refinement_only_when_set(noisy, tmp_path_factory):
    out = run(tmp_path_factory, "photo_prior", "accurate", NOISY + ["slam.photo.gicp_prior=1"])
    with_prior, without = tracks(out), tracks(noisy)
    assert [r["photo_target"] for r in with_prior] == [r["photo_target"] for r in without]
    # the prior holds the pose nearer GICP's: a smaller photometric move on every frame, and another trajectory
    assert all(a["photo_shift_mm"] < b["photo_shift_mm"] for a, b in zip(with_prior, without))
    assert (out / "trajectory.txt").read_text() != (noisy / "trajectory.txt").read_text()


def test_depth_weight_adds_depth_residuals_to_the_photometric_refinement_only_when_set(noisy, tmp_path_factory):
    out = run(tmp_path_factory, "photo_depth", "accurate", NOISY + ["slam.photo.depth_weight=1"])
    with_depth, without = tracks(out), tracks(noisy)
    assert all("photo_depth_points" not in r for r in without)
    # every refinement also had depth residuals, at most one per reference point
    assert all(0 < r["photo_depth_points"] <= r["photo_points"] for r in with_depth)
    assert (out / "trajectory.txt").read_text() != (noisy / "trajectory.txt").read_text()


@pytest.fixture(scope="module")
def kf_refs3(tmp_path_factory):
    """With kf_refs 3 each new photometric keyframe is also aligned onto the two keyframes before its reference and
    its pose averaged with them."""
    return run(tmp_path_factory, "kf_refs3", "accurate", RENEW + ["slam.photo.kf_refs=3"])


def test_new_photometric_keyframes_are_placed_by_several_older_ones_when_asked(renew, kf_refs3):
    one = tracks(renew)  # kf_refs 1
    out = kf_refs3
    three = tracks(out)
    assert all("photo_kf_refs" not in r for r in one)
    # frame 1's reference is keyframe 0 alone; from frame 2 on older keyframes exist (at most 2 more)
    assert "photo_kf_refs" in three[0] and three[0]["photo_kf_refs"] == 1
    assert all(1 <= r["photo_kf_refs"] <= 3 for r in three)
    averaged = [r for r in three if r["photo_kf_refs"] > 1]
    assert averaged and all(r["photo_kf_move_mm"] > 0 for r in averaged)
    assert [r["photo_target"] for r in three] == [r["frame"] - 1 for r in three]
    _, est = read_tum(out / "trajectory.txt")
    _, gt = read_tum(out / "trajectory_gt.txt")
    assert np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1).max() < 0.03  # still tracks (noisy depth)


def test_interrupted_run_with_averaged_photometric_keyframes_resumes_exactly(kf_refs3, tmp_path):
    over = SMALL + RENEW + ["slam.photo.kf_refs=3"]  # kf_refs3's settings
    whole = kf_refs3
    out = tmp_path / "interrupted"

    # the older keyframes' pyramids are rebuilt from the dataset
    run_interrupted(load_config(preset="accurate", overrides=over), out, 4)
    resume_slam(out)
    assert (out / "trajectory.txt").read_text() == (whole / "trajectory.txt").read_text()


class _DroppedFrames:
    """A dataset whose recorder repeated dropped frames: frame 3's colour is frame 2's, frame 5's depth frame 4's."""

    def __init__(self, base):
        self.base = base

    def __getattr__(self, name):
        return getattr(self.base, name)

    def __len__(self):
        return len(self.base)

    def __getitem__(self, i):
        import dataclasses

        f = self.base[i]
        if i == 3:
            return dataclasses.replace(f, rgb=self.base[2].rgb.copy())
        if i == 5:
            return dataclasses.replace(f, depth=self.base[4].depth.copy())
        return f


def test_frames_with_a_repeated_colour_or_depth_are_not_refined_photometrically_when_asked():
    from inrslam.data.frame import repeated_streams
    from inrslam.datasets import open_dataset
    from inrslam.slam.system import SlamSystem

    def run(skip: bool) -> tuple[SlamSystem, list[dict]]:
        # every refined frame becomes the photometric keyframe (kf_rms_factor < 1)
        over = ["data.max_frames=7", "slam.photo.kf_rms_factor=0.5", f"slam.photo.skip_stale={str(skip).lower()}"]
        cfg = load_config(preset="accurate", overrides=SMALL + NOISY + over)
        system = SlamSystem(cfg, _DroppedFrames(open_dataset(cfg.data)))
        return system, [r for i in range(7) for r in system.process(i) if r["type"] == "track"]

    system, on = run(True)
    assert [r.get("stale") for r in on] == [None, None, "colour", None, "depth", None]
    assert all(("photo_iters" in r) == ("stale" not in r) for r in on)  # GICP's pose stands on a stale frame ...
    assert [r.get("photo_target") for r in on] == [0, 1, None, 2, None, 4]  # ... which never becomes a reference
    # after a resume nothing is kept in memory: the previous frame is read again, and is the same
    assert system._previous_frame(7) is system._prev_frame and system._prev_frame.index == 6
    system._prev_frame = None
    again = system._previous_frame(6)
    assert again.index == 5 and repeated_streams(again, system.dataset[5]) == "both"
    _, off = run(False)
    assert all("stale" not in r for r in off) and [r["photo_target"] for r in off] == [0, 1, 2, 3, 4, 5]


@pytest.fixture(scope="module")
def track_refs3(tmp_path_factory):
    """With track_refs 3 each frame is aligned onto its photometric keyframe and the two before it at once."""
    return run(tmp_path_factory, "track_refs3", "accurate", RENEW + ["slam.photo.track_refs=3"])


def test_frames_are_aligned_onto_several_photometric_keyframes_at_once_when_asked(renew, track_refs3,
                                                                                   tmp_path_factory):
    single = run(tmp_path_factory, "track_refs1", "accurate", RENEW + ["slam.photo.track_refs=1"])
    one, two, three = tracks(single), tracks(renew), tracks(track_refs3)  # accurate's own setting is 2
    assert all("photo_refs" not in r for r in one)  # track_refs 1: the key is not logged
    # a keyframe on every frame: frame 1 has keyframe 0 only, frame 2 keyframes 0-1, then 2 or 3 at once
    assert [r["photo_refs"] for r in two] == [min(2, r["frame"]) for r in two]
    assert [r["photo_refs"] for r in three] == [min(3, r["frame"]) for r in three]
    assert [r["photo_target"] for r in three] == [r["frame"] - 1 for r in three]
    assert all("fallback" not in r for r in two + three)
    # frame 1 sees one reference in every run: the same refinement, to the bit; then the runs part
    assert one[0]["photo_shift_mm"] == two[0]["photo_shift_mm"] == three[0]["photo_shift_mm"]
    assert two[1]["photo_shift_mm"] == three[1]["photo_shift_mm"] != one[1]["photo_shift_mm"]
    assert two[2]["photo_shift_mm"] != three[2]["photo_shift_mm"]
    for out in (renew, track_refs3):
        _, est = read_tum(out / "trajectory.txt")
        _, gt = read_tum(out / "trajectory_gt.txt")
        assert np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1).max() < 0.03  # still tracks (noisy depth)


def test_interrupted_run_aligned_onto_several_keyframes_resumes_exactly(track_refs3, tmp_path):
    over = SMALL + RENEW + ["slam.photo.track_refs=3"]  # track_refs3's settings
    out = tmp_path / "interrupted"

    # the older keyframes' pyramids are rebuilt from the dataset on resume
    run_interrupted(load_config(preset="accurate", overrides=over), out, 3)
    resume_slam(out)
    assert (out / "trajectory.txt").read_text() == (track_refs3 / "trajectory.txt").read_text()
