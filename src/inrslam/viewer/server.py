"""The viser scene and panel of finished runs (`inrslam view RUN_DIR ...`).

Each run sits under its own scene node `/run0`, `/run1`, ... holding `mesh`, `trajectory` (estimate, the run's
colour), `trajectory_gt` (grey), `keyframes/NNNNNN` (camera frusta) and `heldout` (the frustum of the held-out frame
chosen in the panel, showing its observed image). The panel has one folder per run (show / hide, metrics, the
held-out pictures observed | render | depth | error, a timeline of the intermediate meshes) and, for several runs, a
table comparing them. viser is imported only here and in `live` (the optional extra `inrslam[viewer]`).
"""

from __future__ import annotations

import contextlib
import io
import logging
import socket
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from inrslam.errors import InrslamError, RunError
from inrslam.viewer.content import RunContent, gather, panel_views
from inrslam.viewer.shapes import GT_COLOR, frustum_pose, overview_camera, run_color, up_direction
from inrslam.viewer.tables import comparison_markdown, metrics_markdown

if TYPE_CHECKING:
    from inrslam.runner.loaded import LoadedRun

LINE_PX = 3.0  # trajectory line width, screen pixels
FRUSTUM_PX = 1.5


def require_viser():
    """The viser module, or a one-line InrslamError saying how to install it."""
    try:
        import viser
    except ImportError:
        raise InrslamError("the viewer needs viser: pip install 'inrslam[viewer]' (or pip install viser)") from None
    return viser


def start_server(host: str = "127.0.0.1", port: int = 8080):
    """A running `viser.ViserServer` on `host`:`port` (the next free port if it is taken; 0 = any free port),
    without viser's banner (callers print `url_lines`)."""
    viser = require_viser()
    # a browser that drops a connection before its handshake (a page reload, a preconnect) is not an error here
    logging.getLogger("websockets.server").setLevel(logging.CRITICAL)
    with contextlib.redirect_stdout(io.StringIO()):
        return viser.ViserServer(host=host, port=port, verbose=False)


def stop_server(server) -> None:
    """Stop a server quietly (viser prints a line when it stops)."""
    with contextlib.redirect_stdout(io.StringIO()):
        server.stop()


def url_lines(host: str, port: int) -> list[str]:
    """What to print for a user: the URL, and the SSH tunnel that reaches it from another machine."""
    shown = "localhost" if host in ("0.0.0.0", "::", "") else host
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"  # an IPv6 address in a URL
    return [f"viewer: http://{shown}:{port}",
            f"viewer on a remote machine: ssh -L {port}:localhost:{port} {socket.gethostname()}, then open "
            f"http://localhost:{port}"]


@dataclass
class RunViewer:
    """A server showing runs. `nodes`: scene nodes by name (`/run0/mesh`, ...); `gui`: panel elements by name
    (`run0/show`, `run0/image`, `compare`, ...); `contents`: what was gathered of each run."""

    server: Any
    contents: list[RunContent]
    nodes: dict[str, Any] = field(default_factory=dict)
    gui: dict[str, Any] = field(default_factory=dict)

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.port}"

    def stop(self) -> None:
        stop_server(self.server)

    def wait(self) -> None:
        """Serve until Ctrl-C, then stop."""
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()


def serve(runs: Sequence[LoadedRun], host: str = "127.0.0.1", port: int = 8080) -> RunViewer:
    """Start a server showing `runs` (from `inrslam.load_run`) and return at once; `.wait()` blocks, `.stop()`
    ends it."""
    server = start_server(host, port)
    try:
        return show_runs(server, runs)
    except BaseException:
        stop_server(server)  # its port and threads are not left behind
        raise


def show_runs(server, runs: Sequence[LoadedRun]) -> RunViewer:
    """Fill `server`'s scene and panel with `runs` (what was there before is cleared)."""
    server.scene.reset()
    server.gui.reset()
    viewer = RunViewer(server, [gather(r) for r in runs])
    if viewer.contents:
        up = up_direction(viewer.contents[0].est)
        server.scene.set_up_direction(tuple(up))
    if len(viewer.contents) > 1:
        viewer.gui["compare"] = server.gui.add_markdown(
            comparison_markdown([c.label for c in viewer.contents], [c.metrics for c in viewer.contents]))
    points = [np.zeros((0, 3))]
    for k, content in enumerate(viewer.contents):
        points += _add_run(viewer, k, content)
    if viewer.contents:
        position, look_at = overview_camera(np.concatenate(points), up)
        server.initial_camera.position, server.initial_camera.look_at = tuple(position), tuple(look_at)
    return viewer


