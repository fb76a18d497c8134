"""Mesh extraction (spec §8.5) on an analytic sphere SDF: orientation, accuracy, colours, chunking, memory."""

from __future__ import annotations

import tracemalloc
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch import nn

from inrslam.slam.mesh_extraction import _module_device, extract_mesh, sdf_volume

T = 0.1
CENTRE = np.array([0.1, -0.05, 0.2])
RADIUS = 0.287  # not a multiple of the grid step: no grid vertex exactly on the surface
BOUNDS = np.array([[-0.3, 0.5], [-0.45, 0.35], [-0.2, 0.6]])
RES = 0.02
LOGITS = (0.5, -1.0, 2.0)


class SphereField(nn.Module):
    """SDF of a sphere in T-units (negative inside) with constant colour logits; no parameters or buffers unless
    `buffer` (so the device lookup is exercised both ways)."""

    def __init__(self, buffer: bool = False):
        super().__init__()
        self.centre = torch.tensor(CENTRE, dtype=torch.float32)
        if buffer:
            self.register_buffer("dummy", torch.zeros(1))
        self.calls: list[int] = []

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        self.calls.append(x.shape[0])
        return ((x - self.centre.to(x.device)).norm(dim=-1) - RADIUS) / T

    def forward(self, x: torch.Tensor):
        rgb = torch.tensor(LOGITS, device=x.device).expand(x.shape[0], 3)
        return SimpleNamespace(sdf=self.sdf(x), rgb_logits=rgb)


@pytest.mark.parametrize("buffer", [False, True])
def test_sphere_mesh_outward_accurate_coloured(buffer):
    mesh = extract_mesh(SphereField(buffer), BOUNDS, resolution=RES, chunk=5000)
    assert mesh is not None and len(mesh.faces) > 1000
    assert mesh.volume > 0
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * RADIUS ** 3, rel=0.02)
    v = np.asarray(mesh.vertices)
    # vertices on the sphere within half a grid cell (marching cubes on an exact distance is far better than that)
    assert np.abs(np.linalg.norm(v - CENTRE, axis=1) - RADIUS).max() < RES / 2
    # faces point outward: the face normal agrees with the direction from the centre
    tri = v[np.asarray(mesh.faces)]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    dots = np.einsum("ij,ij->i", normals, tri.mean(1) - CENTRE)
    assert (dots > 0).mean() > 0.99
    assert not (dots < 0).any()
    # vertex colours = sigmoid(logits), as 8-bit RGBA
    col = np.asarray(mesh.visual.vertex_colors)
    expected = 1.0 / (1.0 + np.exp(-np.array(LOGITS)))
    assert np.abs(col[:, :3] / 255.0 - expected).max() <= 1.0 / 255 + 1e-9
    assert (col[:, 3] == 255).all()


def test_no_zero_crossing_returns_none():
    far = np.array([[1.0, 1.5], [1.0, 1.5], [1.0, 1.5]])  # the sphere is outside this box
    assert extract_mesh(SphereField(), far, resolution=0.1) is None


def test_chunked_volume_matches_full_grid():
    axes = [np.linspace(b[0], b[1], k) for b, k in zip(BOUNDS, (41, 23, 17))]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    pts = torch.from_numpy(np.stack([gx, gy, gz], -1).reshape(-1, 3).astype(np.float32))
    ref = SphereField().sdf(pts).numpy().reshape(41, 23, 17)
    for chunk in (7, 100, 23 * 17, 3 * 23 * 17 + 5, 10 ** 6):
        field = SphereField()
        vol = sdf_volume(field, axes, chunk=chunk)
        assert vol.dtype == np.float32 and vol.shape == (41, 23, 17)
        assert np.array_equal(vol, ref), chunk  # same float32 points as the full meshgrid, bit for bit
        assert max(field.calls) <= chunk and sum(field.calls) == ref.size


def test_grid_is_never_materialised():
    """Host memory of an extraction stays O(volume floats): no float64 meshgrids or (N, 3) copy of the grid."""
    n = 81 ** 3
    bounds = np.array([[-0.5, 0.5]] * 3)
    tracemalloc.start()
    try:
        mesh = extract_mesh(SphereField(), bounds, resolution=1 / 80, chunk=4096, color=False)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert mesh is not None
    # the float32 volume is 4 n bytes (plus the marching-cubes output); the old full grid peaked at ~60 n
    assert peak < 3 * 4 * n


def test_module_device_from_parameters_or_buffers():
    assert _module_device(SphereField()) == torch.device("cpu")
    lin = nn.Linear(2, 2, device="meta")  # parameters only, no buffers
    assert _module_device(lin).type == "meta"
    m = nn.Module()
    m.register_buffer("b", torch.zeros(1, device="meta"))
    assert _module_device(m).type == "meta"
