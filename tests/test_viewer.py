"""The browser viewer: what it draws (analytic poses, NaN gaps, tables), a served viewer of two tiny fake run
directories (scene nodes, panel, HTTP), the `view` command's errors, the live callback, and a headless-browser page
load (skipped without Debian's chromium). No SLAM run: the run directories are written by hand."""

from __future__ import annotations

import json
import math
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from headless_browser import CHROMIUM, load_page
from polling import wait_for
from scipy.spatial.transform import Rotation

from inrslam.bench.testing import write_fake_run
from inrslam.cli import main
from inrslam.viewer.shapes import (
    camera_fov,
    frustum_pose,
    frustum_scale,
    overview_camera,
    polyline_segments,
    run_color,
    up_direction,
)
from inrslam.viewer.tables import comparison_markdown, comparison_rows, metrics_markdown

INTRINSICS = {"fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5, "width": 64, "height": 48}


def look_at_x() -> np.ndarray:
    """c2w of a camera at (1, 2, 3) looking along world +x with its image 'down' (+y) along world -z."""
    c2w = np.eye(4)
    c2w[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: x_c, y_c, z_c in world
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    return c2w


# ---------------------------------------------------------------------------------------------------------------
# what to draw


def test_frustum_pose_is_the_camera_to_world_pose():
    c2w = look_at_x()
    wxyz, pos = frustum_pose(c2w)
    assert np.allclose(pos, [1.0, 2.0, 3.0])
    assert math.isclose(float(np.linalg.norm(wxyz)), 1.0)
    R = Rotation.from_quat(np.roll(wxyz, -1)).as_matrix()  # scalar-first back to scipy's scalar-last
    assert np.allclose(R, c2w[:3, :3])
    assert np.allclose(R @ [0, 0, 1], [1, 0, 0])  # the frustum's +z (OpenCV forward) points where the camera looks


def test_frustum_pose_agrees_with_viser_rotation_convention():
    tf = pytest.importorskip("viser.transforms", reason="viser is not installed (pip install -e '.[viewer]')")
    wxyz, _ = frustum_pose(look_at_x())
    assert np.allclose(tf.SO3(wxyz).as_matrix(), look_at_x()[:3, :3])


def test_polyline_breaks_at_frames_without_a_pose():
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 0, 3] = np.arange(5.0)
    poses[2] = np.nan
    seg = polyline_segments(poses)
    assert seg.shape == (2, 2, 3) and seg.dtype == np.float32
    assert np.allclose(seg[:, :, 0], [[0, 1], [3, 4]])  # 0-1 and 3-4; nothing bridges the missing frame 2
    assert polyline_segments(poses[:1]).shape == (0, 2, 3)


def test_camera_fov_and_frustum_scale():
    fov, aspect = camera_fov({"fx": 80.0, "fy": 100.0, "cx": 0, "cy": 0, "width": 300, "height": 200})
    assert math.isclose(fov, math.pi / 2) and math.isclose(aspect, 1.5)  # 2 atan(100 / 100) = 90 degrees
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 2.0, 4.0]
    assert math.isclose(frustum_scale(poses), 0.16)  # 4 % of a 4 m path


def test_up_direction_follows_the_cameras():
    assert np.allclose(up_direction(look_at_x()[None]), [0, 0, 1])  # image down = world -z
    flipped = look_at_x()
    flipped[:3, 1] *= -1
    assert np.allclose(up_direction(np.stack([flipped, flipped])), [0, 0, -1])
    assert np.allclose(up_direction(np.full((2, 4, 4), np.nan)), [0, 0, 1])


def test_overview_camera_sees_the_scene_from_above():
    corners = np.array([[0.0, 0.0, 0.0], [2.0, 2.0, 2.0], [np.nan, 0.0, 0.0]])
    position, look_at = overview_camera(corners, np.array([0.0, 0.0, 1.0]))
    assert np.allclose(look_at, [1.0, 1.0, 1.0])
    offset = position - look_at
    assert math.isclose(float(np.linalg.norm(offset)), 0.9 * math.sqrt(12.0))  # 0.9 x the box diagonal
    assert math.isclose(math.degrees(math.asin(offset[2] / np.linalg.norm(offset))), 60.0)  # above the horizontal


def test_comparison_table_marks_the_best_and_the_missing():
    a = {"ate_rmse_m": 0.012, "psnr_db": 25.0, "comp_ratio": 0.8, "wall_time_s": 100.0}
    b = {"ate_rmse_m": 0.02, "psnr_db": 27.5, "acc_m": 0.015, "wall_time_s": 90.0}
    rows = comparison_rows(["a", "b"], [a, b])
    assert rows[0][:4] == ["a", "**1.20**", "–", "80.0"]  # ATE in cm, lowest bold; no Acc; one Comp: not bold
    assert rows[1][:3] == ["b", "2.00", "1.50"]
    assert rows[1][4] == "**27.50**" and rows[0][4] == "25.00"  # PSNR: highest is best
    assert rows[1][-1] == "**90**"
    md = comparison_markdown(["a", "b"], [a, None])
    assert md.splitlines()[0].startswith("| run | ATE [cm] |") and md.splitlines()[-1].count("–") == 6


