"""Scene geometry from trimesh primitives: a builder that tags every face with a material, and mesh helpers.

World frame of every built-in scene: metres, z up, floor at z = 0, the room an axis-aligned box whose walls
face inward. Objects are closed primitives (boxes, cylinders, spheres) that rest on surfaces without
interpenetrating much, so the merged mesh is "watertight-ish" (each part is closed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from inrslam.scenes.textures import Material, box_uv, material_arrays, sample_atlas, texture_atlas

LIGHT_DIR = np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81])
"""World direction towards the (distant) light used for Lambertian shading."""


def shade(normals: np.ndarray) -> np.ndarray:
    """View-independent shading factor for (N, 3) unit normals: 0.75 + 0.25 n.l, in [0.5, 1]. Returns (N,)."""
    return (0.75 + 0.25 * (normals @ LIGHT_DIR)).astype(np.float32)


@dataclass
class SceneGeometry:
    """A textured scene mesh.

    Attributes:
        mesh: merged triangle mesh (world metres, z up).
        face_material: (F,) int index into `materials` per face.
        materials: list of materials.
        room: (3, 2) inner box of the room [[xmin, xmax], [ymin, ymax], [zmin, zmax]], metres.
    """

    mesh: trimesh.Trimesh
    face_material: np.ndarray
    materials: list[Material]
    room: np.ndarray

    def vertex_colors(self) -> np.ndarray:
        """(V, 4) uint8 RGBA per vertex: the texture sampled at the vertex with one adjacent face's mapping.

        Primitives are small, so this is a coarse stand-in for the rendered appearance (for viewing / coloured
        mesh metrics), not a resampling of the full texture.
        """
        mesh = self.mesh
        face_of_vertex = np.zeros(len(mesh.vertices), dtype=np.int64)
        face_of_vertex[mesh.faces.reshape(-1)] = np.repeat(np.arange(len(mesh.faces)), 3)
        mat = self.face_material[face_of_vertex]
        normals = mesh.face_normals[face_of_vertex]
        tiles, offsets = material_arrays(self.materials)
        uv = box_uv(mesh.vertices, normals, tiles[mat], offsets[mat])
        rgb = sample_atlas(texture_atlas(self.materials), mat, uv) * shade(normals)[:, None]
        rgba = np.concatenate([np.clip(rgb, 0, 1) * 255.0, np.full((len(rgb), 1), 255.0)], axis=1)
        return np.round(rgba).astype(np.uint8)


class GeometryBuilder:
    """Collects primitives with materials and merges them into a `SceneGeometry`."""

    def __init__(self, room: np.ndarray):
        self.room = np.asarray(room, dtype=np.float64)
        self._parts: list[trimesh.Trimesh] = []
        self._part_mat: list[int] = []
        self._part_face_mat: list[np.ndarray | None] = []
        self.materials: list[Material] = []

    def material(self, mat: Material) -> int:
        """Index of `mat` (added if new)."""
        if mat not in self.materials:
            self.materials.append(mat)
        return self.materials.index(mat)

    def _add(self, mesh: trimesh.Trimesh, mat: Material, face_mat: np.ndarray | None = None) -> None:
        self._parts.append(mesh)
        self._part_mat.append(self.material(mat))
        self._part_face_mat.append(face_mat)

    def add_room(self, floor: Material, ceiling: Material, walls: list[Material]) -> None:
        """The room box with inward-facing walls; `walls` = materials of the -x, +x, -y, +y walls."""
        lo, hi = self.room[:, 0], self.room[:, 1]
        box = trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))
        # reversed winding: normals point into the room (a fresh mesh, as `invert()` may keep stale cached normals)
        box = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)
        n = box.face_normals
        idx = np.empty(len(n), dtype=np.int64)
        ids = [self.material(m) for m in walls]
        idx[n[:, 0] > 0.5] = ids[0]  # the -x wall faces +x
        idx[n[:, 0] < -0.5] = ids[1]
        idx[n[:, 1] > 0.5] = ids[2]
        idx[n[:, 1] < -0.5] = ids[3]
        idx[n[:, 2] > 0.5] = self.material(floor)
        idx[n[:, 2] < -0.5] = self.material(ceiling)
        self._parts.append(box)
        self._part_mat.append(-1)
        self._part_face_mat.append(idx)

    def add_box(self, center, extents, mat: Material, yaw: float = 0.0) -> None:
        """Box with `extents` (3,) metres centred at `center` (3,), rotated by `yaw` radians about z."""
        T = trimesh.transformations.rotation_matrix(yaw, (0, 0, 1))
        T[:3, 3] = center
        self._add(trimesh.creation.box(extents=extents, transform=T), mat)

    def add_box_on(self, xy, z0: float, extents, mat: Material, yaw: float = 0.0) -> None:
        """Box resting on height `z0` (its bottom face), centred at `xy`."""
        self.add_box((xy[0], xy[1], z0 + extents[2] / 2), extents, mat, yaw)

    def add_cylinder(self, p0, p1, radius: float, mat: Material, sections: int = 16) -> None:
        """Closed cylinder of `radius` metres between points `p0` and `p1` (3,)."""
        seg = np.array([p0, p1], dtype=np.float64)
        self._add(trimesh.creation.cylinder(radius=radius, segment=seg, sections=sections), mat)

    def add_post(self, xy, z0: float, z1: float, radius: float, mat: Material, sections: int = 16) -> None:
        """Vertical cylinder at `xy` from height `z0` to `z1`."""
        self.add_cylinder((xy[0], xy[1], z0), (xy[0], xy[1], z1), radius, mat, sections)

    def add_sphere(self, center, radius: float, mat: Material, subdivisions: int = 2) -> None:
        """Icosphere of `radius` metres."""
        s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
        s.apply_translation(center)
        self._add(s, mat)

    def build(self) -> SceneGeometry:
        """Merge the parts; face materials follow the parts' order."""
        face_mats = []
        for part, m, fm in zip(self._parts, self._part_mat, self._part_face_mat):
            face_mats.append(fm if fm is not None else np.full(len(part.faces), m, dtype=np.int64))
        mesh = trimesh.util.concatenate(self._parts)
        return SceneGeometry(mesh=mesh, face_material=np.concatenate(face_mats), materials=list(self.materials),
                             room=self.room.copy())

