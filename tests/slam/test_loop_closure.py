"""Loop closure's pieces on analytic cases: the pose graph corrects a known loop error to its ground truth, the
overlap test, GICP verification accepts a true revisit and rejects a false one (a twin view beyond the drift bound,
a single wall, an ambiguous pair), frames follow their keyframes, and the re-fit moves the map's surface to the
corrected keyframe poses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.geometry.se3 import se3_exp
from inrslam.slam.config import GicpConfig, LoopConfig
from inrslam.slam.loop_closure import (
    Candidate,
    Verification,
    color_confirms,
    consistent,
    corrected_keyframes,
    follow_keyframes,
    nearby_keyframes,
    new_place,
    overlap,
    path_length,
    significant,
)

gtsam = pytest.importorskip("gtsam", reason="loop closure's pose graph needs gtsam (pip install gtsam)")
from interrupted import run_interrupted  # noqa: E402
from test_registration_sdf_tracking import CORNER, INTR, WALL, look_at, plane_depth  # noqa: E402

from inrslam.slam import pose_graph  # noqa: E402


def twist(xi) -> np.ndarray:
    """(6,) twist (rho metres, omega radians) -> (4, 4)."""
    return se3_exp(torch.as_tensor(np.asarray(xi, dtype=np.float64))).numpy()


def circle(n: int, radius: float = 1.0) -> np.ndarray:
    """(n, 4, 4) c2w on a horizontal circle, each camera looking at the centre."""
    out = []
    for a in np.linspace(0.0, 2 * np.pi, n, endpoint=False):
        out.append(look_at((radius * np.cos(a), radius * np.sin(a), 1.0), (0.0, 0.0, 1.0)))
    return np.stack(out)


def drifted(gt: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Dead reckoning of gt's relative motions, each one followed by the error `step` (4, 4)."""
    est = [gt[0]]
    for k in range(1, len(gt)):
        est.append(est[-1] @ pose_graph.relative(gt[k - 1], gt[k]) @ step)
    return np.stack(est)


def pos_err(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)


def test_pose_graph_with_exact_edges_recovers_the_ground_truth_from_drifted_poses():
    gt = circle(16)
    start = drifted(gt, twist([0.0, 0.0, 0.01, 0.01, 0.0, 0.0]))
    edges = pose_graph.odometry_edges(gt, 0.01, 0.005)
    edges.append(pose_graph.Edge(0, 15, pose_graph.relative(gt[0], gt[15]), 0.01, 0.005))
    out = pose_graph.optimise(start, edges)
    assert pos_err(start, gt).max() > 0.05  # the start is far off ...
    assert pos_err(out, gt).max() < 1e-6  # ... and the graph puts every pose back
    assert np.allclose(out[:, :3, :3], gt[:, :3, :3], atol=1e-6)


def test_a_loop_edge_removes_most_of_the_accumulated_drift():
    gt = circle(20)
    est = drifted(gt, twist([0.0, 0.0, 0.004, 0.003, 0.0, 0.0]))  # a biased odometry
    cfg = LoopConfig()
    loop = {"candidate": 0, "frame": 19, "T": pose_graph.relative(gt[0], gt[19])}  # the revisit, measured exactly
    out = corrected_keyframes(est, list(range(20)), [loop], cfg)
    before, after = pos_err(est, gt), pos_err(out, gt)
    assert after[-1] < 0.1 * before[-1]  # the loop's end is put back
    assert np.sqrt(np.mean(after**2)) < 0.5 * np.sqrt(np.mean(before**2))  # and the drift is spread, not kept
    assert np.allclose(out[0], est[0], atol=1e-9)  # keyframe 0 fixed


def test_tracked_odometry_keeps_a_rigid_move_from_becoming_odometry():
    gt = circle(20)
    est = drifted(gt, twist([0.0, 0.0, 0.004, 0.003, 0.0, 0.0]))
    odometry = np.stack([pose_graph.relative(est[k], est[k + 1]) for k in range(19)])  # as tracked
    loop = {"candidate": 0, "frame": 19, "T": pose_graph.relative(gt[0], gt[19])}
    cfg = LoopConfig()
    optimum = corrected_keyframes(est, list(range(20)), [loop], cfg)
    # a closure moved the last 6 keyframes rigidly with the newest (the tracker's window): a kink at keyframe 14
    kinked = optimum.copy()
    kinked[14:] = (optimum[19] @ np.linalg.inv(est[19])) @ est[14:]
    again = corrected_keyframes(kinked, list(range(20)), [loop], cfg, odometry)
    assert pos_err(again, optimum).max() < 1e-5  # the same optimum, from wherever the poses were left
    measured = corrected_keyframes(kinked, list(range(20)), [loop], cfg)  # odometry measured from the kinked poses
    assert pos_err(measured, optimum).max() > 100 * pos_err(again, optimum).max()  # keeps part of the kink
    with pytest.raises(ValueError, match="odometry edges"):
        corrected_keyframes(est, list(range(20)), [loop], cfg, odometry[:5])