def test_metrics_markdown_of_one_run():
    md = metrics_markdown({"ate_rmse_m": 0.0169, "frames": 200, "psnr_db": float("nan")})
    assert "| ATE [cm] | 1.69 |" in md and "| Frames | 200 |" in md and "PSNR" not in md
    assert "no metrics" in metrics_markdown(None)


# ---------------------------------------------------------------------------------------------------------------
# tiny run directories


def tiny_run(root: Path, encoding: str = "dense", full: bool = True) -> Path:
    """A fake finished run of 12 frames (bench.testing), plus, when `full`, what a real run adds: intrinsics,
    keyframes, a coloured mesh, an intermediate mesh and two held-out pictures."""
    import trimesh
    from PIL import Image

    rd = write_fake_run(root, encoding, "density", frames=12)
    info = json.loads((rd / "run_info.json").read_text())
    if not full:
        (rd / "trajectory_gt.txt").unlink()
        return rd
    (rd / "run_info.json").write_text(json.dumps({**info, "intrinsics": INTRINSICS}))
    (rd / "keyframes.json").write_text(json.dumps({"keyframes": [0, 5, 10]}))
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    box.visual.vertex_colors = np.tile([200, 50, 50, 255], (len(box.vertices), 1)).astype(np.uint8)
    box.export(rd / "mesh.ply")
    (rd / "meshes").mkdir()
    trimesh.creation.box((0.5, 0.5, 0.5)).export(rd / "meshes" / "mesh_000005.ply")
    (rd / "renders").mkdir()
    for frame, shade in ((3, 60), (8, 180)):
        picture = np.zeros((48, 4 * 64, 3), np.uint8)
        picture[:, :64] = shade
        Image.fromarray(picture).save(rd / "renders" / f"frame_{frame:06d}.png")
    return rd


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    import inrslam

    root = tmp_path_factory.mktemp("viewer")
    return [inrslam.load_run(tiny_run(root / "full")), inrslam.load_run(tiny_run(root / "bare", "hash", full=False))]


@pytest.fixture(scope="module")
def viewer(runs):
    pytest.importorskip("viser", reason="viser is not installed (pip install -e '.[viewer]')")
    from inrslam.viewer.server import serve

    v = serve(runs, port=0)
    yield v
    v.stop()


def test_gather_notes_what_a_run_lacks(runs):
    from inrslam.viewer.content import gather

    full, bare = gather(runs[0]), gather(runs[1])
    assert full.notes == [] and full.mesh is not None and list(full.renders) == [3, 8] and list(full.meshes) == [5]
    assert sorted(full.keyframes) == [0, 5, 10] and full.gt_segments is not None and len(full.est_segments) == 11
    assert bare.gt is None and bare.mesh is None and not bare.renders
    assert any("ground-truth" in n for n in bare.notes) and any("mesh.ply" in n for n in bare.notes)
    assert full.label == "full (dense x density)"


def test_served_viewer_holds_each_run(viewer, runs):
    n = viewer.nodes
    for name in ("/run0", "/run0/mesh", "/run0/trajectory", "/run0/trajectory_gt", "/run0/heldout",
                 "/run1", "/run1/trajectory"):
        assert name in n, name
    assert {k for k in n if k.startswith("/run0/keyframes/")} == {f"/run0/keyframes/{f:06d}" for f in (0, 5, 10)}
    assert "/run1/mesh" not in n and "/run1/trajectory_gt" not in n  # the bare run has neither
    kf = n["/run0/keyframes/000005"]
    assert np.allclose(kf.position, runs[0].est[5][:3, 3]) and np.allclose(kf.wxyz, frustum_pose(runs[0].est[5])[0])
    assert np.allclose(n["/run0/trajectory"].points, polyline_segments(runs[0].est), atol=1e-3)
    assert tuple(np.asarray(n["/run0/trajectory"].colors).reshape(-1, 3)[0]) == run_color(0)
    assert np.allclose(n["/run0/heldout"].position, runs[0].est[3][:3, 3])  # the first held-out frame
    assert "ATE [cm]" in viewer.gui["compare"].content and "full (dense x density)" in viewer.gui["compare"].content
    assert "ground-truth" in viewer.gui["run1/notes"].content
    assert viewer.gui["run0/image"].image.shape == (48, 256, 3)
    spanned = np.concatenate([runs[0].est[:, :3, 3], runs[1].est[:, :3, 3], [[-0.5] * 3, [0.5] * 3]])  # + the box
    look_at, position = viewer.server.initial_camera.look_at, viewer.server.initial_camera.position
    up = up_direction(runs[0].est)  # -y: the fake cameras have identity rotations
    assert np.allclose(up, [0, -1, 0]) and np.allclose(look_at, (spanned.min(0) + spanned.max(0)) / 2)
    assert (position - look_at) @ up > 1.0  # seen from above


