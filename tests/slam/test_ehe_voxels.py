"""EHE sparse voxels (docs/ehe.md §2): allocation and margin rule on a plane, projective-TSDF priors on a plane,
trilinear prior interpolation, and prior + residual composition of the field."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.geometry.intrinsics import Intrinsics
from inrslam.slam.ehe.config import EheConfig
from inrslam.slam.ehe.field import EheField
from inrslam.slam.ehe.voxels import VoxelGrid

UNIT = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]])


def plane_points(z: float, lo: float = 0.2, hi: float = 0.6, step: float = 0.01) -> torch.Tensor:
    """Points on z = const at the centres of a step-spaced grid over [lo, hi)^2 (10 x 10 per 10 cm voxel)."""
    a = torch.arange(lo + step / 2, hi, step, dtype=torch.float64)
    x, y = torch.meshgrid(a, a, indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1), torch.full((x.numel(),), z, dtype=torch.float64)], 1).float()


def allocated_ijk(vg: VoxelGrid) -> set[tuple[int, int, int]]:
    return {tuple(v) for v in vg.unkey(torch.nonzero(vg.allocated).squeeze(1)).tolist()}


def block(k_values) -> set[tuple[int, int, int]]:
    return {(i, j, k) for i in range(2, 6) for j in range(2, 6) for k in k_values}


@pytest.mark.parametrize("z, layers", [(0.55, [5]), (0.505, [4, 5]), (0.595, [5, 6])])
def test_a_plane_allocates_its_voxels_and_the_margin_rule_adds_face_neighbours(z, layers):
    vg = VoxelGrid(UNIT, 0.1)
    alloc = vg.allocate(plane_points(z), min_points=10, margin=0.1, max_vertices=10**6)
    # x, y: the points' mean sits mid-voxel (0.45 of an edge): no neighbours; z: within 10 % of a face -> the
    # neighbour across it
    assert allocated_ijk(vg) == block(layers)
    assert alloc.observed.tolist() == sorted(alloc.observed.tolist()) and alloc.new.numel() == 16 * len(layers)
    again = vg.allocate(plane_points(z), 10, 0.1, 10**6)
    assert again.new.numel() == 0 and again.observed.numel() == 16 * len(layers)
    assert vg.n_vertices == 25 * (len(layers) + 1)


def test_a_voxel_needs_more_than_min_points_and_the_vertex_cap_refuses_a_frame():
    vg = VoxelGrid(UNIT, 0.1)
    pts = torch.tensor([[0.15, 0.15, 0.15]]).repeat(10, 1)
    assert vg.allocate(pts, 10, 0.1, 10**6).observed.numel() == 0  # 10 points: not more than 10
    assert vg.allocate(torch.cat([pts, pts[:1]]), 10, 0.1, 10**6).new.numel() == 1
    capped = vg.allocate(plane_points(0.55), 10, 0.1, max_vertices=8 + 10)
    assert capped.capped and capped.new.numel() == 0 and vg.n_allocated == 1


def test_lookup_finds_allocated_voxels_only():
    vg = VoxelGrid(UNIT, 0.1)
    vg.allocate(plane_points(0.55), 10, 0.1, 10**6)
    keys = vg.lookup(torch.tensor([[0.25, 0.35, 0.52], [0.75, 0.35, 0.52], [1.5, 0.5, 0.5]]))
    assert vg.unkey(keys[:1]).tolist() == [[2, 3, 5]] and keys[1:].tolist() == [-1, -1]


def wall_setup(depth_value: float = 2.03):
    """Camera at (0, 0, 0) looking +z at a fronto-parallel wall z = depth_value, 100 x 100 px, ±1 m at 2 m."""
    bounds = np.array([[-1.0, 1.0], [-1.0, 1.0], [0.0, 3.0]])
    vg = VoxelGrid(bounds, 0.1)
    intr = Intrinsics(fx=50.0, fy=50.0, cx=49.5, cy=49.5, width=100, height=100)
    depth = torch.full((100, 100), depth_value)
    return vg, intr, depth, torch.eye(4)


def key_at(vg: VoxelGrid, x: float, y: float, z: float) -> torch.Tensor:
    ijk, inside = vg.coords(torch.tensor([[x, y, z]]))
    assert inside.all()
    return vg.key(ijk)


def test_tsdf_priors_on_a_wall_are_the_signed_distance_in_t_units_and_far_voxels_are_rejected():
    vg, intr, depth, c2w = wall_setup(2.03)
    T = 0.05
    near = key_at(vg, 0.05, 0.05, 2.05)  # corners at z = 2.0 and 2.1: distances +3 cm and -7 cm
    far = key_at(vg, 0.05, 0.05, 1.05)  # 1 m in front: |D - z| > sqrt(6) * 0.1 -> not accepted
    edge = key_at(vg, 0.95, 0.05, 1.55)  # x up to 1.0 m at z = 1.5-1.6 m: corners project outside the image
    keys = torch.cat([near, far, edge])
    vg.allocated[keys] = True
    assert vg.init_priors(keys, depth, intr, c2w, T) == 1
    vid = vg.vertex_ids(near)[0]
    corner_z = 2.0 + 0.1 * torch.tensor([c & 1 for c in range(8)], dtype=torch.float32)
    assert torch.allclose(vg.prior[vid], (2.03 - corner_z) / T, atol=1e-4)  # 0.6 T and -1.4 T
    assert vg.vertex_init[vid].all()
    assert not vg.vertex_init[vg.vertex_ids(far)].any() and (vg.prior[vg.vertex_ids(far)] == 0).all()
    # each vertex is initialised once: a later frame with another depth leaves them
    assert vg.init_priors(near, torch.full((100, 100), 2.08), intr, c2w, T) == 0
    assert torch.allclose(vg.prior[vid], (2.03 - corner_z) / T, atol=1e-4)


def test_a_voxel_cut_by_a_tilted_plane_gets_the_projective_distance_and_the_bound_is_sqrt6_voxels():
    vg, intr, _, c2w = wall_setup()
    v, u = torch.meshgrid(torch.arange(100.0), torch.arange(100.0), indexing="ij")
    # plane z = 2 + 0.2 x seen by the pinhole: depth at pixel (u, v) solves z = 2 + 0.2 z (u - cx) / fx
    depth = 2.0 / (1.0 - 0.2 * (u - intr.cx) / intr.fx)
    key = key_at(vg, 0.05, 0.05, 2.05)
    vg.allocated[key] = True
    assert vg.init_priors(key, depth, intr, c2w, 0.05) == 1
    vid = vg.vertex_ids(key)[0]
    corners = vg.unkey(key).float() * 0.1 + vg.origin + 0.1 * torch.tensor(
        [[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], dtype=torch.float32)
    u_px = torch.round(intr.fx * corners[:, 0] / corners[:, 2] + intr.cx).long()
    v_px = torch.round(intr.fy * corners[:, 1] / corners[:, 2] + intr.cy).long()
    expected = (depth[v_px, u_px] - corners[:, 2]) / 0.05
    assert torch.allclose(vg.prior[vid], expected, atol=1e-4)


def test_trilinear_prior_interpolation_reproduces_a_multilinear_function_exactly():
    bounds = np.array([[-0.3, 0.75], [0.0, 0.52], [0.1, 0.9]])  # extents not multiples of the voxel
    vg = VoxelGrid(bounds, 0.1)
    vx, vy, vz = vg.vdims
    idx = torch.arange(vx * vy * vz)
    ijk = torch.stack([idx % vx, (idx // vx) % vy, idx // (vx * vy)], 1).float()
    pos = vg.origin + 0.1 * ijk  # vertex positions, metres

    def f(p):  # multilinear: trilinear interpolation is exact for it inside every cell
        return 1.0 + 2.0 * p[:, 0] - p[:, 1] + 3.0 * p[:, 0] * p[:, 1] * p[:, 2]

    with torch.no_grad():
        vg.priors.table[:, 0] = f(pos)
    b = torch.tensor(bounds, dtype=torch.float32)
    x = b[:, 0] + torch.rand(500, 3, generator=torch.Generator().manual_seed(0)) * (b[:, 1] - b[:, 0])
    assert torch.allclose(vg.prior_at(x), f(x), atol=1e-5)
    # the gradient w.r.t. the priors is the 8 trilinear weights of each point (they sum to 1)
    vg.prior_at(x[:1]).sum().backward()
    g = vg.priors.table.grad.to_dense() if vg.priors.table.grad.is_sparse else vg.priors.table.grad
    assert torch.count_nonzero(g) <= 8 and abs(float(g.sum()) - 1.0) < 1e-5


def test_the_field_is_prior_plus_residual_and_its_fused_first_layer_equals_the_two_decoders():
    field = EheField(EheConfig(), UNIT)
    with torch.no_grad():
        field.voxels.priors.table.normal_()
        field.grid.table.normal_()
    x = torch.rand(64, 3, generator=torch.Generator().manual_seed(1))
    out = field(x)
    assert torch.allclose(out.sdf, field.voxels.prior_at(x) + field.residual(x), atol=1e-5)
    assert torch.allclose(field.sdf(x), out.sdf, atol=1e-5)
    p = field.normalise(x)
    assert torch.allclose(out.rgb_logits, field.rgb_net(torch.cat([p, field.grid(p)], 1)), atol=1e-5)
    assert all(m.bias is None for m in (*field.sdf_net[::2], *field.rgb_net[::2]))


def test_point_stats_kernel_matches_the_torch_reference_on_random_points():
    g = torch.Generator().manual_seed(0)
    vg = VoxelGrid(np.array([[-0.5, 1.0], [0.0, 0.7], [0.2, 1.3]]), 0.1)
    pts = torch.rand(20000, 3, generator=g) * 2.0 - 0.4  # about half of them outside the box
    pts[:5] = float("nan")  # skipped, as by the reference (outside any voxel)
    counts, sums = vg.point_stats(pts)
    ref_counts, ref_sums = vg.point_stats_torch(pts)
    assert torch.equal(counts, ref_counts) and 0 < counts.sum() < 20000
    assert torch.allclose(sums, ref_sums, atol=2e-4)
    occ = counts > 0
    mean = sums[occ] / counts[occ, None]
    assert (mean >= 0).all() and (mean < 1).all()