def test_huber_kernel_limits_a_wrong_loop_edge():
    gt = circle(12)
    wrong = pose_graph.relative(gt[0], gt[11]) @ twist([0.5, 0, 0, 0, 0, 0])  # 50 cm off
    moved = {}
    for huber in (0.0, 1.345):
        edges = pose_graph.odometry_edges(gt, 0.01, 0.005) + [pose_graph.Edge(0, 11, wrong, 0.01, 0.005, huber)]
        moved[huber] = pos_err(pose_graph.optimise(gt, edges), gt).max()
    assert moved[1.345] < 0.5 * moved[0.0]


def test_overlap_of_a_view_with_itself_a_turned_away_view_and_a_wrong_depth():
    T = look_at((0.3, 0.2, 1.2), (2.0, 1.0, 0.6))
    depth = plane_depth(CORNER, T)
    pts = np.argwhere(depth > 0)
    cam = np.stack([(pts[:, 1] - INTR.cx) / INTR.fx, (pts[:, 0] - INTR.cy) / INTR.fy, np.ones(len(pts))], 1)
    cam *= depth[pts[:, 0], pts[:, 1]][:, None]
    assert overlap(cam, T, T, depth, INTR, 0.05) == pytest.approx(1.0)
    away = look_at((0.3, 0.2, 1.2), (-2.0, -1.0, 0.6))  # the opposite direction: nothing in view
    assert overlap(cam, T, away, plane_depth(CORNER, away), INTR, 0.05) == 0.0
    assert overlap(cam, T, T, depth + 0.2, INTR, 0.05) == 0.0  # in view, but not where the depth says
    assert overlap(np.zeros((0, 3)), T, T, depth, INTR, 0.05) == 0.0


def test_candidates_are_old_near_and_facing_the_same_way():
    est = np.stack([np.eye(4)] * 200)
    est[150, :3, 3] = [0.5, 0, 0]  # near, but only 49 frames before 199
    est[10, :3, 3] = [2.0, 0, 0]  # old but far
    est[20, :3, :3] = look_at((0, 0, 0), (0, 1, 0))[:3, :3]  # old, near, looking 90 degrees away
    est[30, :3, 3] = [0.3, 0, 0]  # old, near, same direction
    est[40, :3, 3] = [0.1, 0, 0]
    cands = nearby_keyframes(199, [10, 20, 30, 40, 150], est, LoopConfig(min_gap=100, max_dist=0.8, max_angle=45))
    assert [c.frame for c in cands] == [40, 30]  # nearest first
    assert cands[0].distance == pytest.approx(0.1) and cands[0].angle == pytest.approx(0.0)
    assert path_length(est, 0, 2) == 0.0 and path_length(est, 29, 31) == pytest.approx(0.6)
    # keyframes of the tracker's local map (from frame 35 on here) are registered onto already: never candidates
    near = nearby_keyframes(199, [10, 20, 30, 40, 150], est, LoopConfig(min_gap=100, max_dist=0.8, max_angle=45),
                            before=35)
    assert [c.frame for c in near] == [30]
    assert nearby_keyframes(199, [10, 20, 30, 40], est, LoopConfig(min_gap=100), before=0) == []


@pytest.fixture(scope="module")
def clouds():
    pytest.importorskip("small_gicp", reason="loop verification needs small_gicp")
    from inrslam.slam.loop_closure import stage_clouds
    from inrslam.slam.registration import depth_points

    g = GicpConfig(pixel_stride=1)
    T_cand = look_at((0.3, 0.2, 1.2), (2.0, 1.0, 0.6))
    T_cur = T_cand @ twist([0.02, -0.01, 0.01, 0.03, -0.02, 0.01])
    return g, T_cand, T_cur, {name: stage_clouds(depth_points(plane_depth(CORNER, T), INTR, g), g, LoopConfig())
                              for name, T in (("cand", T_cand), ("cur", T_cur))}