def test_panel_controls_change_the_scene(viewer, runs):
    viewer.gui["run1/show"].value = False
    assert wait_for(lambda: viewer.nodes["/run1"].visible is False)
    viewer.gui["run1/show"].value = True
    assert wait_for(lambda: viewer.nodes["/run1"].visible is True)
    viewer.gui["run0/frame"].value = "8"  # the other held-out frame: its picture and its pose
    assert wait_for(lambda: np.allclose(viewer.nodes["/run0/heldout"].position, runs[0].est[8][:3, 3]))
    assert wait_for(lambda: int(viewer.gui["run0/image"].image[0, 0, 0]) == 180)
    final = viewer.nodes["/run0/mesh"]
    viewer.gui["run0/timeline"].value = 0  # the mesh after frame 5
    assert wait_for(lambda: viewer.nodes["/run0/mesh"] is not final)
    assert wait_for(lambda: viewer.gui["run0/timeline_label"].content == "mesh: after frame 5")


def test_damaged_files_of_a_run_are_notes_not_tracebacks(tmp_path, capsys):
    pytest.importorskip("viser", reason="viser is not installed (pip install -e '.[viewer]')")
    import inrslam
    from inrslam.viewer.content import gather
    from inrslam.viewer.server import serve

    rd = tiny_run(tmp_path / "damaged")
    (rd / "mesh.ply").write_bytes((rd / "mesh.ply").read_bytes()[:300])  # cut short inside its header / data
    (rd / "renders" / "frame_000003.png").write_bytes(b"\x89PNG\r\n\x1a\n cut")
    info = json.loads((rd / "run_info.json").read_text())
    (rd / "run_info.json").write_text(json.dumps({**info, "intrinsics": {"fx": 50.0, "fy": 0}}))
    content = gather(inrslam.load_run(rd))
    assert any(n.startswith("run_info.json: intrinsics") and "expected positive width, height and fy" in n
               for n in content.notes)
    v = serve([inrslam.load_run(rd)], port=0)
    try:
        assert "/run0/mesh" not in v.nodes and "mesh.ply: unreadable mesh" in v.gui["run0/notes"].content
        assert "frame_000003.png: unreadable picture" in v.gui["run0/frame_status"].content
        assert v.gui["run0/image"].image.shape == (8, 32, 3) and "/run0/heldout" not in v.nodes
        v.gui["run0/frame"].value = "8"  # a readable frame: its picture and frustum, the status cleared
        assert wait_for(lambda: v.gui["run0/frame_status"].content == "" and "/run0/heldout" in v.nodes)
    finally:
        v.stop()


def test_panel_callbacks_run_one_at_a_time_and_end_at_the_last_value():
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from inrslam.viewer.server import _latest

    class Control:  # what viser's controls offer the callback: the current value
        value = 0

    shown, running = [], []
    started, release = threading.Event(), threading.Event()

    def show(value):  # the first value is slow (a large mesh): it holds on until the others are queued
        running.append(value)
        assert len(running) == 1, "two callbacks at once"
        if value == 0:
            started.set()
            assert release.wait(10)
        shown.append(value)
        running.pop()

    control = Control()
    on_update = _latest(control, threading.Lock(), show)
    with ThreadPoolExecutor(4) as pool:  # viser: set the value, then submit the callback to its pool
        futures = [pool.submit(on_update, None)]
        assert started.wait(10)
        for value in (1, 2, 3):
            control.value = value
            futures.append(pool.submit(on_update, None))
        release.set()
        for f in futures:
            f.result()  # no assertion failed in a callback
    assert shown == [0, 3]  # the last value, once; the values passed over are never drawn


def test_server_answers_http(viewer):
    with urllib.request.urlopen(f"http://127.0.0.1:{viewer.port}/", timeout=10) as r:
        assert r.status == 200 and b"<html" in r.read(4096).lower()


def test_view_of_a_folder_without_a_run_is_a_one_line_error(tmp_path, capsys):
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("inrslam view: error: ") and "not a run directory" in err


