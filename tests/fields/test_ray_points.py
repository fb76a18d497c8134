"""The fused normalised sample points (`inrslam.fields.kernels.ray_points`) against the reference
((o + z d) − lo) / ext: values bit for bit, gradients to the ray origins and directions, float64 gradcheck, an
analytic ray, thread-count independence; and a field queried through them equals the field queried at world
points."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.fields import FieldConfig, build_field
from inrslam.fields.config import MlpConfig
from inrslam.fields.kernels.ray_points import ray_points_normalised, ray_points_normalised_torch
from inrslam.fields.kernels.threads import thread_scope


def random_rays(seed: int, R: int = 200, S: int = 40, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(R, 3, generator=g, dtype=dtype)
    d = torch.cat([torch.rand(R, 2, generator=g, dtype=dtype) - 0.5, torch.ones(R, 1, dtype=dtype)], dim=1)
    z = torch.sort(0.2 + 4 * torch.rand(R, S, generator=g, dtype=dtype), dim=1).values
    lo = torch.tensor([-3.1, -2.7, -1.3], dtype=dtype)
    ext = torch.tensor([6.4, 5.6, 3.0], dtype=dtype)
    return o, d, z, lo, ext


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1])
def test_points_equal_the_reference_bit_for_bit_and_gradients_to_rounding(dtype, seed):
    o, d, z, lo, ext = random_rays(seed, dtype=dtype)
    o.requires_grad_()
    d.requires_grad_()
    got = ray_points_normalised(o, d, z, lo, ext)
    ref = ray_points_normalised_torch(o, d, z, lo, ext)
    assert got.shape == (z.numel(), 3) and torch.equal(got, ref)  # the same float operations in the same order
    g_out = torch.randn(got.shape, generator=torch.Generator().manual_seed(seed + 5), dtype=dtype)
    g_got = torch.autograd.grad(got, (o, d), g_out)
    g_ref = torch.autograd.grad(ref, (o, d), g_out)
    tol = dict(rtol=1e-4, atol=1e-4) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    for a, b in zip(g_got, g_ref):
        assert a.dtype == dtype
        torch.testing.assert_close(a, b, **tol)


def test_gradcheck_float64_and_an_analytic_ray():
    o, d, z, lo, ext = random_rays(3, R=4, S=5, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a, b: ray_points_normalised(a, b, z, lo, ext),
                                    (o.requires_grad_(), d.requires_grad_()))
    # one ray from (1, 2, 3) along (0, 0, 1): the sample at z = 2 is (1, 2, 5); in the box [0, 10]^3 -> (0.1, 0.2, 0.5);
    # dL/do = Σ_s g / e, dL/dd = Σ_s z g / e
    o = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64, requires_grad=True)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64, requires_grad=True)
    z = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    box = (torch.zeros(3, dtype=torch.float64), torch.full((3,), 10.0, dtype=torch.float64))
    p = ray_points_normalised(o, d, z, *box)
    torch.testing.assert_close(p, torch.tensor([[0.1, 0.2, 0.4], [0.1, 0.2, 0.5]], dtype=torch.float64))
    go, gd = torch.autograd.grad(p, (o, d), torch.ones(2, 3, dtype=torch.float64))
    torch.testing.assert_close(go, torch.full((1, 3), 0.2, dtype=torch.float64))
    torch.testing.assert_close(gd, torch.full((1, 3), 0.3, dtype=torch.float64))


def test_z_with_a_gradient_is_refused_and_results_do_not_depend_on_threads():
    o, d, z, lo, ext = random_rays(4, R=700)
    with pytest.raises(ValueError, match="does not differentiate z"):
        ray_points_normalised(o, d, z.clone().requires_grad_(), lo, ext)
    o.requires_grad_()
    g_out = torch.randn(z.numel(), 3, generator=torch.Generator().manual_seed(1))
    res = []
    for n in (1, 2):
        with thread_scope(n):
            p = ray_points_normalised(o, d.requires_grad_(), z, lo, ext)
            res.append((p, *torch.autograd.grad(p, (o, d), g_out)))
    for a, b in zip(*res):
        assert torch.equal(a, b)


@pytest.mark.parametrize("encoding", ["dense", "hash+tri", "mlp"])
def test_a_field_at_normalised_points_equals_the_field_at_world_points(encoding):
    box = np.array([[-3.1, 3.3], [-2.7, 2.9], [-1.3, 1.7]])
    small = dict(block_coarse=0.5, block_fine=0.25, plane_block_coarse=0.5, mlp=MlpConfig(width=32),
                 log2_hashmap_size=8)
    torch.manual_seed(0)
    field = build_field(FieldConfig(encoding=encoding, **small), box)
    o, d, z, _, _ = random_rays(5, R=16, S=8)
    lo, ext = field.box(torch.float32)
    world = (o[:, None, :] + z[..., None] * d[:, None, :]).reshape(-1, 3)
    a = field(world)
    b = field.decode_normalised(ray_points_normalised(o, d, z, lo, ext))
    assert torch.equal(a.sdf, b.sdf) and torch.equal(a.rgb_logits, b.rgb_logits)