def test_stage_clouds_are_coarse_then_fine(clouds):
    from inrslam.slam.loop_closure import stage_clouds, verify
    from inrslam.slam.registration import depth_points

    g, T_cand, T_cur, c = clouds
    coarse, mid, fine = c["cur"]
    assert coarse is mid and 0 < coarse.size < fine.size / 3  # 5 cm voxels: the coarse stages share fewer points
    pts = depth_points(plane_depth(CORNER, T_cur), INTR, g)
    same = stage_clouds(pts, g, LoopConfig(coarse_downsample=0.0))
    assert [cl.size for cl in same] == [fine.size] * 3
    assert len(stage_clouds(pts, g, LoopConfig(corr_stages=[0.05]))) == 1
    with pytest.raises(ValueError, match="3 verification stages"):
        verify(c["cand"][:1], c["cur"], T_cand, T_cur, 1.0, 7, g, LoopConfig())


def test_verification_accepts_a_true_revisit_despite_drift(clouds):
    from inrslam.slam.loop_closure import verify

    g, T_cand, T_cur, c = clouds
    drift = twist([0.06, 0.04, 0, 0, 0, 0])  # the estimate of the current keyframe is 7 cm off
    v = verify(c["cand"], c["cur"], T_cand, drift @ T_cur, 5.0, 7, g, LoopConfig())
    assert v.ok and v.reason is None and v.frame == 7
    assert np.allclose(v.T_cand_cur, np.linalg.solve(T_cand, T_cur), atol=2e-3)  # the true relative pose
    assert v.correction == pytest.approx(np.linalg.norm([0.06, 0.04]), abs=3e-3)
    assert v.record()["ok"] is True


def test_verification_rejects_a_twin_view_beyond_the_drift_bound(clouds):
    from inrslam.slam.loop_closure import verify

    g, T_cand, T_cur, c = clouds
    # the same view, but the estimates put the cameras 20 cm apart after only 1 m of travel: a repeated-structure
    # twin, not a revisit (bound: 5 cm + 5 cm per metre travelled)
    claimed = twist([0.2, 0, 0, 0, 0, 0]) @ T_cur
    v = verify(c["cand"], c["cur"], T_cand, claimed, 1.0, 7, g, LoopConfig())
    assert not v.ok and v.reason == "correction" and v.correction > v.bound == pytest.approx(0.1)
    assert verify(c["cand"], c["cur"], T_cand, claimed, 4.0, 7, g, LoopConfig()).ok  # after 4 m, plausible drift


def test_verification_rejects_a_single_wall():
    pytest.importorskip("small_gicp", reason="loop verification needs small_gicp")
    from inrslam.slam.loop_closure import stage_clouds, verify
    from inrslam.slam.registration import depth_points

    g = GicpConfig(pixel_stride=1)
    T = look_at((0.0, 0.0, 1.2), (2.0, 0.0, 1.2))
    wall = stage_clouds(depth_points(plane_depth(WALL, T), INTR, g), g, LoopConfig())
    v = verify(wall, wall, T, T, 5.0, 3, g, LoopConfig())
    assert not v.ok and v.reason == "coarse_degenerate"  # the wide stage already sees a one-wall view


def test_verifications_that_disagree_are_ambiguous():
    est = np.stack([np.eye(4)] * 3)
    est[2, :3, 3] = [1.0, 0, 0]
    near = lambda frame, T: Verification(frame, True, None, T, 0.9, 0.01, 0.1, 0.1)
    a = near(0, twist([0.5, 0, 0, 0, 0, 0]))  # keyframe at x = 0.5
    b = near(2, twist([-0.49, 0, 0, 0, 0, 0]))  # x = 0.51: agrees
    c = near(2, twist([-0.3, 0, 0, 0, 0, 0]))  # x = 0.7: another place
    assert consistent([a, b], est, 0.05) and not consistent([a, c], est, 0.05) and consistent([a], est, 0.05)
    lo, hi = near(0, twist([0.46, 0, 0, 0, 0, 0])), near(0, twist([0.54, 0, 0, 0, 0, 0]))
    assert not consistent([a, lo, hi], est, 0.05)  # each 4 cm from the first, 8 cm from each other
    assert consistent([], est, 0.05)
    assert isinstance(Candidate(1, 0.1, 2.0).overlap, float)


