"""Built-in scenes: geometry/pose conventions, determinism, sensor effects, cache behaviour, exporters."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from inrslam.geometry.angles import rotation_angle_deg_np
from inrslam.geometry.pinhole import backproject_np, project_np
from inrslam.io.trajectory import read_tum
from inrslam.scenes import DEFAULT_SCENE, SceneConfig, export_replica, export_tum, list_scenes, load_scene, store
from inrslam.scenes.layouts import SCENES
from inrslam.scenes.sensor import hole_mask
from inrslam.scenes.trajectory import camera_poses, dense_loop

SMALL = dict(frames=8, width=80, height=60)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One private cache folder shared by the tests of this module."""
    with pytest.MonkeyPatch.context() as mp:
        path = tmp_path_factory.mktemp("scene-cache")
        mp.setenv("INRSLAM_CACHE", str(path))
        yield path


@pytest.fixture(scope="module")
def room(cache):
    return load_scene("room", SceneConfig(frames=12, width=80, height=60))


def _rot_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    return rotation_angle_deg_np(np.einsum("...ji,...jk->...ik", Ra, Rb))


def distance_to_mesh(points: np.ndarray, mesh: trimesh.Trimesh, max_dist: float = np.inf,
                     chunk: int = 128) -> np.ndarray:
    """Exact point-to-surface distance (brute force with a bounding-box prefilter; no rtree needed): the oracle the
    scene checks measure clearance and depth consistency with.

    Args:
        points: (N, 3) metres.
        mesh: triangle mesh.
        max_dist: distances above this are reported as `max_dist` (prunes far triangles).
        chunk: points per batch.
    Returns:
        (N,) float64 metres, min(distance, max_dist).
    """
    points = np.asarray(points, dtype=np.float64)
    tris = mesh.triangles
    lo, hi = tris.min(axis=1), tris.max(axis=1)
    out = np.full(len(points), max_dist, dtype=np.float64)
    for s in range(0, len(points), chunk):
        p = points[s:s + chunk]
        gap = np.maximum(lo[None] - p[:, None], 0) + np.maximum(p[:, None] - hi[None], 0)
        box_d = np.sqrt((gap * gap).sum(-1))  # (n, F) lower bound of the distance to each triangle
        if np.isfinite(max_dist):
            pi, fi = np.nonzero(box_d < max_dist)
        else:
            # keep triangles whose box distance is below the smallest upper bound (farthest box corner)
            far = np.sqrt((np.maximum(np.abs(p[:, None] - lo[None]), np.abs(p[:, None] - hi[None])) ** 2).sum(-1))
            pi, fi = np.nonzero(box_d <= far.min(axis=1, keepdims=True))
        if len(pi) == 0:
            continue
        closest = trimesh.triangles.closest_point(tris[fi], p[pi])
        d = np.linalg.norm(closest - p[pi], axis=1)
        res = out[s:s + chunk]
        np.minimum.at(res, pi, d)
        out[s:s + chunk] = res
    return out


def test_registry_lists_three_scenes_and_names_close_match():
    names = [name for name, _ in list_scenes()]
    assert DEFAULT_SCENE == "room" and names[0] == "room"
    assert {"room", "cluttered", "thin"} <= set(names)
    assert all(desc for _, desc in list_scenes())
    with pytest.raises(KeyError, match="did you mean 'room'"):
        load_scene("rooom", SceneConfig(**SMALL))


