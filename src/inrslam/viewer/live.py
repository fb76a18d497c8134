"""The live view of a running SLAM loop (`inrslam run --viewer`): a progress callback that moves the current camera,
redraws the trajectory so far and, every few frames and within a time budget, the map's mesh.

It never waits on the browser: viser queues each update and sends it from its own thread. The costly part, the
marching-cubes mesh of the current map (0.2-2 s at 5 cm), runs on the SLAM thread only every `mesh_every` frames and
only while the meshes so far plus one more as costly as the last stay within `mesh_budget` of the loop's time (the
first mesh is always made), so the view slows the loop by about that fraction at most (benchmarks/bench_viewer.py
measures it).
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np

from inrslam.errors import InrslamWarning
from inrslam.viewer.server import add_mesh
from inrslam.viewer.shapes import (
    CURRENT_COLOR,
    DEFAULT_ASPECT,
    DEFAULT_FOV_Y,
    GT_COLOR,
    frustum_pose,
    frustum_scale,
    overview_camera,
    polyline_segments,
    run_color,
    up_direction,
    valid_poses,
)

MESH_EVERY = 20  # frames between two meshes
MESH_RESOLUTION = 0.05  # m, marching-cubes grid of the live mesh
MESH_BUDGET = 0.05  # at most this fraction of the loop's time goes to live meshes
REDRAW_S = 0.1  # trajectory and status are redrawn at most this often (the camera every frame)


def to_numpy(poses: Any) -> np.ndarray:
    """(N, 4, 4) float64 copy of a torch tensor or array of poses."""
    if hasattr(poses, "detach"):
        poses = poses.detach().cpu().double().numpy()
    return np.array(poses, dtype=np.float64)


class LiveViewer:
    """Progress callback `(i, n_frames, info)` showing the run on a viser `server` (info: `SlamSystem.progress_info`).

    Scene: `/live/camera` (current frustum), `/live/trajectory`, `/live/trajectory_gt`, `/live/keyframes/NNNNNN`,
    `/live/mesh`; panel: a status line. `meshes` / `mesh_s` count the meshes sent and the seconds they cost,
    `busy_s` all seconds the callback took on the SLAM thread (meshes included).
    """

    def __init__(self, server, mesh_every: int = MESH_EVERY, mesh_resolution: float = MESH_RESOLUTION,
                 mesh_budget: float = MESH_BUDGET, fov_y: float = DEFAULT_FOV_Y, aspect: float = DEFAULT_ASPECT):
        self.server = server
        self.mesh_every, self.mesh_resolution, self.mesh_budget = mesh_every, mesh_resolution, mesh_budget
        self.fov_y, self.aspect = fov_y, aspect
        self.nodes: dict[str, Any] = {}
        self.status = server.gui.add_markdown("*waiting for the first frame*")
        self.meshes, self.mesh_s, self.skipped_meshes, self.busy_s = 0, 0.0, 0, 0.0
        self._last_cost = 0.0  # s, the last mesh
        self._t0: float | None = None
        self._redrawn = -np.inf
        self._mesh_frame = 0  # frame of the last mesh attempt
        self._mesh_at = 0  # frame of the mesh shown
        self._scale = 0.1
        self._up = np.array([0.0, 0.0, 1.0])
        self.failed: str | None = None  # why the viewer stopped drawing (an error in it), or None

    def __call__(self, i: int, n: int, info: dict) -> None:
        if self.failed is not None:
            return
        now = time.perf_counter()
        try:
            self._update(i, n, info, now)
        except Exception as e:  # noqa: BLE001 - the viewer must never stop the SLAM run it shows
            self.failed = f"{type(e).__name__}: {str(e)[:120]}"
            warnings.warn(f"the live viewer stopped at frame {i} ({self.failed}); the run goes on", InrslamWarning,
                          stacklevel=2)
        finally:
            self.busy_s += time.perf_counter() - now

    def _update(self, i: int, n: int, info: dict, now: float) -> None:
        if self._t0 is None:
            self._t0 = now
        est = to_numpy(info["est"])
        self._camera(est[-1])
        if now - self._redrawn >= REDRAW_S or i == n - 1:
            self._redrawn = now
            self._paths(est, info.get("gt"))
            self._keyframes(est, info.get("keyframes", []), refresh=False)
            self._status(i, n, info)
        if self.mesh_every > 0 and i - self._mesh_frame >= self.mesh_every and callable(info.get("mesh")):
            if self.mesh_s + self._last_cost <= self.mesh_budget * (now - self._t0):  # the next one, if as costly
                self._mesh(info["mesh"], i, est)
                self._keyframes(est, info.get("keyframes", []), refresh=True)  # bundle adjustment moved them
            else:
                self.skipped_meshes += 1
            self._mesh_frame = i

    def _camera(self, c2w: np.ndarray) -> None:
        if not np.isfinite(c2w).all():
            return
        wxyz, pos = frustum_pose(c2w)
        cam = self.nodes.get("/live/camera")
        if cam is None:
            self.nodes["/live/camera"] = self.server.scene.add_camera_frustum(
                "/live/camera", self.fov_y, self.aspect, scale=1.5 * self._scale, color=CURRENT_COLOR, wxyz=wxyz,
                position=pos, thickness=3.0, thickness_units="screen")
        else:
            cam.wxyz, cam.position = wxyz, pos

    def _paths(self, est: np.ndarray, gt: Any) -> None:
        scene = self.server.scene
        if "/live/trajectory" not in self.nodes and valid_poses(est).sum() >= 2:
            self._up = up_direction(est)
            scene.set_up_direction(tuple(self._up))
        self._scale = frustum_scale(est)
        for name, poses, color in (("/live/trajectory", est, run_color(0)),
                                   ("/live/trajectory_gt", None if gt is None else to_numpy(gt), GT_COLOR)):
            seg = polyline_segments(poses) if poses is not None else np.zeros((0, 2, 3), np.float32)
            if len(seg):
                self.nodes[name] = scene.add_line_segments(name, seg, color, thickness=3.0, thickness_units="screen")

    def _keyframes(self, est: np.ndarray, ids: list[int], refresh: bool) -> None:
        for fid in ids:
            name = f"/live/keyframes/{fid:06d}"
            if fid >= len(est) or not np.isfinite(est[fid]).all() or (name in self.nodes and not refresh):
                continue
            wxyz, pos = frustum_pose(est[fid])
            if name in self.nodes:
                self.nodes[name].wxyz, self.nodes[name].position = wxyz, pos
            else:
                self.nodes[name] = self.server.scene.add_camera_frustum(
                    name, self.fov_y, self.aspect, scale=self._scale, color=run_color(0), wxyz=wxyz, position=pos,
                    thickness=1.5, thickness_units="screen")

    def _mesh(self, extract, i: int, est: np.ndarray) -> None:
        t = time.perf_counter()
        mesh = extract(self.mesh_resolution)
        if mesh is not None and len(mesh.faces):
            self.nodes["/live/mesh"] = add_mesh(self.server, "/live/mesh", mesh)
            self.meshes += 1
            if self.meshes == 1:  # a browser opened from now on starts with the whole map in view
                cam = self.server.initial_camera
                cam.position, cam.look_at = overview_camera(np.concatenate([mesh.bounds, est[:, :3, 3]]), self._up)
        self._last_cost = time.perf_counter() - t
        self.mesh_s += self._last_cost
        self._mesh_at = i

    def _status(self, i: int, n: int, info: dict) -> None:
        text = f"**SLAM** frame {i + 1} / {n}, tracking {float(info.get('track_ms', 0.0)):.0f} ms"
        if self.meshes:
            text += f"; mesh after frame {self._mesh_at} ({self.mesh_resolution * 100:.0f} cm grid)"
        self.status.content = text
