"""Ray sampling (spec §5.1) and pixel sampling (spec §5.2)."""

from __future__ import annotations

import pytest
import torch

from inrslam.rendering import SamplingConfig, SamplingVariant, aabb_exit, sample_depths, sample_pixels
from inrslam.rendering.sampling import stratified_jitter

T = 0.1
BOUNDS = torch.tensor([[-2.0, 2.0], [-1.0, 1.0], [-1.0, 4.0]], dtype=torch.float64)


def _rays(depths):
    depth = torch.tensor(depths, dtype=torch.float64)
    n = depth.shape[0]
    dirs = torch.tensor([[0.1, -0.2, 1.0]], dtype=torch.float64).expand(n, 3)
    origins = torch.tensor([[0.5, 0.0, 0.0]], dtype=torch.float64).expand(n, 3)
    return depth, dirs, origins


def _expected_depth_ray(d, n_free=48, n_surf=12, band=1.0, far=1.2):
    free = torch.linspace(0, far * d, n_free, dtype=torch.float64)
    surf = d + torch.linspace(-band * T, band * T, n_surf, dtype=torch.float64)
    return torch.sort(torch.cat([free, surf])).values


def test_depth_rays_exact_positions_without_jitter():
    depth, dirs, origins = _rays([2.0, 1.3])
    z = sample_depths(depth, dirs, origins, BOUNDS, SamplingConfig(jitter=False), T)
    assert z.shape == (2, 60)
    for r, d in enumerate([2.0, 1.3]):
        torch.testing.assert_close(z[r], _expected_depth_ray(d))
    # 12 band samples exactly on d +- T (d - T and d + T inclusive), 48 free samples end at 1.2 d
    band = ((z[0] >= 2.0 - T - 1e-12) & (z[0] <= 2.0 + T + 1e-12)).sum().item()
    free_in_band = ((torch.linspace(0, 2.4, 48) >= 1.9) & (torch.linspace(0, 2.4, 48) <= 2.1)).sum().item()
    assert band == 12 + free_in_band
    assert z[0, 0] == 0 and z[0, -1] == pytest.approx(2.4)


def test_faithful_band_and_sampling_variant():
    depth, dirs, origins = _rays([2.0])
    z = sample_depths(depth, dirs, origins, BOUNDS, SamplingConfig(jitter=False, band=1.5), T)
    torch.testing.assert_close(z[0], _expected_depth_ray(2.0, band=1.5))
    cfg = SamplingConfig(jitter=False, variant=SamplingVariant.SAMPLING)
    z = sample_depths(depth, dirs, origins, BOUNDS, cfg, T)
    torch.testing.assert_close(z[0], torch.linspace(0, 2.4, 60, dtype=torch.float64))


def test_band_clamped_at_near_for_shallow_depth():
    depth, dirs, origins = _rays([0.05])
    z = sample_depths(depth, dirs, origins, BOUNDS, SamplingConfig(jitter=False), T)
    assert (z >= 0).all() and (z[:, 1:] >= z[:, :-1]).all()


def test_jitter_stays_in_strata_sorted_and_is_fresh():
    depth, dirs, origins = _rays([2.0, 0.0, 3.1])
    base = sample_depths(depth, dirs, origins, BOUNDS, SamplingConfig(jitter=False), T)
    mid = 0.5 * (base[:, 1:] + base[:, :-1])
    lower = torch.cat([base[:, :1], mid], 1)
    upper = torch.cat([mid, base[:, -1:]], 1)
    g = torch.Generator().manual_seed(0)
    z1 = sample_depths(depth, dirs, origins, BOUNDS, SamplingConfig(), T, g)
    z2 = sample_depths(depth, dirs, origins, BOUNDS, SamplingConfig(), T, g)
    for z in (z1, z2):
        assert ((z >= lower) & (z <= upper)).all()
        assert (z[:, 1:] >= z[:, :-1]).all()
    assert not torch.equal(z1, z2)  # fresh every call
    z3 = sample_depths(depth, dirs, origins, BOUNDS, SamplingConfig(), T, torch.Generator().manual_seed(0))
    assert torch.equal(z1, z3)  # reproducible from the generator
    # band samples: each of the 12 strata around d keeps at least one sample within d +- (T + half a gap)
    gap = (base[0, 1:] - base[0, :-1]).max()
    assert ((z1[0] > 2.0 - T - gap / 2) & (z1[0] < 2.0 + T + gap / 2)).sum() >= 12


def test_stratified_jitter_uniform_in_stratum():
    z = torch.tensor([[0.0, 1.0, 3.0]]).expand(20000, 3)
    j = stratified_jitter(z, torch.Generator().manual_seed(0))
    # strata [0, .5], [.5, 2], [2, 3] -> means .25, 1.25, 2.5
    torch.testing.assert_close(j.mean(0), torch.tensor([0.25, 1.25, 2.5]), atol=0.02, rtol=0)


def test_aabb_exit_slab():
    o = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.5, 0.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [-0.5, 0.25, 1.0]], dtype=torch.float64)
    t = aabb_exit(o, d, BOUNDS)
    # ray 0 leaves through z = 4; ray 1 through x = 2 (t = 2); ray 2: x: (-2-1)/-0.5 = 6, y: (1-.5)/.25 = 2, z: 4
    torch.testing.assert_close(t, torch.tensor([4.0, 2.0, 2.0], dtype=torch.float64))