def test_run_help_lists_the_viewer_flags(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    assert "--viewer" in out and "--viewer-port" in out and "--viewer-mesh-every" in out


# ---------------------------------------------------------------------------------------------------------------
# the live view


class FakeMesh:
    def __init__(self):
        import trimesh

        self.mesh = trimesh.creation.box((1.0, 1.0, 1.0))
        self.mesh.apply_translation([2.0, 0.0, 0.0])
        self.calls: list[float] = []

    def __call__(self, resolution):
        self.calls.append(resolution)
        return self.mesh


def test_live_viewer_follows_the_run_and_spaces_its_meshes():
    pytest.importorskip("viser", reason="viser is not installed (pip install -e '.[viewer]')")
    from inrslam.viewer.live import LiveViewer
    from inrslam.viewer.server import start_server, stop_server

    server = start_server(port=0)
    try:
        live = LiveViewer(server, mesh_every=4, mesh_budget=1e9)
        mesh = FakeMesh()
        est = np.tile(np.eye(4), (10, 1, 1))
        est[:, 0, 3] = np.arange(10) * 0.1
        gt = est.copy()
        gt[7] = np.nan
        est_t = torch.as_tensor(est, dtype=torch.float32)  # SlamSystem.progress_info gives torch poses, numpy GT
        for i in range(10):
            live(i, 10, {"track_ms": 5.0, "est": est_t[: i + 1], "gt": gt[: i + 1], "keyframes": [0, 5][: 1 + i // 5],
                         "mesh": mesh})
        assert np.allclose(live.nodes["/live/camera"].position, [0.9, 0, 0])
        assert len(live.nodes["/live/trajectory"].points) == 9 and len(live.nodes["/live/trajectory_gt"].points) == 7
        assert {k for k in live.nodes if "keyframes" in k} == {"/live/keyframes/000000", "/live/keyframes/000005"}
        assert mesh.calls == [0.05, 0.05] and live.meshes == 2  # frames 4 and 8
        assert np.allclose(server.initial_camera.look_at, [1.25, 0, 0])  # centre of the first mesh and path (x 0-2.5)
        assert "frame 10 / 10" in live.status.content
        assert 0 < live.busy_s < 5.0
        starved = LiveViewer(server, mesh_every=1, mesh_budget=0.0)  # no time for meshes: only the first is made
        for i in range(4):
            starved(i, 4, {"est": est[: i + 1], "mesh": mesh})
        assert starved.meshes == 1 and starved.skipped_meshes == 2 and len(mesh.calls) == 3
    finally:
        stop_server(server)


def test_an_error_in_the_live_viewer_warns_once_and_the_run_goes_on():
    pytest.importorskip("viser", reason="viser is not installed (pip install -e '.[viewer]')")
    from inrslam.errors import InrslamWarning
    from inrslam.viewer.live import LiveViewer
    from inrslam.viewer.server import start_server, stop_server

    def broken(resolution):
        raise ValueError("marching cubes found no surface")

    server = start_server(port=0)
    try:
        live = LiveViewer(server, mesh_every=1, mesh_budget=1e9)
        est = np.tile(np.eye(4), (4, 1, 1))
        with pytest.warns(InrslamWarning, match=r"live viewer stopped at frame 1 \(ValueError: marching cubes found "
                                                r"no surface\); the run goes on") as caught:
            for i in range(4):
                live(i, 4, {"est": est[: i + 1], "mesh": broken})  # frame 1 asks for the first mesh
        assert len(caught) == 1 and live.failed.startswith("ValueError")
    finally:
        stop_server(server)


# ---------------------------------------------------------------------------------------------------------------
# a real browser


@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium (apt-get install -y chromium) for the "
                                             "headless page test")
def test_the_page_renders_in_a_headless_browser(viewer, tmp_path):
    """The served page connects to the server (the panel shows the runs' folders, sent over the websocket), draws
    something and logs no error."""
    import io

    from PIL import Image

    page = load_page(f"http://127.0.0.1:{viewer.port}/",
                     "document.querySelector('canvas') && document.body.innerText.includes('full (dense x density)')")
    assert page.ready, page.text[:500]
    assert "bare (hash x density)" in page.text and "held-out frame" in page.text
    (tmp_path / "viewer.png").write_bytes(page.png)
    img = np.asarray(Image.open(io.BytesIO(page.png)).convert("RGB"))
    assert img.shape[:2] == (700, 1000)
    assert img.reshape(-1, 3).std(axis=0).max() > 10 and len(np.unique(img.reshape(-1, 3), axis=0)) > 50  # not blank
    assert not page.errors, page.errors


def test_the_printed_url_brackets_an_ipv6_host():
    from inrslam.viewer.server import url_lines

    assert url_lines("::1", 8080)[0] == "viewer: http://[::1]:8080"
    assert url_lines("127.0.0.1", 8080)[0] == "viewer: http://127.0.0.1:8080"
    assert url_lines("0.0.0.0", 8080)[0] == "viewer: http://localhost:8080"