@pytest.mark.parametrize("name", ["room", "cluttered", "thin"])
def test_layout_clearance_and_camera_motion(name):
    for seed in (0, 1, 2):
        layout = SCENES.get(name)(seed)
        mesh, room = layout.geometry.mesh, layout.geometry.room
        # every camera position of the (closed) loop is >= 0.4 m from every surface
        assert distance_to_mesh(dense_loop(layout.path, 400), mesh, max_dist=1.0).min() >= 0.4
        poses = camera_poses(layout.path, layout.default_frames)
        t = poses[:, :3, 3]
        assert np.all((t > room[:, 0] + 0.4) & (t < room[:, 1] - 0.4))
        step = np.linalg.norm(np.diff(t, axis=0), axis=1)
        assert 0.004 < step.min() and step.max() < 0.015 and 0.007 < step.mean() < 0.011
        rot = _rot_deg(poses[:-1, :3, :3], poses[1:, :3, :3])
        assert 0.2 < rot.mean() < 1.0 and rot.max() < 1.5
        R = poses[:, :3, :3]
        np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
        assert np.all(R[:, 2, 1] < -0.7)  # OpenCV: camera y (down) points down in the z-up world
        assert np.all(R[:, 2, 2] < 0)  # looking slightly downwards
    # motion_scale multiplies the speed (and the angular speed)
    fast = camera_poses(layout.path, 50, motion_scale=2.0)
    slow = camera_poses(layout.path, 50, motion_scale=1.0)
    ratio = np.linalg.norm(np.diff(fast[:, :3, 3], axis=0), axis=1).sum() / np.linalg.norm(
        np.diff(slow[:, :3, 3], axis=0), axis=1).sum()
    assert ratio == pytest.approx(2.0, rel=0.02)
    assert _rot_deg(fast[:-1, :3, :3], fast[1:, :3, :3]).mean() > 1.6 * _rot_deg(slow[:-1, :3, :3], slow[1:, :3, :3]).mean()


def test_dataset_protocol_and_frames(room):
    from inrslam.data.frame import RGBDDataset

    assert isinstance(room, RGBDDataset) and room.name == "builtin"
    assert len(room) == 12 and room.intrinsics.width == 80 and room.intrinsics.height == 60
    assert room.intrinsics.fx == pytest.approx(64.0) and room.intrinsics.cx == pytest.approx(39.5)
    fr = room[3]
    assert fr.rgb.shape == (60, 80, 3) and fr.rgb.dtype == np.float32 and 0 <= fr.rgb.min() and fr.rgb.max() <= 1
    assert fr.depth.shape == (60, 80) and fr.depth.dtype == np.float32
    assert fr.timestamp == pytest.approx(3 / 30.0) and fr.pose_valid and fr.index == 3
    assert (fr.depth > 0).all() and fr.depth.max() < 6.0  # closed room: every ray hits
    assert fr.rgb.std() > 0.05  # textured
    np.testing.assert_array_equal(fr.c2w, room.poses[3])
    assert room.bounds.shape == (3, 2) and room.gt_mesh.is_file()
    assert [f.index for f in room] == list(range(12)) and room[-1].index == 11
    with pytest.raises(IndexError):
        room[12]
    # bounds = room box + 0.1 m, and every camera is inside
    assert np.all(room.poses[:, :3, 3] > room.bounds[:, 0] + 0.5) and np.all(room.poses[:, :3, 3] < room.bounds[:, 1] - 0.5)


def test_depth_is_metric_z_depth_on_the_mesh(room):
    mesh = trimesh.load(room.gt_mesh, process=False)
    intr = room.intrinsics
    rng = np.random.default_rng(0)
    for i in (0, 7):
        fr = room[i]
        v, u = rng.integers(0, intr.height, 300), rng.integers(0, intr.width, 300)
        z = fr.depth[v, u].astype(np.float64)
        cam = np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], axis=1)
        world = cam @ fr.c2w[:3, :3].T + fr.c2w[:3, 3]
        d = distance_to_mesh(world, mesh, max_dist=0.05)
        assert np.max(d) < 1e-3, np.max(d)
        # the ray length is longer than the z-depth off-centre: storing ray length would miss the surface
        ray_len = z * np.sqrt(1 + ((u - intr.cx) / intr.fx) ** 2 + ((v - intr.cy) / intr.fy) ** 2)
        wrong = (cam / z[:, None] * ray_len[:, None]) @ fr.c2w[:3, :3].T + fr.c2w[:3, 3]
        assert np.median(distance_to_mesh(wrong, mesh, max_dist=0.05)) > 5e-3