def test_rays_without_depth_uniform_to_box_exit():
    depth, dirs, origins = _rays([0.0, 2.0])
    z = sample_depths(depth, dirs, origins, BOUNDS, SamplingConfig(jitter=False), T)
    assert z.shape == (2, 60)  # mixed batch: the depth layout's S for every ray
    t_far = aabb_exit(origins[:1], dirs[:1], BOUNDS)[0] + 0.01
    torch.testing.assert_close(z[0], torch.linspace(0, float(t_far), 60, dtype=torch.float64))
    # a batch without any depth uses n_uniform samples
    depth, dirs, origins = _rays([0.0, 0.0])
    z = sample_depths(depth, dirs, origins, BOUNDS, SamplingConfig(jitter=False, n_uniform=17), T)
    assert z.shape == (2, 17)
    assert z[0, -1] == pytest.approx(float(t_far)) and z[0, 0] == 0
    zj = sample_depths(depth, dirs, origins, BOUNDS, SamplingConfig(n_uniform=17), T)
    assert (zj >= 0).all() and (zj <= float(t_far) + 1e-12).all()


def test_sample_depths_no_grad_and_dtype():
    depth, dirs, origins = _rays([2.0])
    dirs = dirs.clone().requires_grad_(True)
    z = sample_depths(depth.float(), dirs, origins, BOUNDS, SamplingConfig(), T)
    assert not z.requires_grad and z.dtype == torch.float32


def test_sample_pixels_margins_distinct_and_complete():
    g = torch.Generator().manual_seed(0)
    u, v = sample_pixels(48, 64, 500, 5, g)
    assert u.dtype == torch.int64 and u.shape == (500,)
    assert (u >= 5).all() and (u < 59).all() and (v >= 5).all() and (v < 43).all()
    assert len(set(zip(u.tolist(), v.tolist()))) == 500
    u, v = sample_pixels(6, 8, 48, 0, g)  # all pixels
    assert set(zip(u.tolist(), v.tolist())) == {(a, b) for a in range(8) for b in range(6)}
    with pytest.raises(ValueError):
        sample_pixels(10, 10, 37, 2, g)  # only 36 pixels inside the margin
    with pytest.raises(ValueError):
        sample_pixels(10, 10, 1, 5, g)


def _strict_generator_device(monkeypatch) -> None:
    """Make torch.rand / torch.randperm enforce CUDA's rule on every device: a generator draws only on its own device
    (on a CPU-only machine this reproduces the `generator=cpu_gen, device=cuda` error with the meta device)."""
    for name in ("rand", "randperm"):
        orig = getattr(torch, name)

        def strict(*args, generator=None, device=None, _orig=orig, **kw):
            if generator is not None and device is not None and torch.device(device) != generator.device:
                raise RuntimeError(f"Expected a '{torch.device(device).type}' device type for generator but found "
                                   f"'{generator.device.type}'")
            return _orig(*args, generator=generator, device=device, **kw)

        monkeypatch.setattr(torch, name, strict)


def test_cpu_generator_with_tensors_on_another_device(monkeypatch):
    _strict_generator_device(monkeypatch)
    z = torch.linspace(0.0, 1.0, 8).expand(4, 8).to("meta")
    j = stratified_jitter(z, torch.Generator().manual_seed(0))
    assert j.device.type == "meta" and j.shape == (4, 8) and j.dtype == z.dtype
    u, v = sample_pixels(16, 16, 10, 1, torch.Generator().manual_seed(0), device="meta")
    assert u.device.type == "meta" and v.shape == (10,)


def test_sample_depths_with_cpu_generator_on_every_device(device):
    depth, dirs, origins = _rays([2.0, 0.0, 3.1])
    cfg = SamplingConfig()
    ref = sample_depths(depth, dirs, origins, BOUNDS, cfg, T, torch.Generator().manual_seed(3))
    z = sample_depths(depth.to(device), dirs.to(device), origins.to(device), BOUNDS, cfg, T,
                      torch.Generator().manual_seed(3))
    assert z.device.type == device.type and z.dtype == torch.float64
    torch.testing.assert_close(z.cpu(), ref)  # same draws whatever the tensors' device
    u, v = sample_pixels(20, 30, 50, 2, torch.Generator().manual_seed(1), device=device)
    assert u.device.type == device.type and v.device.type == device.type


def test_cpu_jitter_draws_unchanged():
    """On CPU the jitter is exactly lower + U(0,1)·(upper - lower) with the generator's next draws in z's dtype."""
    for dtype in (torch.float32, torch.float64):
        z = torch.tensor([[0.0, 1.0, 3.0, 3.5], [0.5, 0.7, 0.9, 2.0]], dtype=dtype)
        u = torch.rand(z.shape, generator=torch.Generator().manual_seed(7), dtype=dtype)
        mid = 0.5 * (z[:, 1:] + z[:, :-1])
        lower, upper = torch.cat([z[:, :1], mid], 1), torch.cat([mid, z[:, -1:]], 1)
        j = stratified_jitter(z, torch.Generator().manual_seed(7))
        assert torch.equal(j, lower + u * (upper - lower))


def test_distinct_indices_are_distinct_in_range_and_uniform():
    from inrslam.rendering.sampling import distinct_indices

    g = torch.Generator().manual_seed(0)
    hits = torch.zeros(1000)
    for _ in range(400):
        idx = distinct_indices(1000, 100, g)  # the draw-and-deduplicate branch (100 <= 1000 / 4)
        assert idx.numel() == 100 and idx.unique().numel() == 100 and idx.min() >= 0 and idx.max() < 1000
        hits[idx] += 1
    # each index drawn with probability 0.1: 40 expected in 400 draws, std 6; every one within 6 std
    assert (hits - 40).abs().max() < 36 and abs(hits.mean().item() - 40) < 1e-9
    assert distinct_indices(10, 10, g).sort().values.tolist() == list(range(10))
