"""EHE mesh (docs/ehe.md §6): marching cubes over the allocated voxels, or only over those whose 8 priors were
initialised (`ehe.mesh_voxels`), on a plane the priors represent exactly."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.slam.ehe.config import EheConfig
from inrslam.slam.ehe.field import EheField
from inrslam.slam.ehe.mesh import voxel_mesh

UNIT = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]])
Z0 = 0.55  # the plane z = Z0 inside the voxel layer k = 5


def plane_field() -> EheField:
    """A field whose SDF is (z − Z0)/T exactly: priors of every vertex set to it, decoders zero; voxels (2..5, 2..5,
    5) allocated, the 8 priors of only those with i <= 3 marked initialised."""
    cfg = EheConfig()
    field = EheField(cfg, UNIT, kernel="torch")
    for p in field.parameters():
        if p is not field.voxels.priors.table:
            torch.nn.init.zeros_(p)
    vg = field.voxels
    vx, vy, vz = vg.vdims
    k, j, i = torch.meshgrid(torch.arange(vz), torch.arange(vy), torch.arange(vx), indexing="ij")
    z = k.reshape(-1).float() * vg.voxel_size  # vertex id i + vx·(j + vy·k): k slowest
    with torch.no_grad():
        vg.priors.table[:, 0] = (z - Z0) / cfg.truncation
    ijk = torch.tensor([[a, b, 5] for a in range(2, 6) for b in range(2, 6)])
    keys = vg.key(ijk)
    vg.allocated[keys] = True
    vg.vertex_used[vg.vertex_ids(keys).reshape(-1)] = True
    vg.vertex_init[vg.vertex_ids(keys[ijk[:, 0] <= 3]).reshape(-1)] = True
    return field


@pytest.mark.parametrize("voxels, x_hi", [("allocated", 0.6), ("initialised", 0.4)])
def test_the_mesh_covers_the_chosen_voxels_and_lies_on_the_plane(voxels, x_hi):
    mesh = voxel_mesh(plane_field(), n=4, color=False, voxels=voxels)
    v = np.asarray(mesh.vertices)
    np.testing.assert_allclose(v[:, 2], Z0, atol=1e-5)  # trilinear priors of a linear SDF: exact
    assert v[:, 0].min() == pytest.approx(0.2, abs=1e-6) and v[:, 0].max() == pytest.approx(x_hi, abs=1e-6)
    assert v[:, 1].min() == pytest.approx(0.2, abs=1e-6) and v[:, 1].max() == pytest.approx(0.6, abs=1e-6)
    assert mesh.area == pytest.approx((x_hi - 0.2) * 0.4, rel=1e-4)


def test_an_unknown_voxel_rule_is_refused():
    with pytest.raises(ValueError, match="allocated.*initialised"):
        voxel_mesh(plane_field(), n=2, color=False, voxels="seen")
