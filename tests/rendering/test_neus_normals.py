"""NeuS normals: the fused second-order path through a real field vs the PyTorch reference, and the
`ray_difference` slope (`functional.ray_slope`) vs a loop reference, gradcheck and the analytic plane / sphere."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from inrslam.config import load_config
from inrslam.errors import ConfigError
from inrslam.fields import FieldConfig, build_field
from inrslam.fields.config import KernelChoice
from inrslam.fields.encoders import TableEncoder
from inrslam.rendering import RenderConfig, build_renderer, render_rays
from inrslam.rendering.config import NeusConfig, NormalsMethod
from inrslam.rendering.functional import ray_slope

from test_rendering_analytic import CASES, _render_all

BOUNDS = np.array([[-1.0, 1.0], [-1.0, 1.0], [0.0, 2.0]])


def _with_kernel(field, kernel: KernelChoice):
    out = copy.deepcopy(field)
    for m in out.modules():
        if isinstance(m, TableEncoder):
            m.kernel = kernel
    return out


def _neus_grads(field, renderer, origins, dirs, z):
    """Loss gradients of one NeuS render (autograd normals, create_graph) w.r.t. every field parameter and the rays."""
    o = origins.clone().requires_grad_()
    d = dirs.clone().requires_grad_()
    out = render_rays(field, renderer, o, d, z, 0.1)
    (out.depth.square().sum() + out.rgb.sum() + out.normals.square().sum()).backward()
    grads = {n: (p.grad.to_dense() if p.grad.is_sparse else p.grad) for n, p in field.named_parameters()}
    return out.depth.detach(), o.grad, d.grad, grads


@pytest.mark.parametrize("encoding", ["dense", "triplane", "hash+tri"])  # trilinear, planes, both in one field
def test_fused_normals_match_the_reference_through_a_field(encoding):
    torch.manual_seed(0)
    cfg = FieldConfig(encoding=encoding, block_coarse=0.5, block_fine=0.1, log2_hashmap_size=10)
    fused = build_field(cfg, BOUNDS).double()
    with torch.no_grad():  # a random, not flat, field
        for m in fused.modules():
            if isinstance(m, TableEncoder):
                m.table.normal_(0.0, 0.5)
    ref = _with_kernel(fused, KernelChoice.TORCH)
    fused = _with_kernel(fused, KernelChoice.NUMBA)
    renderer = build_renderer(RenderConfig(name="neus")).double()
    origins = torch.rand(16, 3, dtype=torch.float64) * 0.4 - 0.2
    dirs = torch.cat([torch.rand(16, 2, dtype=torch.float64) - 0.5, torch.ones(16, 1, dtype=torch.float64)], -1)
    z = torch.sort(torch.rand(16, 24, dtype=torch.float64) * 1.8 + 0.1, dim=-1).values
    a = _neus_grads(fused, renderer, origins, dirs, z)
    b = _neus_grads(ref, renderer, origins, dirs, z)
    torch.testing.assert_close(a[0], b[0])
    torch.testing.assert_close(a[1], b[1], rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(a[2], b[2], rtol=1e-7, atol=1e-9)
    for name, g in b[3].items():
        torch.testing.assert_close(a[3][name], g, rtol=1e-7, atol=1e-9 * max(g.abs().max().item(), 1.0), msg=name)
    assert b[1].abs().sum() > 0 and all(g.abs().sum() > 0 for g in b[3].values())


def _ray_slope_loop(f, z, ray_norm):
    """Reference: one sample at a time."""
    R, S = f.shape
    out = torch.empty_like(f)
    for r in range(R):
        for i in range(S):
            lo, hi = max(i - 1, 0), min(i + 1, S - 1)
            out[r, i] = (f[r, hi] - f[r, lo]) / ((z[r, hi] - z[r, lo]) * ray_norm[r, 0])
    return out


def test_ray_slope_matches_loop_and_gradcheck():
    torch.manual_seed(1)
    f = torch.randn(4, 7, dtype=torch.float64, requires_grad=True)
    z = torch.sort(torch.rand(4, 7, dtype=torch.float64) * 3, dim=-1).values.requires_grad_()
    n = (torch.rand(4, 1, dtype=torch.float64) + 1.0).requires_grad_()
    torch.testing.assert_close(ray_slope(f, z, n), _ray_slope_loop(f, z, n))
    cot = torch.randn(4, 7, dtype=torch.float64)
    ga = torch.autograd.grad((ray_slope(f, z, n) * cot).sum(), (f, z, n))
    gb = torch.autograd.grad((_ray_slope_loop(f, z, n) * cot).sum(), (f, z, n))
    for a, b in zip(ga, gb):
        torch.testing.assert_close(a, b)
    assert torch.autograd.gradcheck(ray_slope, (f, z, n))


def test_ray_slope_is_exact_on_a_plane():
    """f = h − ⟨n, x⟩ along x = z d: slope = −⟨n, d/|d|⟩ at every sample, jittered spacing or not."""
    normal = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64)
    d = torch.tensor([[0.3, -0.2, 1.0]], dtype=torch.float64)
    z = torch.sort(torch.rand(1, 30, dtype=torch.float64) * 4, dim=-1).values
    f = 2.0 - z * (d @ normal)
    expect = -(d @ normal) / d.norm()
    torch.testing.assert_close(ray_slope(f, z, d.norm(dim=-1, keepdim=True)), expect.expand(1, 30))


def test_ray_difference_neus_renders_plane_and_sphere_depth():
    """NeuS with `ray_difference` on the analytic scenes, paper sampling: as the exact autograd normals (1.83 mm
    max; planes identical, the sphere within 0.12 mm)."""
    rcfg = RenderConfig(name="neus", neus=NeusConfig(normals=NormalsMethod.RAY_DIFFERENCE))
    assert not build_renderer(rcfg).needs_normals
    exact = _render_all(CASES["neus"][0], CASES["neus"][1])
    for (scene, out, t), (_, ref, _) in zip(_render_all(rcfg, CASES["neus"][1]), exact):
        assert out.normals is None
        assert (out.depth - t).abs().max().item() <= 1.9e-3, scene
        assert (out.depth - ref.depth).abs().max().item() <= (2e-4 if scene == "sphere" else 1e-9), scene


def test_normals_config_values():
    cfg = load_config(preset="paper", overrides=["render.name=neus", "render.neus.normals=ray_difference"])
    assert cfg.render.neus.normals is NormalsMethod.RAY_DIFFERENCE
    with pytest.raises(ConfigError, match="ray_difference") as err:
        load_config(preset="paper", overrides=["render.name=neus", "render.neus.normals=bogus"])
    assert "\n" not in str(err.value)