def _reprojection_error(src, dst, c2w_src, c2w_dst) -> tuple[float, float]:
    """Median |z_pred - z_dst| (m) of src pixels warped into dst, and the fraction that lands inside dst.

    z_dst is read at the sub-pixel location by bilinear interpolation of inverse depth (exact on planes);
    pixels whose four neighbours disagree by more than 5% (depth edges) are skipped.
    """
    intr = src.intrinsics
    pts = backproject_np(src.depth, intr.fx, intr.fy, intr.cx, intr.cy)
    T = np.linalg.inv(c2w_dst) @ c2w_src
    u, v, z = project_np(pts @ T[:3, :3].T + T[:3, 3], intr.fx, intr.fy, intr.cx, intr.cy)
    ok = (z > 0.1) & (u >= 0) & (u <= intr.width - 1) & (v >= 0) & (v <= intr.height - 1)
    u0 = np.clip(np.floor(u[ok]).astype(int), 0, intr.width - 2)
    v0 = np.clip(np.floor(v[ok]).astype(int), 0, intr.height - 2)
    fu, fv = u[ok] - u0, v[ok] - v0
    inv = 1.0 / dst.depth.astype(np.float64)
    q = np.stack([inv[v0, u0], inv[v0, u0 + 1], inv[v0 + 1, u0], inv[v0 + 1, u0 + 1]])
    smooth = q.max(0) < 1.05 * q.min(0)
    inv_i = (q[0] * (1 - fu) + q[1] * fu) * (1 - fv) + (q[2] * (1 - fu) + q[3] * fu) * fv
    err = np.abs(z[ok] - 1.0 / inv_i)[smooth]
    return float(np.median(err)), float(ok.mean())


def test_pose_convention_reprojects_depth_between_frames(room):
    a, b = room[0], room[8]
    err, inside = _reprojection_error(a, b, a.c2w, b.c2w)
    assert inside > 0.5
    assert err < 1e-3, err  # acceptance is 1 cm; exact poses + 0.2 mm depth steps give ~0.05 mm
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # the same poses read as OpenGL axes must not fit
    err_gl, inside_gl = _reprojection_error(a, b, a.c2w @ flip, b.c2w @ flip)
    assert inside_gl > 0.3 and err_gl > 0.05
    err_w2c, _ = _reprojection_error(a, b, np.linalg.inv(a.c2w), np.linalg.inv(b.c2w))  # world-to-camera misread
    assert err_w2c > 0.01


def test_same_seed_identical_different_seed_differs(cache, tmp_path, monkeypatch):
    cfg = SceneConfig(**SMALL, seed=3)
    a = load_scene("thin", cfg)
    monkeypatch.setenv("INRSLAM_CACHE", str(tmp_path))  # regenerate from scratch elsewhere
    b = load_scene("thin", cfg)
    assert a.root != b.root
    np.testing.assert_array_equal(a.poses, b.poses)
    for i in (0, 7):
        np.testing.assert_array_equal(a[i].rgb, b[i].rgb)
        np.testing.assert_array_equal(a[i].depth, b[i].depth)
    c = load_scene("thin", SceneConfig(**SMALL, seed=4))
    assert np.abs(c.poses[:, :3, 3] - a.poses[:, :3, 3]).max() > 0.05
    assert not np.array_equal(c.bounds, a.bounds)
    # noise is deterministic from the seed too
    n1 = load_scene("thin", SceneConfig(**SMALL, seed=3, depth_noise=0.01))
    n2 = load_scene("thin", SceneConfig(**SMALL, seed=3, depth_noise=0.01))
    np.testing.assert_array_equal(n1[2].depth, n2[2].depth)
    assert not np.array_equal(n1[2].depth, n1.depth(2, clean=True))
    assert not np.array_equal(n1[2].depth - n1.depth(2, clean=True), n1[3].depth - n1.depth(3, clean=True))


def test_sensor_effects_match_configuration(cache):
    clean = load_scene("room", SceneConfig(**SMALL))
    holes = load_scene("room", SceneConfig(**SMALL, missing_depth=0.2))
    noisy = load_scene("room", SceneConfig(**SMALL, depth_noise=0.01))
    assert holes.root == clean.root == noisy.root  # one cached render; effects applied on read
    for i in range(len(clean)):
        d0, dh = clean[i].depth, holes[i].depth
        zero = dh == 0
        assert zero.mean() == pytest.approx(0.2, abs=0.01)
        np.testing.assert_array_equal(dh[~zero], d0[~zero])
        # holes come in blobs: a hole's right neighbour is mostly a hole too (iid pixels would give ~0.2)
        assert (zero[:, 1:] & zero[:, :-1]).sum() / zero[:, :-1].sum() > 0.7
    res = np.concatenate([((noisy[i].depth - clean[i].depth) / clean[i].depth ** 2).ravel() for i in range(len(clean))])
    assert res.std() == pytest.approx(0.01, rel=0.05) and abs(res.mean()) < 1e-3
    m = hole_mask((48, 64), 0.35, np.random.default_rng(1))
    assert m.mean() == pytest.approx(0.35, abs=0.005)


