"""`render.kernel`: the fused weights of G (`inrslam.rendering.weights_kernel`) against their references
(`functional.weights_from_optical_depth(density_optical_depth(...))`, `functional.direct_weights`): values and
gradients on fresh random rays, float64 gradcheck, analytic rays, subnormal gradients, thread-count independence,
and the renderers' dispatch; and the fused sample points inside `render_losses` (the kernel itself:
tests/fields/test_ray_points.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from autograd_graph import node_names

from inrslam.fields import FieldConfig, build_field
from inrslam.fields.kernels import second_order
from inrslam.fields.kernels.threads import thread_scope
from inrslam.rendering import functional as F
from inrslam.rendering import render_losses
from inrslam.rendering.config import LossConfig, RenderConfig
from inrslam.rendering.renderers import build_renderer
from inrslam.rendering.weights_kernel import density_weights_fused, direct_weights_fused

T = 0.1


def random_rays(seed: int, R: int = 64, S: int = 32, dtype=torch.float64, margin: float = 0.0):
    """Sorted z (metres) and an SDF (T-units) crossing zero near each ray's surface, plus noise; every 7th ray has
    no crossing (all outside), every 11th one all inside. With `margin`, |s| >= margin (no sign flips under small
    perturbations)."""
    g = torch.Generator().manual_seed(seed)
    D = 0.5 + 2.5 * torch.rand(R, 1, generator=g, dtype=dtype)
    z = torch.sort(D + 0.3 * torch.randn(R, S, generator=g, dtype=dtype), dim=1).values
    sdf = (D - z) / T + 0.3 * torch.randn(R, S, generator=g, dtype=dtype)
    sdf[::7] = sdf[::7].abs() + 0.05
    sdf[::11] = -sdf[::11].abs() - 0.05
    if margin > 0:
        sdf = torch.where(sdf.abs() < margin, torch.sign(sdf) * margin + (sdf == 0) * margin, sdf)
    return sdf, z


def density_reference(sdf, beta):
    return F.weights_from_optical_depth(F.density_optical_depth(sdf, beta))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_density_weights_and_gradients_equal_the_reference(seed):
    sdf, _ = random_rays(seed)
    beta = torch.tensor(4.0 + 8.0 * torch.rand(1, generator=torch.Generator().manual_seed(seed)).item(),
                        dtype=torch.float64, requires_grad=True)
    sdf.requires_grad_()
    ref = density_reference(sdf, beta)
    got = density_weights_fused(sdf, beta)
    assert got.grad_fn is not None and type(got.grad_fn).__name__ == "DensityWeightsFnBackward"
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-15)
    g_out = torch.randn(ref.shape, generator=torch.Generator().manual_seed(seed + 10), dtype=ref.dtype)
    g_ref = torch.autograd.grad(ref, (sdf, beta), g_out)
    g_got = torch.autograd.grad(got, (sdf, beta), g_out)
    for a, b in zip(g_got, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-13)
    assert float(g_ref[0].abs().max()) > 1e-3 and abs(float(g_ref[1])) > 1e-6  # not vacuous


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("keeps_all", [True, False])
def test_direct_weights_and_gradients_equal_the_reference(seed, keeps_all):
    sdf, z = random_rays(seed)
    sdf.requires_grad_()
    ref = F.direct_weights(sdf, z, T, no_crossing_keeps_all=keeps_all)
    got = direct_weights_fused(sdf, z, T, no_crossing_keeps_all=keeps_all)
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-15)
    masked = (ref == 0).any(dim=1)
    assert masked[1:7].all()  # rays cut at T behind their first surface; rays without a crossing kept whole or not:
    assert bool(masked[::7].any()) != keeps_all
    g_out = torch.randn(ref.shape, generator=torch.Generator().manual_seed(seed + 10), dtype=ref.dtype)
    (g_ref,) = torch.autograd.grad(ref, (sdf,), g_out)
    (g_got,) = torch.autograd.grad(got, (sdf,), g_out)
    torch.testing.assert_close(g_got, g_ref, rtol=1e-10, atol=1e-13)
    assert float(g_ref.abs().max()) > 1e-3


@pytest.mark.parametrize("kind", ["density", "direct"])
def test_float32_equals_the_reference_to_rounding(kind):
    sdf, z = (x.float() for x in random_rays(3, R=300, S=60))
    sdf.requires_grad_()
    beta = torch.tensor(10.0, requires_grad=True)
    if kind == "density":
        ref, got = density_reference(sdf, beta), density_weights_fused(sdf, beta)
        inputs = (sdf, beta)
    else:
        ref, got = F.direct_weights(sdf, z, T), direct_weights_fused(sdf, z, T)
        inputs = (sdf,)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-6)
    g_out = torch.rand(ref.shape, generator=torch.Generator().manual_seed(4))
    for a, b in zip(torch.autograd.grad(got, inputs, g_out), torch.autograd.grad(ref, inputs, g_out)):
        assert a.dtype == b.dtype
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()))


def test_gradcheck_float64():
    sdf, z = random_rays(5, R=6, S=10, margin=0.02)  # signs and masks stay put under gradcheck's steps
    sdf.requires_grad_()
    beta = torch.tensor(7.0, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s, b: density_weights_fused(s, b), (sdf, beta))
    assert torch.autograd.gradcheck(lambda s: direct_weights_fused(s, z, T), (sdf,))
    assert torch.autograd.gradcheck(lambda s: direct_weights_fused(s, z, T, no_crossing_keeps_all=False), (sdf,))


def test_analytic_rays():
    """Density: one sample on the surface has τ = β/2, w = 1 - e^{-β/2}; the second sample sees the transmittance
    e^{-β/2}. Direct: samples at ±s around a crossing get equal bells, normalised to 1/2 each, and a sample more than
    T behind the crossing gets none."""
    beta = 10.0
    sdf = torch.tensor([[0.0, -1.0]], dtype=torch.float64)
    w = density_weights_fused(sdf, beta)
    tau2 = beta / (1 + math.exp(-beta))  # β σ(β)
    assert abs(float(w[0, 0]) - (1 - math.exp(-5.0))) < 1e-15
    assert abs(float(w[0, 1]) - (1 - math.exp(-tau2)) * math.exp(-5.0)) < 1e-15
    sdf = torch.tensor([[0.3, -0.3, -5.0]], dtype=torch.float64)
    z = torch.tensor([[1.0, 1.06, 1.3]], dtype=torch.float64)  # crossing at sample 0: kept up to z = 1.1
    w = direct_weights_fused(sdf, z, T)
    torch.testing.assert_close(w, torch.tensor([[0.5, 0.5, 0.0]], dtype=torch.float64), rtol=0, atol=1e-7)
    # the bell's slope: d/ds [σ(s/T)σ(-s/T)] = σσ'(σ' - σ)/T, here with ∂L/∂w = (1, 0, 0)
    s = sdf.clone().requires_grad_()
    (g,) = torch.autograd.grad(direct_weights_fused(s, z, T)[0, 0], (s,))
    sp, sm = 1 / (1 + math.exp(-3.0)), 1 / (1 + math.exp(3.0))
    bell, dbell = sp * sm, sp * sm * (sm - sp) / T
    assert abs(float(g[0, 0]) - dbell * (1 - 0.5) / (2 * bell + 1e-8)) < 1e-6
    assert float(g[0, 2]) == 0.0  # outside the mask


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_subnormal_sdf_gradients_are_written_as_zero(dtype):
    """Deep inside, the transmittance falls below the smallest normal number: the reference's gradients there are
    subnormal or zero; the kernel's are exactly zero there and equal elsewhere."""
    tiny = torch.finfo(dtype).tiny
    S = 80 if dtype == torch.float32 else 800
    sdf = torch.linspace(1.0, -3.0, S, dtype=dtype)[None].repeat(3, 1).requires_grad_()
    beta = torch.tensor(10.0, dtype=dtype)
    g_out = torch.randn(3, S, generator=torch.Generator().manual_seed(0), dtype=dtype)
    (g_ref,) = torch.autograd.grad(density_reference(sdf, beta), (sdf,), g_out)
    (g_got,) = torch.autograd.grad(density_weights_fused(sdf, beta), (sdf,), g_out)
    sub = (g_ref != 0) & (g_ref.abs() < tiny)
    assert sub.any()  # the case arises
    assert (g_got[sub] == 0).all()
    normal = g_ref.abs() >= 100 * tiny
    scale = float(g_ref.abs().max())  # deep samples' gradients cancel: their rounding is relative to the largest
    torch.testing.assert_close(g_got[normal], g_ref[normal], rtol=1e-4 if dtype == torch.float32 else 1e-10,
                               atol=(1e-6 if dtype == torch.float32 else 1e-14) * scale)


