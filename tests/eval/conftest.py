"""Scene builders for the evaluation tests (fine grids, boxes, cameras)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from inrslam.data.frame import Intrinsics


def grid_plane(size: float, n: int, z: float = 0.0) -> trimesh.Trimesh:
    """Finely tessellated square (size x size m, n x n cells) at height z, normal +z, centred on the z axis."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return trimesh.Trimesh(V, F, process=False)


def fine_box(extents, center, subdivisions: int = 3) -> trimesh.Trimesh:
    """Closed box with subdivided faces (so culling decisions are per small face)."""
    box = trimesh.creation.box(extents=extents)
    for _ in range(subdivisions):
        box = box.subdivide()
    box.apply_translation(center)
    return box


@pytest.fixture
def intr() -> Intrinsics:
    """64 x 64 px camera, f = 50 px: half field of view tan = 32/50 (1.28 m half-width at 2 m)."""
    return Intrinsics(fx=50.0, fy=50.0, cx=31.5, cy=31.5, width=64, height=64)


@pytest.fixture
def make_plane():
    return grid_plane


@pytest.fixture
def make_box():
    return fine_box