def test_cache_reused_and_robust_to_partial_folders(tmp_path, monkeypatch):
    monkeypatch.setenv("INRSLAM_CACHE", str(tmp_path))
    cfg = SceneConfig(frames=4, width=64, height=48)
    params = store.render_params("room", cfg)
    final = store.scene_dir(params)
    assert final.parent == tmp_path / "scenes"
    # a half-written temp folder of a killed process, and a broken final folder (no meta.json)
    junk = final.parent / f".tmp-{final.name}-99999-deadbeef"
    (junk / "rgb").mkdir(parents=True)
    (junk / "rgb" / "000000.png").write_bytes(b"\x89PNG broken")
    (final / "depth").mkdir(parents=True)
    ds = load_scene("room", cfg)
    assert ds.root == final and store.is_complete(final) and len(ds) == 4
    assert ds[3].depth.max() > 0
    assert sorted(p.name for p in final.parent.iterdir() if not p.name.startswith(".tmp-")) == [final.name]
    mtime = (final / "meta.json").stat().st_mtime_ns

    def no_generate(*a, **k):
        raise AssertionError("regenerated a cached scene")

    monkeypatch.setattr(store, "generate", no_generate)
    again = load_scene("room", cfg)
    assert again.root == final and (final / "meta.json").stat().st_mtime_ns == mtime
    np.testing.assert_array_equal(again[1].rgb, ds[1].rgb)
    # a different configuration is a different folder
    assert store.scene_dir(store.render_params("room", SceneConfig(frames=5, width=64, height=48))) != final


def test_concurrent_generation_loser_uses_winner(tmp_path, monkeypatch):
    monkeypatch.setenv("INRSLAM_CACHE", str(tmp_path))
    cfg = SceneConfig(frames=3, width=64, height=48)
    final = store.scene_dir(store.render_params("room", cfg))
    real = store.generate

    def racing(layout, params, out):  # another process finishes first while we render
        real(layout, params, final)
        real(layout, params, out)

    monkeypatch.setattr(store, "generate", racing)
    ds = load_scene("room", cfg)
    assert ds.root == final and len(ds) == 3
    assert not [p for p in final.parent.iterdir() if p.name.startswith(".tmp-")]


def test_export_replica_layout(room, tmp_path):
    out = export_replica(room, tmp_path / "room_replica")
    n = len(room)
    res = out / "results"
    assert sorted(p.name for p in res.iterdir()) == sorted(
        [f"frame{k:06d}.jpg" for k in range(n)] + [f"depth{k:06d}.png" for k in range(n)])
    rows = (out / "traj.txt").read_text().strip().splitlines()
    assert len(rows) == n
    traj = np.array([[float(x) for x in r.split()] for r in rows])
    assert traj.shape == (n, 16)
    np.testing.assert_allclose(traj.reshape(n, 4, 4), room.poses, atol=1e-10)
    with Image.open(res / "depth000005.png") as im:
        raw = np.asarray(im)
    assert raw.dtype == np.uint16
    np.testing.assert_allclose(raw / 6553.5, room[5].depth, atol=0.5 / 6553.5 + 1e-6)
    with Image.open(res / "frame000005.jpg") as im:
        assert im.format == "JPEG"
        jpg = np.asarray(im).astype(np.float32) / 255
    assert np.abs(jpg - room[5].rgb).mean() < 0.03
    assert (out / "mesh.ply").is_file()
    assert json.loads((out / "cam_params.json").read_text())["camera"]["scale"] == 6553.5