def read_picture(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 of a PNG; RunError naming the file when it cannot be read."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as e:
        raise RunError(f"{path}: unreadable picture ({type(e).__name__}: {str(e)[:80]})") from None


def load_mesh(path: Path):
    """A trimesh of a PLY; RunError naming the file when it cannot be read."""
    import trimesh

    try:
        return trimesh.load(path, process=False, force="mesh")
    except Exception as e:  # noqa: BLE001 - a damaged PLY fails anywhere in trimesh's parsers
        raise RunError(f"{path}: unreadable mesh ({type(e).__name__}: {str(e)[:80]})") from None


def mesh_glb(mesh) -> bytes:
    """GLB of a trimesh (vertex colours as stored) for viser's `add_glb`, with vertex normals for smooth shading."""
    from trimesh.exchange.gltf import export_glb

    return export_glb(mesh, include_normals=True)


def add_mesh(server, name: str, mesh):
    """Show `mesh` (a trimesh) as scene node `name` (replacing one of that name); returns its handle."""
    return server.scene.add_glb(name, mesh_glb(mesh))


def _add_run(v: RunViewer, k: int, c: RunContent) -> list[np.ndarray]:
    """Draw run `k` and its panel folder; returns the points it spans (camera centres, mesh bounds)."""
    scene, gui, root = v.server.scene, v.server.gui, f"/run{k}"
    spans = [c.est[:, :3, 3]]
    v.nodes[root] = scene.add_frame(root, show_axes=False)
    if c.mesh is not None:
        try:
            mesh = load_mesh(c.mesh)
        except RunError as e:
            c.notes.append(str(e))
        else:
            v.nodes[f"{root}/mesh"] = add_mesh(v.server, f"{root}/mesh", mesh)
            if mesh.bounds is not None:
                spans.append(np.asarray(mesh.bounds))
    if len(c.est_segments):
        v.nodes[f"{root}/trajectory"] = scene.add_line_segments(
            f"{root}/trajectory", c.est_segments, run_color(k), thickness=LINE_PX, thickness_units="screen")
    if c.gt_segments is not None and len(c.gt_segments):
        v.nodes[f"{root}/trajectory_gt"] = scene.add_line_segments(
            f"{root}/trajectory_gt", c.gt_segments, GT_COLOR, thickness=LINE_PX, thickness_units="screen")
    for fid, c2w in c.keyframes.items():
        name = f"{root}/keyframes/{fid:06d}"
        wxyz, pos = frustum_pose(c2w)
        v.nodes[name] = scene.add_camera_frustum(name, c.fov_y, c.aspect, scale=c.frustum_scale, color=run_color(k),
                                                 wxyz=wxyz, position=pos, thickness=FRUSTUM_PX,
                                                 thickness_units="screen")
    with gui.add_folder(f"{k}: {c.label}"):
        show = v.gui[f"run{k}/show"] = gui.add_checkbox("show", True)
        show.on_update(lambda _: setattr(v.nodes[root], "visible", show.value))
        v.gui[f"run{k}/metrics"] = gui.add_markdown(metrics_markdown(c.metrics))
        if c.notes:
            v.gui[f"run{k}/notes"] = gui.add_markdown("\n".join(f"- {n}" for n in c.notes))
        if c.renders:
            _add_renders(v, k, c)
        if c.meshes:
            _add_timeline(v, k, c)
    return spans


def _latest(control, lock: threading.Lock, show: Any) -> Any:
    """A callback for `control` that calls show(value): one at a time (viser runs callbacks on a thread pool) and
    only for a value not shown yet, read after the lock, so the scene ends at the control's last value."""
    shown: list[Any] = [object()]

    def on_update(_) -> None:
        with lock:
            value = control.value
            if value != shown[0]:
                show(value)
                shown[0] = value

    return on_update


def _picture(path: Path, status) -> np.ndarray | None:
    """read_picture, or None with the error shown in `status` (a markdown element)."""
    try:
        picture = read_picture(path)
    except RunError as e:
        status.content = f"{e}"
        return None
    status.content = ""
    return picture


def _add_renders(v: RunViewer, k: int, c: RunContent) -> None:
    """A dropdown of the held-out frames, their picture in the panel and on a frustum at the frame's pose."""
    scene, gui, name = v.server.scene, v.server.gui, f"/run{k}/heldout"
    frames = list(c.renders)
    pick = v.gui[f"run{k}/frame"] = gui.add_dropdown("held-out frame", [str(f) for f in frames],
                                                      initial_value=str(frames[0]))
    status = v.gui[f"run{k}/frame_status"] = gui.add_markdown("")
    first = _picture(c.renders[frames[0]], status)
    blank = np.zeros((8, 32, 3), np.uint8)
    image = v.gui[f"run{k}/image"] = gui.add_image(blank if first is None else first,
                                                   label="observed | render | depth | error", format="jpeg")

    def place(frame: int, picture: np.ndarray) -> None:
        if frame >= len(c.est) or not np.isfinite(c.est[frame]).all():
            return
        wxyz, pos = frustum_pose(c.est[frame])
        v.nodes[name] = scene.add_camera_frustum(name, c.fov_y, c.aspect, scale=1.5 * c.frustum_scale,
                                                 color=run_color(k), image=panel_views(picture), format="jpeg",
                                                 wxyz=wxyz, position=pos, thickness=2 * FRUSTUM_PX,
                                                 thickness_units="screen")

    def show(value: str) -> None:
        picture = _picture(c.renders[int(value)], status)
        image.image = blank if picture is None else picture
        if picture is not None:
            place(int(value), picture)

    if first is not None:
        place(frames[0], first)
    pick.on_update(_latest(pick, threading.Lock(), show))


def _add_timeline(v: RunViewer, k: int, c: RunContent) -> None:
    """A slider over the intermediate meshes (meshes/mesh_NNNNNN.ply) and the final mesh.ply."""
    steps: list[tuple[str, Path]] = [(f"after frame {f}", p) for f, p in c.meshes.items()]
    if c.mesh is not None:
        steps.append(("final", c.mesh))
    gui, name = v.server.gui, f"/run{k}/mesh"
    slider = v.gui[f"run{k}/timeline"] = gui.add_slider("mesh", 0, len(steps) - 1, 1, len(steps) - 1)
    shown = v.gui[f"run{k}/timeline_label"] = gui.add_markdown(f"mesh: {steps[-1][0]}")

    def show(value: float) -> None:
        label, path = steps[int(value)]
        try:
            mesh = load_mesh(path)
        except RunError as e:
            shown.content = f"mesh: {label}: {e}"
            return
        v.nodes[name] = add_mesh(v.server, name, mesh)
        shown.content = f"mesh: {label}"

    on_move = _latest(slider, threading.Lock(), show)
    if c.mesh is None:
        on_move(None)
    slider.on_update(on_move)