def test_results_do_not_depend_on_the_thread_count():
    sdf, z = (x.float() for x in random_rays(6, R=500, S=40))
    sdf.requires_grad_()
    beta = torch.tensor(10.0, requires_grad=True)
    g_out = torch.randn(sdf.shape, generator=torch.Generator().manual_seed(2))
    res = []
    for n in (1, 2):
        with thread_scope(n):
            wd = density_weights_fused(sdf, beta)
            wi = direct_weights_fused(sdf, z, T)
            res.append((wd, wi, *torch.autograd.grad(wd, (sdf, beta), g_out), *torch.autograd.grad(wi, (sdf,), g_out)))
    for a, b in zip(*res):
        assert torch.equal(a, b)


@pytest.mark.parametrize("name", ["density", "direct"])
@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_renderers_dispatch_by_render_kernel(name, device):
    """torch: the reference; numba / auto: the fused weights on CPU floats, equal to the reference; auto falls back
    on other devices and inside second-order scopes; numba where it cannot run is one clear error."""
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    sdf, z = (x.float().to(device) for x in random_rays(7, R=16, S=12))
    dirs = torch.tensor([[0.0, 0.0, 1.0]], device=device).expand(16, 3)
    out = {}
    for kernel in ("torch", "numba", "auto"):
        renderer = build_renderer(RenderConfig(name=name, kernel=kernel)).to(device)
        s = sdf.clone().requires_grad_()
        if kernel == "numba" and device != "cpu":
            with pytest.raises(ValueError, match="render.kernel 'numba' needs CPU float32/float64"):
                renderer(s, z, dirs, None, T)
            continue
        w = renderer(s, z, dirs, None, T)
        out[kernel] = (w, type(w.grad_fn).__name__)
        with second_order():  # a second-order backward may follow: the reference
            assert type(renderer(s, z, dirs, None, T).grad_fn).__name__ == out["torch"][1]
    fused_name = "DensityWeightsFnBackward" if name == "density" else "DirectWeightsFnBackward"
    assert out["torch"][1] != fused_name
    assert out["auto"][1] == (fused_name if device == "cpu" else out["torch"][1])
    if device == "cpu":
        assert out["numba"][1] == fused_name
        torch.testing.assert_close(out["numba"][0], out["torch"][0], rtol=1e-5, atol=1e-6)
        renderer = build_renderer(RenderConfig(name=name, kernel="numba"))
        with pytest.raises(ValueError, match="render.kernel 'numba' needs CPU float32/float64"):
            renderer(sdf.double(), z.float(), dirs, None, T)  # mixed dtypes