def test_a_first_loop_must_correct_more_than_the_verification_error():
    cfg = LoopConfig(min_correction=0.005, min_gap=100)
    small = Verification(5, True, None, np.eye(4), 0.6, 0.003, 0.2, 0.3)  # 3 mm: within a verification's own error
    large = Verification(5, True, None, np.eye(4), 0.6, 0.011, 0.0, 0.3)
    first = lambda loops: new_place(small.frame, loops, cfg)
    assert not significant(small, first([]), cfg) and significant(large, first([]), cfg)
    # once a loop edge onto a nearby candidate exists, the loop is closed there: small corrections keep it closed
    assert significant(small, first([{"candidate": 0, "frame": 270}]), cfg)
    assert not significant(small, first([{"candidate": 200, "frame": 400}]), cfg)  # a different place
    assert significant(small, True, LoopConfig(min_correction=0.0))  # off


def test_color_disagreement_is_lowest_at_the_true_relative_pose():
    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.slam.loop_closure import color_disagreement
    from inrslam.slam.photometric import grey

    cfg = load_config(preset="accurate", overrides=["data.path=builtin:loop", "data.builtin.frames=12",
                                                    "data.builtin.width=96", "data.builtin.height=72"])
    ds = open_dataset(cfg.data)
    a, b = ds[0], ds[8]
    true = np.linalg.solve(a.c2w, b.c2w)  # b's camera in a's
    ga, gb = grey(a.rgb), grey(b.rgb)
    assert color_disagreement(b.depth, gb, gb, np.eye(4), b.intrinsics) < 1e-12  # a view onto itself
    at_true = color_disagreement(b.depth, gb, ga, true, b.intrinsics, stride=1)
    for off in ([0.03, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0.02, 0]):  # 3 cm, about 1 degree
        assert at_true < 0.8 * color_disagreement(b.depth, gb, ga, twist(off) @ true, b.intrinsics, stride=1)
    away = np.eye(4)
    away[:3, 3] = [0.0, 0.0, -100.0]  # everything behind the destination camera
    assert np.isnan(color_disagreement(b.depth, gb, ga, away, b.intrinsics))


def test_a_loop_onto_a_new_place_needs_edges_elsewhere():
    cfg = LoopConfig(min_gap=100)
    assert new_place(5, [], cfg)
    loops = [{"candidate": 0, "frame": 270}]
    assert not new_place(5, loops, cfg) and not new_place(99, loops, cfg) and new_place(100, loops, cfg)


def test_the_colour_must_clearly_confirm_a_first_loop():
    # margin 5 % of the estimate's disagreement for the first loop onto a place; further edges need only lower it
    assert color_confirms(0.094, 0.1, True, 0.05) and not color_confirms(0.096, 0.1, True, 0.05)
    assert color_confirms(0.099, 0.1, False, 0.05) and not color_confirms(0.1, 0.1, False, 0.05)
    assert color_confirms(0.099, 0.1, True, 0.0)  # margin 0: only lower
    assert not color_confirms(float("nan"), 0.1, True, 0.05) and not color_confirms(0.05, float("nan"), False, 0.0)


def test_a_registration_the_colour_cannot_tell_from_the_drifted_estimate_is_not_a_first_loop():
    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.slam.loop_closure import color_disagreement
    from inrslam.slam.photometric import grey

    cfg = load_config(preset="accurate", overrides=["data.path=builtin:loop", "data.builtin.frames=12",
                                                    "data.builtin.width=96", "data.builtin.height=72"])
    lc = cfg.slam.loop
    ds = open_dataset(cfg.data)
    a, b = ds[0], ds[8]
    true = np.linalg.solve(a.c2w, b.c2w)  # b's camera in a's
    ga, gb = grey(a.rgb), grey(b.rgb)
    e = lambda T: color_disagreement(b.depth, gb, ga, T, b.intrinsics)  # noqa: E731
    e_est = e(twist([-0.03, 0, 0, 0, 0, 0]) @ true)  # the estimate, drifted 3 cm
    # the true relative pose explains the colour clearly better: a loop
    assert color_confirms(e(true), e_est, True, lc.color_margin)
    # a registration as far off the other way explains it a little better than the estimate, not clearly: the
    # colour cannot tell the two apart, so no first loop (without the margin it would move the keyframe 6 cm)
    e_wrong = e(twist([0.03, 0, 0, 0, 0, 0]) @ true)
    assert e_wrong < e_est and color_confirms(e_wrong, e_est, True, 0.0)
    assert not color_confirms(e_wrong, e_est, True, lc.color_margin)
    assert color_confirms(e_wrong, e_est, False, lc.color_margin)  # onto a closed place only lower is asked


