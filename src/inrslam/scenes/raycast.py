"""Ray-cast RGB-D rendering of a textured `SceneGeometry` (numpy + trimesh; embree when `embreex` imports).

Rays follow the package convention: pixel centres at integer (u, v), camera direction
d_cam = ((u - cx) / fx, (v - cy) / fy, 1). With d_world = R d_cam the hit point is o + t d_world, so the ray
parameter t *is* the z-depth. t is recomputed in float64 from the hit triangle's plane,
t = n . (a - o) / n . d_world, so depth is exact up to float64 rounding.
"""

from __future__ import annotations

import numpy as np
import trimesh

from inrslam.geometry.intrinsics import Intrinsics
from inrslam.geometry.pinhole import image_directions_np
from inrslam.scenes.geometry import SceneGeometry, shade
from inrslam.scenes.textures import box_uv, material_arrays, sample_atlas, texture_atlas


def make_intersector(mesh: trimesh.Trimesh):
    """Embree intersector when `embreex` imports, else trimesh's pure-numpy one (which needs `rtree`)."""
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    except ImportError:
        from trimesh.ray.ray_triangle import RayMeshIntersector

        return RayMeshIntersector(mesh)


def camera_dirs(intr: Intrinsics) -> np.ndarray:
    """(H*W, 3) float64 camera-frame directions with z = 1, row-major over (v, u)."""
    return image_directions_np(intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height)


class Renderer:
    """Renders RGB and z-depth images of a scene from camera-to-world poses (OpenCV axes)."""

    def __init__(self, geom: SceneGeometry):
        self.geom = geom
        self.mesh = geom.mesh
        self._intersector = make_intersector(geom.mesh)
        self._atlas = texture_atlas(geom.materials)
        self._tiles, self._offsets = material_arrays(geom.materials)
        self._normals = np.asarray(geom.mesh.face_normals, dtype=np.float64)
        self._anchor = np.asarray(geom.mesh.triangles[:, 0, :], dtype=np.float64)
        self._shade = shade(self._normals)

    def render(self, c2w: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """One view. Returns rgb (H, W, 3) float32 in [0, 1] and depth (H, W) float32 metres (0 = no hit)."""
        rgb, depth = self.render_many(np.asarray(c2w)[None], intr)
        return rgb[0], depth[0]

    def render_many(self, c2w: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Several views in one intersector call.

        Args:
            c2w: (B, 4, 4) camera-to-world poses, OpenCV axes, metres.
            intr: intrinsics.
        Returns:
            rgb (B, H, W, 3) float32 in [0, 1]; depth (B, H, W) float32 z-depth in metres, 0 where nothing is hit.
        """
        c2w = np.asarray(c2w, dtype=np.float64)
        B, H, W = len(c2w), intr.height, intr.width
        d_cam = camera_dirs(intr)
        R = c2w[:, None, :3, :3]  # d_world = R d_cam, written out (tiny matmuls are slow under BLAS threading)
        dirs = (d_cam[None, :, 0:1] * R[..., 0] + d_cam[None, :, 1:2] * R[..., 1] + d_cam[None, :, 2:3] * R[..., 2]).reshape(-1, 3)
        cam_o = c2w[:, :3, 3]
        origins = np.repeat(cam_o, H * W, axis=0)
        tri, ray = self._intersector.intersects_id(origins, dirs, multiple_hits=False, return_locations=False)[:2]
        tri = np.asarray(tri, dtype=np.int64)
        ray = np.asarray(ray, dtype=np.int64)

        n = self._normals[tri]
        o, d = cam_o[ray // (H * W)], dirs[ray]
        denom = np.einsum("ij,ij->i", n, d)
        ok = np.abs(denom) > 1e-12
        t = np.einsum("ij,ij->i", n, self._anchor[tri] - o) / np.where(ok, denom, 1.0)
        ok &= t > 0
        if not ok.all():
            tri, ray, t, n, o, d = tri[ok], ray[ok], t[ok], n[ok], o[ok], d[ok]
        pts = o + d * t[:, None]

        mat = self.geom.face_material[tri]
        uv = box_uv(pts, n, self._tiles[mat], self._offsets[mat])
        col = sample_atlas(self._atlas, mat, uv) * self._shade[tri][:, None]

        rgb = np.zeros((B * H * W, 3), dtype=np.float32)
        depth = np.zeros(B * H * W, dtype=np.float32)
        rgb[ray] = np.clip(col, 0.0, 1.0)
        depth[ray] = t
        return rgb.reshape(B, H, W, 3), depth.reshape(B, H, W)