@pytest.mark.parametrize("name", ["density", "direct", "volsdf", "neus"])
def test_render_kernel_also_fuses_the_sample_points(name):
    """With `render.kernel` numba, the sample points reach the field normalised by one fused pass
    (`kernels.ray_points`), except for a G that needs normals, a field without `decode_normalised` or a z that needs
    a gradient; losses and the gradients to the rays' origins and directions equal the reference's to rounding."""
    torch.manual_seed(0)
    field = build_field(FieldConfig(encoding="dense", block_coarse=0.5, block_fine=0.25),
                        np.array([[-2.0, 2.0], [-2.0, 2.0], [0.0, 4.0]]))
    g = torch.Generator().manual_seed(3)
    R, S = 32, 16
    origins = (0.1 * torch.randn(R, 3, generator=g)).requires_grad_()
    dirs = torch.cat([0.4 * torch.rand(R, 2, generator=g) - 0.2, torch.ones(R, 1)], dim=1).requires_grad_()
    z = torch.sort(0.5 + 3 * torch.rand(R, S, generator=g), dim=1).values
    C, D = torch.rand(R, 3, generator=g), 1 + 2 * torch.rand(R, generator=g)
    res = {}
    for kernel in ("torch", "numba"):
        renderer = build_renderer(RenderConfig(name=name, kernel=kernel))
        losses, _ = render_losses(field, renderer, origins, dirs, z, C, D, LossConfig(), 0.1)
        res[kernel] = (losses["total"], *torch.autograd.grad(losses["total"], (origins, dirs), retain_graph=True))
        res[kernel + "_names"] = node_names(losses["total"].grad_fn)
    assert ("RayPointsFnBackward" in res["numba_names"]) == (name != "neus")
    assert "RayPointsFnBackward" not in res["torch_names"]
    for a, b in zip(res["numba"], res["torch"]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    assert float(res["torch"][1].abs().max()) > 0  # the pose gradients are not vacuous
    renderer = build_renderer(RenderConfig(name=name, kernel="numba"))
    plain, _ = render_losses(lambda x: field(x), renderer, origins, dirs, z, C, D, LossConfig(), 0.1)
    assert "RayPointsFnBackward" not in node_names(plain["total"].grad_fn)  # a callable without decode_normalised
    zg, _ = render_losses(field, renderer, origins, dirs, z.clone().requires_grad_(), C, D, LossConfig(), 0.1)
    assert "RayPointsFnBackward" not in node_names(zg["total"].grad_fn)