def test_frames_follow_their_keyframes_rigidly():
    est = np.stack([np.eye(4)] * 6)
    for j in range(6):
        est[j, :3, 3] = [0.1 * j, 0, 0]
    kf_ids, rel_kf = [0, 3], np.array([-1, 0, 0, 0, 3, 3])
    old_kf = est[kf_ids]
    new_kf = old_kf.copy()
    new_kf[1] = twist([0, 0.2, 0, 0, 0, np.pi / 2]) @ old_kf[1]  # keyframe 3 turned and shifted
    out = follow_keyframes(est, old_kf, new_kf, kf_ids, rel_kf, upto=4)
    assert np.allclose(out[:3], est[:3]) and np.allclose(out[3], new_kf[1])
    # frame 4 keeps its pose relative to keyframe 3; frame 5 (after `upto`) is not touched
    assert np.allclose(np.linalg.solve(out[3], out[4]), np.linalg.solve(est[3], est[4]))
    assert np.allclose(out[5], est[5])
    # with the tracker's local map from frame 2 on, frames 2.. move rigidly with the newest keyframe (3)
    rigid = follow_keyframes(est, old_kf, new_kf, kf_ids, rel_kf, upto=4, rigid_from=2)
    assert np.allclose(rigid[:2], est[:2]) and np.allclose(rigid[3], new_kf[1])
    for a in (2, 3, 4):  # the window keeps its shape
        assert np.allclose(np.linalg.solve(rigid[3], rigid[a]), np.linalg.solve(est[3], est[a]))


def test_refit_moves_the_surface_to_the_corrected_keyframe_poses():
    from inrslam.config import load_config
    from inrslam.slam.keyframes import KeyframeStore
    from inrslam.slam.mapping import initialise, refit
    from inrslam.slam.model import SceneModel

    cfg = load_config(preset="quick", overrides=["field.encoding=dense", "field.block_coarse=0.25",
                                                 "field.block_fine=0.1", "render.name=direct", "sampling.n_free=8",
                                                 "sampling.n_surface=8"])
    bounds = np.array([[-1.0, 1.0], [-1.0, 1.0], [-0.2, 1.8]])
    torch.manual_seed(0)
    model = SceneModel(cfg, bounds)
    opts = model.make_optimizers(0.01)
    g = torch.Generator().manual_seed(0)
    # a wall 1.4 m in front of a camera at the origin looking along +z; its rays in the keyframe store
    n = 1024
    dirs = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 0.8, torch.ones(n, 1)], 1)
    depth, rgb = torch.full((n,), 1.4), torch.full((n, 3), 0.5)
    store = KeyframeStore()
    store.add(0, dirs, rgb, depth)
    wrong = torch.eye(4)
    wrong[2, 3] = -0.1  # the keyframe's drifted pose puts the wall at z = 1.3 ...
    right = torch.eye(4)  # ... the corrected one at z = 1.4
    initialise(model, opts, lambda k: (wrong,) + (dirs[:k], rgb[:k], depth[:k]), 60, 512, g)

    def sdf_err(c2w: torch.Tensor) -> float:
        pts = (dirs[:512] * depth[:512, None]) @ c2w[:3, :3].T + c2w[:3, 3]
        with torch.no_grad():
            return float(model.field.sdf(pts).abs().mean())

    before = sdf_err(right)
    losses = refit(model, opts, store, right[None], 60, 512, g)
    after = sdf_err(right)
    assert len(losses) == 60 and losses[-1] < losses[0]
    assert after < 0.5 * before  # the surface now sits where the corrected keyframe sees it


@pytest.mark.parametrize("override, expected", [("slam.loop.corr_stages=[]", "at least one"),
                                                ("slam.loop.corr_stages=[0.2,-0.1]", "> 0"),
                                                ("slam.loop.min_overlap=1.5", "in [0, 1]"),
                                                ("slam.loop.color_margin=-0.1", "in [0, 1]")])
def test_bad_loop_settings_are_one_line_config_errors(override, expected):
    from inrslam.config import load_config
    from inrslam.errors import ConfigError

    with pytest.raises(ConfigError, match=r"slam\.loop\.") as e:
        load_config(preset="accurate", overrides=[override])
    assert expected in str(e.value) and "\n" not in str(e.value)