def test_export_tum_layout(room, tmp_path):
    out = export_tum(room, tmp_path / "room_tum")
    n = len(room)

    def entries(name):
        return [line.split() for line in (out / name).read_text().splitlines() if line and not line.startswith("#")]

    rgb, depth = entries("rgb.txt"), entries("depth.txt")
    assert len(rgb) == len(depth) == n
    t_rgb = np.array([float(t) for t, _ in rgb])
    t_depth = np.array([float(t) for t, _ in depth])
    np.testing.assert_allclose(t_rgb, np.arange(n) / 30.0, atol=1e-6)
    np.testing.assert_allclose(t_depth - t_rgb, 0.005, atol=1e-6)
    assert [f for _, f in rgb] == [f"rgb/{t:.6f}.png" for t in t_rgb]
    assert sorted(os.listdir(out / "rgb")) == sorted(Path(f).name for _, f in rgb)
    assert sorted(os.listdir(out / "depth")) == sorted(Path(f).name for _, f in depth)
    with Image.open(out / depth[4][1]) as im:
        raw = np.asarray(im)
    assert raw.dtype == np.uint16
    np.testing.assert_allclose(raw / 5000.0, room[4].depth, atol=0.5 / 5000 + 1e-6)
    with Image.open(out / rgb[4][1]) as im:
        np.testing.assert_array_equal(np.asarray(im), np.round(room[4].rgb * 255).astype(np.uint8))
    ts, poses = read_tum(out / "groundtruth.txt")
    assert len(entries("groundtruth.txt")) == n
    np.testing.assert_allclose(ts, t_rgb, atol=1e-6)
    np.testing.assert_allclose(poses, room.poses, atol=1e-6)


class _FailsAt:
    """`room` whose frame `k` cannot be read: an export that stops there."""

    def __init__(self, ds, k: int):
        self.ds, self.k, self.intrinsics, self.gt_mesh = ds, k, ds.intrinsics, getattr(ds, "gt_mesh", None)

    def __iter__(self):
        for i in range(len(self.ds)):
            if i == self.k:
                raise KeyboardInterrupt  # Ctrl-C in the middle
            yield self.ds[i]


@pytest.mark.parametrize("export", [export_replica, export_tum])
def test_an_interrupted_export_leaves_no_half_dataset(room, tmp_path, export):
    out = tmp_path / "new"
    with pytest.raises(KeyboardInterrupt):
        export(_FailsAt(room, 5), out)
    assert not out.exists() and os.listdir(tmp_path) == []  # nor a temporary folder
    (tmp_path / "empty").mkdir()
    with pytest.raises(KeyboardInterrupt):
        export(_FailsAt(room, 5), tmp_path / "empty")
    assert os.listdir(tmp_path / "empty") == []
    done = export(room, tmp_path / "empty")  # an empty folder is filled as a whole
    assert sorted(os.listdir(tmp_path)) == ["empty"] and (done / "mesh.ply").is_file()
    if export is export_tum:
        assert "# file: 'empty'" in (done / "rgb.txt").read_text()  # the folder's own name, not the temporary one


@pytest.mark.parametrize("name", ["loop", "symmetric"])
def test_loop_scenes_go_once_around_and_come_back(name):
    layout = SCENES.get(name)(0)
    mesh, room = layout.geometry.mesh, layout.geometry.room
    assert layout.default_frames >= 300
    assert distance_to_mesh(dense_loop(layout.path, 400), mesh, max_dist=1.0).min() >= 0.4
    poses = camera_poses(layout.path, layout.default_frames)
    t = poses[:, :3, 3]
    assert np.all((t > room[:, 0] + 0.4) & (t < room[:, 1] - 0.4))
    pts = dense_loop(layout.path)
    length = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1).sum()
    travelled = np.linalg.norm(np.diff(t, axis=0), axis=1).sum()
    assert travelled == pytest.approx(1.06 * length, rel=0.03)  # once around, and a little on
    assert np.linalg.norm(t[-20:, None] - t[None, :20], axis=-1).min() < 0.05  # the end revisits the start
    # faster segments: the per-frame step varies by +-40 %
    step = np.linalg.norm(np.diff(t, axis=0), axis=1)
    assert step.max() > 1.25 * step.mean() and step.min() < 0.75 * step.mean()


def test_symmetric_scene_is_identical_under_quarter_turns():
    mesh = SCENES.get("symmetric")(0).geometry.mesh
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    turned = mesh.vertices @ quarter.T
    # every turned vertex lies on the original geometry (the posters' thickness aside)
    assert distance_to_mesh(turned[:: max(1, len(turned) // 2000)], mesh, max_dist=0.1).max() < 0.02


@pytest.mark.parametrize("key,value,message", [
    ("seed", -1, "data.builtin.seed: expected an integer >= 0, got -1"),
    ("width", -2, r"data.builtin.width: expected >= 0"),
    ("motion_scale", 0.0, "data.builtin.motion_scale: expected > 0"),
])
def test_bad_scene_parameters_are_config_errors(key, value, message):
    from inrslam.errors import ConfigError

    with pytest.raises(ConfigError, match=message):
        store.render_params("room", SceneConfig(**{key: value}))
