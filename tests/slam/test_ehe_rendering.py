"""EHE ray marching, rendering and losses (docs/ehe.md §3-4) against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.slam.ehe.config import EheConfig
from inrslam.slam.ehe.losses import ehe_losses, packed_sdf_terms, sdf_terms
from inrslam.slam.ehe.model import EheModel
from inrslam.slam.ehe.raymarch import packed_samples_in_voxels, sample_in_voxels, voxel_hits
from inrslam.slam.ehe.rendering import EheRender, fill_padding, masked_direct_weights, packed_direct_weights
from inrslam.slam.ehe.voxels import VoxelGrid

UNIT = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]])


def grid_with(*ijk) -> VoxelGrid:
    vg = VoxelGrid(UNIT, 0.1)
    vg.allocated[vg.key(torch.tensor(ijk))] = True
    return vg


def test_voxel_hits_merge_adjacent_voxels_count_voxels_and_clip_to_the_box():
    vg = grid_with((3, 5, 5), (4, 5, 5), (7, 5, 5))
    o = torch.tensor([[0.0, 0.55, 0.55], [-0.5, 0.55, 0.55], [0.0, 0.05, 0.55]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    t_in, t_out, n = voxel_hits(vg, o, d, max_hits=10, t_max=10.0)
    assert n.tolist() == [2, 2, 0]
    assert np.allclose(t_in[0, :2], [0.3, 0.7]) and np.allclose(t_out[0, :2], [0.5, 0.8])
    assert np.allclose(t_in[1, :2], [0.8, 1.2]) and np.allclose(t_out[1, :2], [1.0, 1.3])  # starts outside the box
    t_in, t_out, n = voxel_hits(vg, o[:1], d[:1], max_hits=2, t_max=10.0)  # stops after its 2nd voxel
    assert n.tolist() == [1] and np.allclose([t_in[0, 0], t_out[0, 0]], [0.3, 0.5])
    t_in, t_out, n = voxel_hits(vg, o[:1], d[:1], max_hits=10, t_max=0.45)  # max depth cuts the interval
    assert n.tolist() == [1] and np.isclose(t_out[0, 0], 0.45)


def test_a_slanted_ray_leaves_a_voxel_where_it_crosses_its_face():
    # y = 0.52 + 0.5 t crosses y = 0.7 at t = 0.36, inside x in [0.3, 0.4] (t in [0.3, 0.4])
    vg = grid_with((3, 6, 5))
    t_in, t_out, n = voxel_hits(vg, torch.tensor([[0.0, 0.52, 0.55]]), torch.tensor([[1.0, 0.5, 0.0]]), 10, 10.0)
    assert n.tolist() == [1] and np.allclose([t_in[0, 0], t_out[0, 0]], [0.3, 0.36])


def test_samples_lie_every_step_inside_hit_voxels_only():
    vg = grid_with((3, 5, 5), (4, 5, 5), (7, 5, 5))
    s = sample_in_voxels(vg, torch.tensor([[0.0, 0.55, 0.55], [0.0, 0.05, 0.05]]),
                         torch.tensor([[2.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), step=0.01, max_hits=10, t_max=10.0)
    # |d| = 2: a metric step of 1 cm is 0.005 in t; u = 0.5 -> x = 2 t = 0.305, 0.315, ... inside the voxels
    z = s.z[0][s.valid[0]]
    x = 2 * z
    expected = np.concatenate([np.arange(0.305, 0.5, 0.01), np.arange(0.705, 0.8, 0.01)])
    assert np.allclose(x.numpy(), expected, atol=1e-5)
    assert s.valid.shape[1] == 30 and not s.valid[1].any() and s.n_hits.tolist() == [2, 0]
    assert (s.z[0, 29] == s.z[0][s.valid[0]][-1]).item()
    g = torch.Generator().manual_seed(0)
    jit = sample_in_voxels(vg, torch.tensor([[0.0, 0.55, 0.55]]), torch.tensor([[1.0, 0.0, 0.0]]), 0.01, 10, 10.0, g)
    zj = jit.z[0][jit.valid[0]]
    assert ((zj >= 0.3) & (zj < 0.5) | (zj >= 0.7) & (zj < 0.8)).all()
    assert torch.allclose(torch.diff(zj[:10]), torch.full((9,), 0.01), atol=1e-5)


def test_padding_and_masked_direct_weights():
    v = torch.tensor([[True, True, False]])
    assert fill_padding(torch.tensor([[1.0, 2.0, 9.0]]), v).tolist() == [[1.0, 2.0, 2.0]]
    # two valid samples at +-a around the zero crossing share the weight; padding and other rays get none
    sdf = torch.tensor([[0.2, -0.2, -0.2], [0.5, 0.5, 0.5]])
    z = torch.tensor([[1.0, 1.01, 1.01], [1.0, 1.0, 1.0]])
    w = masked_direct_weights(sdf, z, torch.tensor([[True, True, False], [False, False, False]]), 0.05)
    assert torch.allclose(w, torch.tensor([[0.5, 0.5, 0.0], [0.0, 0.0, 0.0]]), atol=1e-6)


def test_sdf_terms_on_a_hand_computed_ray():
    T, D = 0.1, 1.0
    z = torch.tensor([[0.5, 0.85, 0.95, 1.0, 1.05, 1.2]])
    s = torch.tensor([[1.0, 0.5, 0.5, 0.2, -0.5, -2.0]])
    valid = torch.ones_like(z, dtype=torch.bool)
    fs, sd = sdf_terms(s, z, valid, torch.tensor([D]), T)
    # front z < 0.9: (1-1)^2 + (0.5-1)^2 = 0.25; band |z - 1| <= 0.1: 0 + 0.02^2 + 0; N = 6 valid samples;
    # balance 1 - 2/5 and 1 - 3/5
    assert fs.item() == pytest.approx(0.6 * 0.25 / 6)
    assert sd.item() == pytest.approx(0.4 * 0.02 ** 2 / 6, rel=1e-4)
    none = sdf_terms(s, z, torch.zeros_like(valid), torch.tensor([D]), T)
    assert none[0].item() == 0 and none[1].item() == 0


def test_ehe_losses_are_l1_on_hit_rays_with_the_configured_weights():
    cfg = EheConfig()
    z = torch.tensor([[1.0, 1.01], [1.0, 1.0], [2.0, 2.0]])
    valid = torch.tensor([[True, True], [False, False], [True, True]])
    slot = torch.nonzero(valid.reshape(-1)).reshape(-1)
    out = EheRender(rgb=torch.tensor([[0.5, 0.5, 0.5], [0.0, 0.0, 0.0], [0.2, 0.2, 0.2]]),
                    depth=torch.tensor([1.005, 0.0, 2.0]), hit=valid.any(1), sdf=torch.zeros(4),
                    z=z.reshape(-1)[slot], ray=slot // 2, weights=torch.full((4,), 0.5),
                    start=torch.tensor([0, 2, 2, 4]))
    rgb = torch.tensor([[0.6, 0.5, 0.3], [1.0, 1.0, 1.0], [0.2, 0.2, 0.2]])
    depth = torch.tensor([1.0, 1.0, 0.0])  # ray 1 misses every voxel: no loss; ray 2 has no depth
    l = ehe_losses(out, rgb, depth, cfg)
    assert l["rgb"].item() == pytest.approx((0.1 + 0.0 + 0.2) / 6)
    assert l["depth"].item() == pytest.approx(0.005, rel=1e-4)
    fs, sd = sdf_terms(torch.zeros(3, 2), z, valid & torch.tensor([True, False, False])[:, None], depth,
                       cfg.truncation)
    assert l["total"].item() == pytest.approx(5 * l["rgb"].item() + 0.005 + 10 * fs.item() + 5e4 * sd.item(),
                                              rel=1e-5)


def random_padded_rays(seed: int, R: int = 40, S: int = 12, dtype=torch.float64):
    """Rays with 0..S leading valid samples (sorted z, SDF crossing zero on many rays), padded as the sampler does:
    sdf (R, S) requiring grad, z (R, S), valid (R, S), depth (R,), has_depth (R,)."""
    g = torch.Generator().manual_seed(seed)
    count = torch.randint(0, S + 1, (R,), generator=g)
    valid = torch.arange(S)[None, :] < count[:, None]
    z = 0.5 + torch.cumsum(torch.rand(R, S, generator=g, dtype=dtype) * 0.02, dim=1)
    z = fill_padding(z, valid)
    sdf = (torch.rand(R, 1, generator=g, dtype=dtype) * 2 - 0.5) - 3.0 * (z - z[:, :1])  # falls along the ray
    sdf = sdf + 0.05 * torch.randn(R, S, generator=g, dtype=dtype)
    depth = z[:, :1].squeeze(1) + torch.rand(R, generator=g, dtype=dtype) * 0.2
    has_depth = torch.rand(R, generator=g) < 0.8
    return fill_padding(sdf, valid).requires_grad_(), z, valid, depth, has_depth


def packed(values, valid):
    return values.reshape(-1)[torch.nonzero(valid.reshape(-1)).reshape(-1)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_packed_weights_and_sdf_terms_match_the_padded_reference(seed):
    sdf, z, valid, depth, has_depth = random_padded_rays(seed)
    R, S = z.shape
    ray = torch.nonzero(valid.reshape(-1)).reshape(-1) // S
    T = 0.05
    ref_w = masked_direct_weights(sdf, z, valid, T)
    ref_fs, ref_sd = sdf_terms(sdf, z, valid & has_depth[:, None], depth, T)
    s = packed(sdf, valid)
    w = packed_direct_weights(s, packed(z, valid), ray, R, T)
    fs, sd = packed_sdf_terms(s, packed(z, valid), ray, depth, has_depth, T)
    assert torch.allclose(w, packed(ref_w, valid), atol=1e-12) and (ref_w[~valid] == 0).all()
    assert torch.allclose(fs, ref_fs, atol=1e-12) and torch.allclose(sd, ref_sd, atol=1e-12)
    # gradients with respect to the SDF of the valid samples
    coef = torch.randn(R, S, generator=torch.Generator().manual_seed(seed + 10), dtype=sdf.dtype)
    g_ref, = torch.autograd.grad((ref_w * coef).sum() + ref_fs + 3 * ref_sd, sdf)
    g, = torch.autograd.grad((w * packed(coef, valid)).sum() + fs + 3 * sd, s)
    assert torch.allclose(g, packed(g_ref, valid), atol=1e-10)


def test_packed_weights_gradcheck():
    sdf, z, valid, _, _ = random_padded_rays(5, R=6, S=8)
    ray = torch.nonzero(valid.reshape(-1)).reshape(-1) // 8
    s = packed(sdf, valid).detach().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: packed_direct_weights(x, packed(z, valid), ray, 6, 0.05), (s,))


def test_a_render_packs_its_samples_and_pads_them_back():
    sdf, z, valid, _, _ = random_padded_rays(7, R=5, S=6, dtype=torch.float32)
    slot = torch.nonzero(valid.reshape(-1)).reshape(-1)
    out = EheRender(rgb=torch.zeros(5, 3), depth=torch.zeros(5), hit=valid.any(1), sdf=packed(sdf, valid),
                    z=packed(z, valid), ray=slot // 6, weights=packed(sdf, valid),
                    start=torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(valid.sum(1), 0)]))
    assert torch.equal(out.padded(out.z), z) and torch.equal(out.padded(out.sdf.detach()), sdf.detach())


def test_a_plane_prior_renders_the_planes_depth():
    class Cfg:
        ehe = EheConfig()
        field = type("F", (), {"kernel": "auto", "decoder_kernel": "torch"})

    model = EheModel(Cfg, UNIT)
    vg, T = model.field.voxels, Cfg.ehe.truncation
    with torch.no_grad():  # residual 0, prior = the signed distance (T-units) to the wall x = 0.537
        for m in (*model.field.sdf_net, *model.field.rgb_net):
            if hasattr(m, "weight"):
                m.weight.zero_()
        vx, vy, vz = vg.vdims
        i = torch.arange(vx * vy * vz) % vx
        vg.priors.table[:, 0] = (0.537 - 0.1 * i.float()) / T
    vg.allocated[:] = True
    o = torch.tensor([[0.02, 0.5, 0.5], [0.02, 0.3, 0.6]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.2, -0.1]])
    out = model.render(o, d, None)
    expected = (0.537 - 0.02) / d[:, 0]
    assert torch.allclose(out.depth, expected, atol=2e-3) and out.hit.all()


def brute_force_hits(vg: VoxelGrid, o: np.ndarray, d: np.ndarray, max_hits: int, t_max: float, dt: float = 1e-4):
    """Reference for `voxel_hits`: march t in dt steps, merge allocated runs, stop after max_hits voxels."""
    t = np.arange(0.0, t_max, dt)
    ijk = np.floor((o + t[:, None] * d - vg.origin.numpy()) / vg.voxel_size).astype(np.int64)
    inside = ((ijk >= 0) & (ijk < np.array(vg.dims))).all(1)
    keys = np.where(inside, vg.key(torch.from_numpy(np.clip(ijk, 0, None))).numpy(), -1)
    alloc = np.where(inside, vg.allocated.numpy()[np.clip(keys, 0, vg.allocated.numel() - 1)], False)
    runs, seen = [], []
    for k in range(len(t)):
        if not alloc[k]:
            continue
        if keys[k] not in seen:
            if len(seen) == max_hits:
                break
            seen.append(keys[k])
        if runs and abs(runs[-1][1] - t[k]) < 1.5 * dt:
            runs[-1][1] = t[k] + dt
        else:
            runs.append([t[k], t[k] + dt])
    return runs


def test_voxel_hits_match_a_brute_force_march_on_random_voxels():
    g = torch.Generator().manual_seed(3)
    vg = VoxelGrid(UNIT, 0.1)
    vg.allocated[:] = torch.rand(vg.allocated.numel(), generator=g) < 0.25
    o = torch.rand(12, 3, generator=g) * 0.8 + 0.1
    d = torch.randn(12, 3, generator=g)
    t_in, t_out, n = voxel_hits(vg, o, d, max_hits=4, t_max=1.5)
    for r in range(12):
        ref = brute_force_hits(vg, o[r].double().numpy(), d[r].double().numpy(), 4, 1.5)
        assert n[r] == len(ref)
        got = np.stack([t_in[r, :n[r]], t_out[r, :n[r]]], 1)
        assert np.allclose(got, np.array(ref).reshape(-1, 2), atol=3e-4)


def test_packed_samples_are_the_padded_samples_valid_ones_with_their_points():
    g = torch.Generator().manual_seed(3)
    vg = VoxelGrid(UNIT, 0.1)
    vg.allocated[:] = torch.rand(vg.allocated.numel(), generator=g) < 0.3
    o = torch.rand(50, 3, generator=g) * 0.8 + 0.1
    d = torch.randn(50, 3, generator=g)
    pad = sample_in_voxels(vg, o, d, 0.01, 10, 1.5, torch.Generator().manual_seed(9))
    pk = packed_samples_in_voxels(vg, o, d, 0.01, 10, 1.5, torch.Generator().manual_seed(9))
    slot = torch.nonzero(pad.valid.reshape(-1)).reshape(-1)
    assert torch.equal(pk.z, pad.z.reshape(-1)[slot]) and torch.equal(pk.ray, slot // pad.z.shape[1])
    assert pk.start.tolist() == [0, *torch.cumsum(pad.valid.sum(1), 0).tolist()]
    assert torch.allclose(pk.points, o[pk.ray] + pk.z[:, None] * d[pk.ray], atol=1e-6)
    assert pk.z.numel() > 100