LOOP_RUN = ["data.builtin.frames=120", "data.builtin.motion_scale=2.67", "data.builtin.width=96",
            "data.builtin.height=72", "slam.init_iters=20", "slam.map_every=10", "slam.map_iters=3",
            "slam.map_pixels=512", "slam.gicp.pixel_stride=2", "slam.loop.refit_iters=5",
            "slam.loop.refit_pixels=512", "slam.checkpoint_every=0", "eval.enabled=false", "mesh.enabled=false",
            "output.tensorboard=false", "slam.init_pixels=512", "field.block_fine=0.06", "field.block_coarse=0.24"]


@pytest.fixture(scope="module")
def loop_run(tmp_path_factory):
    """`accurate` with loop closure once around the built-in loop scene (120 small frames)."""
    pytest.importorskip("small_gicp", reason="the accurate preset needs small_gicp")
    from inrslam.config import load_config
    from inrslam.runner import run_slam

    out = tmp_path_factory.mktemp("loop") / "run"
    run_slam(load_config(preset="accurate", overrides=["data.path=builtin:loop", "slam.loop_closure=true",
                                                       *LOOP_RUN]), out)
    return out


def _records(run_dir, kind: str) -> list[dict]:
    import json

    recs = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]
    return [r for r in recs if r["type"] == kind]


def test_closure_fires_at_the_revisit_of_the_loop_scene_and_brings_the_end_back(loop_run):
    import json

    from inrslam.io.trajectory import read_tum

    closed = _records(loop_run, "loop_closed")
    edges = _records(loop_run, "loop_edge") + closed
    assert closed and all(r["frame"] >= 100 and r["candidate"] <= 20 for r in edges)  # only where the loop ends
    c = closed[0]  # its start, where the drift was corrected
    cands = _records(loop_run, "loop_candidate")
    assert cands and all(r["frame"] - r["candidate"] >= 100 for r in cands)
    m = json.loads((loop_run / "metrics.json").read_text())
    assert m["loops_closed"] == len(closed) and m["loop_edges"] == edges[-1]["edges"]
    assert m["loop_verified"] >= m["loop_edges"] and m["loop_candidates"] >= m["loop_verified"]
    assert m["loop_ms_per_frame"] > 0
    final = _records(loop_run, "loop_final")  # after the last frame, every frame follows its own keyframe
    assert [r["frame"] for r in final] == [119] and final[0]["edges"] == m["loop_edges"]
    # the map follows the final graph when the keyframe moves it has not been re-fitted to exceed refit_final_move
    assert ("refit_ms" in final[0]) == (final[0]["unfitted_m"] > 0.001)
    _, est = read_tum(loop_run / "trajectory.txt")
    _, gt = read_tum(loop_run / "trajectory_gt.txt")
    err = np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1)
    # the closure moved the closing keyframe towards where it really is: it is now closer than the move was long
    assert err[c["frame"]] < c["correction_m"]
    assert err[0] < 1e-6  # the first keyframe anchors the graph: no closure moves it


def test_no_loop_onto_the_trackers_own_local_map(tmp_path):
    """With a local map longer than the loop (every GICP keyframe stays in it), the revisit is registered onto the
    first keyframes by tracking itself: no loop candidates, and the first frame stays where it started (a loop onto
    a keyframe of the window used to move the whole window rigidly, the anchoring first keyframe included)."""
    pytest.importorskip("small_gicp", reason="the accurate preset needs small_gicp")
    from inrslam.config import load_config
    from inrslam.io.trajectory import read_tum
    from inrslam.runner import run_slam

    out = tmp_path / "run"
    run_slam(load_config(preset="accurate", overrides=["data.path=builtin:loop", "slam.loop_closure=true",
                                                       "slam.gicp.local_map_keyframes=1000", *LOOP_RUN]), out)
    assert _records(out, "loop_candidate") == [] and _records(out, "loop_edge") == []
    _, est = read_tum(out / "trajectory.txt")
    _, gt = read_tum(out / "trajectory_gt.txt")
    assert np.linalg.norm(est[0, :3, 3] - gt[0, :3, 3]) < 1e-6


