"""The fused compositing + losses (`inrslam.rendering.fused_losses`, `loss.kernel`) against its reference,
`composite` + `compute_losses`: values and gradients on fresh random rays, float64 gradcheck, an analytic ray,
thread-count independence, dispatch; and a SLAM model's loss through either path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from inrslam.fields.kernels.threads import thread_scope
from inrslam.rendering import RenderOutput, composite, compute_losses, render_losses
from inrslam.rendering.config import LossConfig
from inrslam.rendering.fused_losses import TERMS, composite_losses

T = 0.1


def random_rays(seed: int, R: int = 64, S: int = 24, dtype=torch.float64):
    """Weights, colours, sorted z, SDF crossing zero near the depth, targets (every 5th ray without depth)."""
    g = torch.Generator().manual_seed(seed)
    D = 0.5 + 2.5 * torch.rand(R, generator=g, dtype=dtype)
    z = torch.sort(D[:, None] + 0.4 * torch.randn(R, S, generator=g, dtype=dtype), dim=1).values
    sdf = (D[:, None] - z) / T + 0.3 * torch.randn(R, S, generator=g, dtype=dtype)
    D[::5] = 0
    w = torch.rand(R, S, generator=g, dtype=dtype) / S
    c = torch.rand(R, S, 3, generator=g, dtype=dtype)
    C = torch.rand(R, 3, generator=g, dtype=dtype)
    return w, c, z, sdf, C, D


def reference(w, c, z, sdf, C, D, cfg, sdf_terms=True, behind=None):
    out = RenderOutput(*composite(w, c, z), w, sdf, z)
    return compute_losses(out, C, D, cfg, T, sdf_terms, behind), out


def fused(w, c, z, sdf, C, D, cfg, sdf_terms=True, behind=None):
    return composite_losses(w, c, z, sdf, C, D, T, cfg.center_band, cfg.free_space_target, cfg.reduction == "per_ray",
                            sdf_terms, cfg.behind if behind is None else behind)


CASES = [("per_ray", 1.0, False), ("global", 1.0, False), ("per_ray", 0.5, False), ("global", 0.3, False),
         ("per_ray", 1.0, True), ("global", 1.0, True)]


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("reduction,behind,per_ray_behind", CASES)
def test_fused_terms_composites_and_gradients_match_the_reference(seed, reduction, behind, per_ray_behind):
    w, c, z, sdf, C, D = random_rays(seed)
    for x in (w, c, sdf):
        x.requires_grad_()
    cfg = LossConfig(reduction=reduction, behind=behind)
    b = 0.2 + torch.rand(w.shape[0], generator=torch.Generator().manual_seed(seed), dtype=w.dtype) if per_ray_behind \
        else None
    ref, out = reference(w, c, z, sdf, C, D, cfg, behind=b)
    got, comp = fused(w, c, z, sdf, C, D, cfg, behind=b)
    assert all(float(ref[k].detach()) > 0 for k in TERMS)  # every term has samples: the comparison is not vacuous
    for k in TERMS:
        assert torch.allclose(got[k], ref[k], rtol=1e-12, atol=1e-15), k
    assert torch.allclose(comp[:, :3], out.rgb) and torch.allclose(comp[:, 3], out.depth)
    assert torch.allclose(comp[:, 4], out.opacity) and torch.allclose(comp[:, 5], out.depth_var)
    assert not comp.requires_grad
    coef = torch.tensor([5.0, 1.0, 10.0, 50.0, 200.0], dtype=w.dtype)  # the paper's weights
    g_ref = torch.autograd.grad(sum(a * ref[k] for a, k in zip(coef, TERMS)), (w, c, sdf))
    g_got = torch.autograd.grad(sum(a * got[k] for a, k in zip(coef, TERMS)), (w, c, sdf))
    for a, b2 in zip(g_got, g_ref):
        assert torch.allclose(a, b2, rtol=1e-10, atol=1e-14)


def test_float32_matches_the_reference_to_rounding():
    w, c, z, sdf, C, D = (x.float() for x in random_rays(5, R=300, S=40))
    for x in (w, c, sdf):
        x.requires_grad_()
    cfg = LossConfig()
    ref, _ = reference(w, c, z, sdf, C, D, cfg)
    got, _ = fused(w, c, z, sdf, C, D, cfg)
    for k in TERMS:
        assert got[k].dtype == torch.float32 and torch.allclose(got[k], ref[k], rtol=1e-5), k
    g_ref = torch.autograd.grad(ref["total"], (w, c, sdf))
    g_got = torch.autograd.grad(sum(a * got[k] for a, k in zip((5.0, 1.0, 10.0, 50.0, 200.0), TERMS)), (w, c, sdf))
    for a, b in zip(g_got, g_ref):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6 * float(b.abs().max()))


def test_gradcheck_float64():
    w, c, z, sdf, C, D = random_rays(3, R=6, S=7)
    w, c, sdf = (x.clone().requires_grad_() for x in (w, c, sdf))
    for reduction in ("per_ray", "global"):
        cfg = LossConfig(reduction=reduction)

        def f(w, c, sdf, cfg=cfg):
            terms, _ = fused(w, c, z, sdf, C, D, cfg)
            return torch.stack([terms[k] for k in TERMS])

        assert torch.autograd.gradcheck(f, (w, c, sdf), eps=1e-6, atol=1e-6)


def test_an_analytic_ray():
    """One ray, two samples: w = (0.25, 0.75), z = (1, 2), colours red / blue, target grey at depth 1.5.
    Ĉ = (0.25, 0, 0.75), D̂ = 1.75, Var = 0.1875; colour MSE = ((0.25-0.5)² + 0.5² + (0.75-0.5)²)/3 = 0.125,
    depth MSE = 0.0625. With T = 0.1 the sample at z = 1 is free space (z < D - T: (s - 1)² = (2 - 1)² = 1) and
    z = 2 is behind the band (unsupervised)."""
    w = torch.tensor([[0.25, 0.75]], dtype=torch.float64)
    c = torch.tensor([[[1.0, 0, 0], [0, 0, 1.0]]], dtype=torch.float64)
    z = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    sdf = torch.tensor([[2.0, -5.0]], dtype=torch.float64)
    C = torch.full((1, 3), 0.5, dtype=torch.float64)
    D = torch.tensor([1.5], dtype=torch.float64)
    terms, comp = fused(w, c, z, sdf, C, D, LossConfig())
    assert np.allclose(comp.numpy(), [[0.25, 0, 0.75, 1.75, 1.0, 0.1875]])
    assert [float(terms[k]) for k in TERMS] == pytest.approx([0.125, 0.0625, 1.0, 0.0, 0.0])


def test_rays_without_depth_or_sdf_terms_give_zeros_not_nan():
    w, c, z, sdf, C, D = random_rays(4, R=8)
    D[:] = 0
    w.requires_grad_()
    sdf.requires_grad_()
    got, _ = fused(w, c, z, sdf, C, D, LossConfig())
    values = {k: float(v.detach()) for k, v in got.items()}
    assert all(values[k] == 0.0 for k in ("depth", "free_space", "center", "tail")) and values["color"] > 0
    gw, gs = torch.autograd.grad(got["color"] + got["tail"], (w, sdf))
    assert torch.isfinite(gw).all() and float(gs.abs().max()) == 0.0
    _, _, _, sdf2, _, D2 = random_rays(4, R=8)
    off, _ = fused(w, c, z, sdf2, C, D2, LossConfig(), sdf_terms=False)
    values = {k: float(v.detach()) for k, v in off.items()}
    assert all(values[k] == 0.0 for k in ("free_space", "center", "tail")) and values["depth"] > 0


def test_results_do_not_depend_on_the_thread_count():
    w, c, z, sdf, C, D = (x.float() for x in random_rays(6, R=500, S=32))
    sdf.requires_grad_()
    outs = []
    for n in (1, 2):
        with thread_scope(n):
            got, _ = fused(w, c, z, sdf, C, D, LossConfig())
            (gs,) = torch.autograd.grad(sum(got[k] for k in TERMS), (sdf,))
        outs.append((torch.stack([got[k] for k in TERMS]).detach(), gs))
    assert torch.equal(outs[0][0], outs[1][0]) and torch.equal(outs[0][1], outs[1][1])


class _Field:
    """A sphere of radius 1 about the origin: SDF in T-units, constant colour logits."""

    def __call__(self, x):
        class Out:
            sdf = (x.norm(dim=-1) - 1.0) / T
            rgb_logits = torch.zeros(x.shape[0], 3, dtype=x.dtype) + x[:, :1]
        return Out()


def test_inputs_the_kernel_does_not_differentiate_are_refused_and_composites_are_private():
    w, c, z, sdf, C, D = random_rays(7, R=10)
    with pytest.raises(ValueError, match="z and the targets must not require grad"):
        fused(w, c, z.clone().requires_grad_(), sdf, C, D, LossConfig())
    with pytest.raises(ValueError, match="0 < center_band <= 1"):
        composite_losses(w, c, z, sdf, C, D, T, 1.5, 1.0, True, True)
    w.requires_grad_()
    ref, _ = reference(w, c, z, sdf, C, D, LossConfig())
    got, comp = fused(w, c, z, sdf, C, D, LossConfig())
    comp.mul_(0)  # a caller editing the composites does not change the gradient
    (g,) = torch.autograd.grad(got["color"] + got["depth"], (w,))
    (g_ref,) = torch.autograd.grad(ref["color"] + ref["depth"], (w,))
    assert torch.allclose(g, g_ref, rtol=1e-10)


@pytest.mark.parametrize("render", ["density", "direct", "nerf", "neus", "volsdf"])
def test_render_losses_by_kernel(render):
    from inrslam.rendering import RenderConfig, build_renderer

    renderer = build_renderer(RenderConfig(name=render))
    g = torch.Generator().manual_seed(0)
    R = 32
    origins = torch.zeros(R, 3, dtype=torch.float64)
    origins[:, 2] = -3.0
    dirs = torch.cat([0.2 * torch.rand(R, 2, generator=g, dtype=torch.float64) - 0.1,
                      torch.ones(R, 1, dtype=torch.float64)], dim=1).requires_grad_()
    z = torch.linspace(1.0, 3.0, 40, dtype=torch.float64).expand(R, 40).contiguous()
    C, D = torch.rand(R, 3, generator=g, dtype=torch.float64), torch.full((R,), 2.0, dtype=torch.float64)
    res = {}
    for kernel in ("torch", "numba", "auto"):
        losses, out = render_losses(_Field(), renderer, origins, dirs, z, C, D, LossConfig(kernel=kernel), T)
        (gd,) = torch.autograd.grad(losses["total"], (dirs,))
        res[kernel] = (losses, out, gd)
    (ref, out_ref, g_ref), (got, out, g_got) = res["torch"], res["numba"]
    assert set(got) == set(ref)
    for k in ref:
        assert torch.allclose(got[k], ref[k], rtol=1e-10, atol=1e-14), k
    assert torch.allclose(out.depth, out_ref.depth) and torch.allclose(out.rgb, out_ref.rgb)
    assert torch.allclose(g_got, g_ref, rtol=1e-9, atol=1e-14) and float(g_ref.abs().max()) > 0
    assert torch.equal(res["auto"][2], g_got)  # auto picks the fused kernel for CPU tensors
    zg = z.clone().requires_grad_()  # a differentiable z: the fused choice runs the reference
    losses, _ = render_losses(_Field(), renderer, origins, dirs, zg, C, D, LossConfig(kernel="numba"), T)
    (gz,) = torch.autograd.grad(losses["total"], (zg,))
    assert float(gz.abs().max()) > 0
    if render == "nerf":  # not SDF-based: the SDF terms are zeros without gradient, as the reference's
        assert not got["tail"].requires_grad and float(got["tail"]) == 0.0


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_numba_needs_cpu_tensors_and_auto_falls_back(device):
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    from inrslam.rendering import RenderConfig, build_renderer

    renderer = build_renderer(RenderConfig(name="density"))
    R = 4
    o = torch.zeros(R, 3, device=device)
    d = torch.tensor([[0.0, 0.0, 1.0]] * R, device=device)
    z = torch.linspace(1.0, 3.0, 8, device=device).expand(R, 8).contiguous()
    C, D = torch.rand(R, 3, device=device), torch.full((R,), 2.0, device=device)
    field = _Field()
    if device == "cpu":  # mixed dtypes cannot be fused
        with pytest.raises(ValueError, match="loss.kernel 'numba' needs CPU float32/float64"):
            render_losses(field, renderer, o, d, z.double(), C, D, LossConfig(kernel="numba"), T)
    else:
        with pytest.raises(ValueError, match="loss.kernel 'numba' needs CPU"):
            render_losses(field, renderer, o, d, z, C, D, LossConfig(kernel="numba"), T)
    auto, _ = render_losses(field, renderer, o, d, z, C, D, LossConfig(kernel="auto"), T)
    ref, _ = render_losses(field, renderer, o, d, z, C, D, LossConfig(kernel="torch"), T)
    assert torch.allclose(auto["total"], ref["total"])
