"""`surface_intervals` / `refine_crossing`: the held-out surface search looks again where uniform samples may have
stepped over a thin object (`eval.heldout_refine`)."""

from __future__ import annotations

import torch
from rendering_helpers import PlaneField, SphereField, T, camera_rays

from inrslam.rendering import first_crossing, refine_crossing, surface_intervals


def _uniform(o: torch.Tensor, step: float, n: int, start: float) -> torch.Tensor:
    return (start + step * torch.arange(n, dtype=torch.float64)).expand(o.shape[0], n)


def _metric(field):
    return lambda p: field(p).sdf * T


def test_intervals_are_the_crossing_and_the_earlier_ones_a_surface_fits_in():
    seg = torch.full((1, 3), 0.1)
    k, valid = surface_intervals(torch.tensor([[0.1, 0.02, 0.03, -0.1]]), seg, 2, margin=1.0)
    assert k.tolist() == [[1, 2]] and valid.tolist() == [[True, True]]  # 0.1 + 0.02 > 0.1: not the first one
    # nothing after the first crossing, however close; padding where fewer intervals qualify
    k, valid = surface_intervals(torch.tensor([[0.5, -0.1, 0.01, 0.01, -0.2]]), torch.full((1, 4), 0.1), 3)
    assert k[0, 0].item() == 0 and valid.tolist() == [[True, False, False]]
    # no surface anywhere near: no interval
    _, valid = surface_intervals(torch.full((2, 6), 0.3), torch.full((2, 5), 0.1), 4)
    assert not valid.any()


def test_a_thin_sphere_between_the_uniform_samples_is_found():
    """A 1 cm sphere 2 m away, uniform samples every 5 cm placed so that none lands inside it on the central rays:
    the uniform search misses it, the refined one finds it within 1 mm of its analytic depth."""
    ball = SphereField([0.0, 0.0, 2.0], 0.01)
    o, d = camera_rays(41, 0.006)  # a pencil of rays over the sphere and around it
    t = ball.true_depth(o, d)
    hit = ~t.isnan()
    z = _uniform(o, 0.05, 80, 0.025)  # samples at 1.975 and 2.025 m: both outside the sphere on the axis
    pts = o[:, None, :] + z[..., None] * d[:, None, :]
    sdf_m = _metric(ball)(pts.reshape(-1, 3)).reshape(z.shape)
    coarse, has = first_crossing(sdf_m, z)
    assert hit.sum() > 100 and not has.any()
    depth, found = refine_crossing(_metric(ball), o, d, z, sdf_m, 8)
    chord = 2 * (ball.r**2 - (d[:, :2] / d.norm(dim=-1, keepdim=True) * 2.0).pow(2).sum(-1)).clamp_min(0).sqrt()
    assert found[chord > 0.012].all()  # a chord over twice the refined spacing (5.6 mm) holds a sample
    assert not found[~hit].any() and (depth[~found] == 0).all()
    assert (depth[found] - t[found]).abs().max().item() < 1e-3


def test_where_the_uniform_samples_already_cross_the_refined_depth_is_the_same_surface():
    """A tilted plane the uniform samples cross: every ray finds it again, on the plane (linear SDF: exact)."""
    plane = PlaneField([0.0, 0.3, 1.0], 2.0)
    o, d = camera_rays(9, 0.4)
    t = plane.true_depth(o, d)
    z = _uniform(o, 0.07, 60, 0.1)
    pts = o[:, None, :] + z[..., None] * d[:, None, :]
    sdf_m = _metric(plane)(pts.reshape(-1, 3)).reshape(z.shape)
    coarse, has = first_crossing(sdf_m, z)
    depth, found = refine_crossing(_metric(plane), o, d, z, sdf_m, 8)
    assert has.all() and found.all()
    torch.testing.assert_close(depth, t, atol=1e-9, rtol=0)
    torch.testing.assert_close(coarse, t, atol=1e-9, rtol=0)


def test_a_thin_object_in_front_of_a_wall_wins_over_the_wall():
    """A 1.2 cm sphere at 1.5 m in front of a wall at 3 m: the uniform samples see only the wall, the refined search
    the sphere first."""
    ball, wall = SphereField([0.0, 0.0, 1.5], 0.012), PlaneField([0.0, 0.0, 1.0], 3.0)
    o, d = camera_rays(1, 0.0)
    both = lambda p: torch.minimum(_metric(ball)(p), _metric(wall)(p))  # noqa: E731
    z = _uniform(o, 0.06, 80, 0.03)  # 1.47 and 1.53 m around the sphere
    pts = o[:, None, :] + z[..., None] * d[:, None, :]
    sdf_m = both(pts.reshape(-1, 3)).reshape(z.shape)
    assert abs(first_crossing(sdf_m, z)[0].item() - 3.0) < 1e-9
    depth, found = refine_crossing(both, o, d, z, sdf_m, 8)
    assert found.item() and abs(depth.item() - 1.488) < 1e-9


def test_only_the_candidate_intervals_are_queried():
    """The field is asked for `n_refine` points per candidate interval and none for padding: rays far from any
    surface cost nothing."""
    plane = PlaneField([0.0, 0.0, 1.0], 2.0)
    o, d = camera_rays(5, 0.2)
    z = _uniform(o, 0.1, 30, 0.05)
    pts = o[:, None, :] + z[..., None] * d[:, None, :]
    sdf_m = _metric(plane)(pts.reshape(-1, 3)).reshape(z.shape)
    seg = (z[:, 1:] - z[:, :-1]) * d.norm(dim=-1, keepdim=True)
    _, valid = surface_intervals(sdf_m, seg, 8)
    queried = []

    def counting(p: torch.Tensor) -> torch.Tensor:
        queried.append(p.shape[0])
        return _metric(plane)(p)

    depth, found = refine_crossing(counting, o, d, z, sdf_m, 6)
    assert 0 < valid.sum().item() < valid.numel() and sum(queried) == 6 * valid.sum().item()
    assert found.all()
    far = torch.full_like(sdf_m, 5.0)  # no surface anywhere: nothing queried, nothing found
    queried.clear()
    _, found = refine_crossing(counting, o, d, z, far, 6)
    assert sum(queried) == 0 and not found.any()