def test_a_colour_margin_no_registration_can_meet_closes_no_loop(loop_run, tmp_path):
    """`slam.loop.color_margin=1` asks a first loop for a colour disagreement below zero: the same run as `loop_run`
    (which closes loops) verifies its candidates but rejects each on colour, also those whose colour was better than
    the estimate's, and adds no edge."""
    from inrslam.config import load_config
    from inrslam.runner import run_slam

    assert _records(loop_run, "loop_edge") + _records(loop_run, "loop_closed")
    out = tmp_path / "run"
    run_slam(load_config(preset="accurate", overrides=["data.path=builtin:loop", "slam.loop_closure=true",
                                                       "slam.loop.color_margin=1", *LOOP_RUN]), out)
    assert _records(out, "loop_edge") == [] and _records(out, "loop_closed") == []
    coloured = [r for r in _records(out, "loop_candidate") if r["reason"] == "color"]
    assert any(r["color_loop"] < r["color_estimate"] for r in coloured)
    assert not any(r["ok"] for r in _records(out, "loop_candidate"))


def test_interrupted_loop_closure_run_resumes_to_the_uninterrupted_result(loop_run, tmp_path):
    from inrslam.config import load_config
    from inrslam.runner import resume_slam
    from inrslam.runner.checkpoint import load_checkpoint

    out = tmp_path / "interrupted"
    first = _records(loop_run, "loop_edge") + _records(loop_run, "loop_closed")
    stop_at = min(r["frame"] for r in first) + 5  # after the first loop edge and a checkpoint (every 5 frames)

    cfg = load_config(preset="accurate", overrides=["data.path=builtin:loop", "slam.loop_closure=true", *LOOP_RUN,
                                                    "slam.checkpoint_every=5"])
    run_interrupted(cfg, out, stop_at)
    saved = load_checkpoint(out / "checkpoints" / "latest.pt")
    assert saved["loops"] and saved["kf_odometry"]  # the graph's edges travel with the checkpoint
    resume_slam(out)
    assert (out / "trajectory.txt").read_text() == (loop_run / "trajectory.txt").read_text()
    # the last frame's graph pass and its re-fit ran once, after the resume, as in the uninterrupted run
    (mine,), (theirs,) = _records(out, "loop_final"), _records(loop_run, "loop_final")
    assert mine["frame"] == 119 and mine["edges"] == theirs["edges"] and mine["unfitted_m"] == theirs["unfitted_m"]
    assert ("refit_ms" in mine) == ("refit_ms" in theirs)


def test_reported_keyframe_moves_are_the_moves_applied():
    # keyframes 0, 4, 8, 12 along x; one loop edge says keyframe 12 is where keyframe 0 is. With the tracker's local
    # map from frame 8 on (rigid_from), keyframes 8 and 12 move with the newest's correction, not to the graph's
    # optimum: the returned moves (which decide re-fits) must be those applied.
    from types import MethodType, SimpleNamespace

    from inrslam.slam.system import SlamSystem

    n = 14
    est = np.stack([np.eye(4)] * n)
    est[:, 0, 3] = 0.1 * np.arange(n)
    kf_ids = [0, 4, 8, 12]
    state = SimpleNamespace(est=torch.tensor(est, dtype=torch.float64), kf_odometry={},
                            rel_kf=np.array([k // 4 * 4 for k in range(n)]),
                            loops=[{"candidate": 0, "frame": 12, "T": np.eye(4)}])
    fake = SimpleNamespace(state=state, store=SimpleNamespace(frame_ids=kf_ids), _local_target="cached",
                           cfg=SimpleNamespace(slam=SimpleNamespace(loop=LoopConfig())))
    fake._odometry_edges = MethodType(SlamSystem._odometry_edges, fake)
    moved = SlamSystem._optimise_graph(fake, n - 1, est.copy(), rigid_from=8)
    after = state.est.numpy()
    applied = np.linalg.norm(after[kf_ids, :3, 3] - est[kf_ids, :3, 3], axis=1)
    np.testing.assert_allclose(moved, applied, atol=1e-12)
    optimum = corrected_keyframes(est[kf_ids], kf_ids, state.loops, LoopConfig(),
                                  fake._odometry_edges(kf_ids, est))
    assert abs(np.linalg.norm(optimum[2, :3, 3] - est[8, :3, 3]) - applied[2]) > 1e-3  # the two differ here
    assert np.allclose(after[8], after[12] @ np.linalg.solve(est[12], est[8]))  # 8 moved rigidly with 12
    assert fake._local_target is None
