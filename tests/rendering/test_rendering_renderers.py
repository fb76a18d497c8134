"""Rendering functions G, compositing and render_rays: equations, gradients, normals, registry."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from inrslam.errors import ConfigError
from inrslam.rendering import (
    RENDERERS,
    DensityConfig,
    LossConfig,
    NeusConfig,
    NormalsMethod,
    RenderConfig,
    SamplingConfig,
    SdfToWeights,
    VolSdfConfig,
    build_renderer,
    composite,
    compute_losses,
    render_rays,
    renderer_param_groups,
    sample_depths,
)
from inrslam.rendering import functional as F

from rendering_helpers import T, Out, PlaneField, rotation_x


class CountingField:
    def __init__(self, f):
        self.f, self.calls = f, 0

    def __call__(self, x):
        self.calls += 1
        return self.f(x)


class TinyMLPField(nn.Module):
    """Random smooth field (N,3) -> (sdf, rgb logits) for registry-wide and gradient tests."""

    def __init__(self, seed=0, dtype=torch.float64):
        super().__init__()
        torch.manual_seed(seed)
        self.net = nn.Sequential(nn.Linear(3, 16), nn.Softplus(), nn.Linear(16, 4)).to(dtype)

    def forward(self, x):
        h = self.net(x)
        return Out(h[:, 0] + 2.0 - x[:, 2], h[:, 1:])


# -- registry -------------------------------------------------------------------------------------------------


def test_registry_and_build():
    assert set(RENDERERS.names()) == {"direct", "density", "neus", "volsdf", "nerf"}
    for name in RENDERERS.names():
        r = build_renderer(RenderConfig(name=name))
        assert isinstance(r, nn.Module)
        assert r.needs_normals == (name == "neus")
    with pytest.raises(ConfigError, match="did you mean 'density'"):
        build_renderer(RenderConfig(name="densty"))
    with pytest.raises(ConfigError, match="volsdf.beta_init"):
        build_renderer(RenderConfig(name="volsdf", volsdf=VolSdfConfig(beta_init=1e-5)))


def test_learnable_parameters():
    assert renderer_param_groups(build_renderer(RenderConfig(name="density")), RenderConfig()) == []
    cfg = RenderConfig(name="density", density=DensityConfig(learn_beta=True), beta_lr=0.1)
    r = build_renderer(cfg)
    (group,) = renderer_param_groups(r, cfg)
    assert group["lr"] == 0.1 and group["params"][0] is r.beta and r.beta.item() == 10.0
    r = build_renderer(RenderConfig(name="neus"))
    assert r.log_inv_s.requires_grad and r.inv_s.item() == pytest.approx(math.exp(5.0), rel=1e-6)
    assert not build_renderer(RenderConfig(name="neus", neus=NeusConfig(learn_s=False))).log_inv_s.requires_grad
    r = build_renderer(RenderConfig(name="volsdf", volsdf=VolSdfConfig(beta_init=0.02)))
    assert r.log_beta.requires_grad and r.beta.item() == pytest.approx(0.02, rel=1e-6)


# -- functional -----------------------------------------------------------------------------------------------


def test_functional_docstring_examples():
    s, e = F.section_bounds(torch.tensor([[0.0, 1.0, 3.0]]))
    assert s.tolist() == [[0.0, 0.5, 2.0]] and e.tolist() == [[0.5, 2.0, 3.0]]
    w = F.weights_from_alpha(torch.tensor([[0.5, 0.5, 1.0]]), eps=0.0)
    torch.testing.assert_close(w, torch.tensor([[0.5, 0.25, 0.25]]))
    tau = F.density_optical_depth(torch.tensor([0.0]), 10.0)
    assert 1 - math.exp(-tau.item()) == pytest.approx(0.9933, abs=1e-4)
    assert F.bell_weights(torch.tensor([0.0]), 0.1).item() == 0.25
    # bell half maximum at |d| ~ 1.76 T^2 metres (s = d / T)
    assert F.bell_weights(torch.tensor([1.7627 * 0.1]), 0.1).item() == pytest.approx(0.125, rel=1e-3)
    rgb, depth, op, var = composite(torch.tensor([[0.25, 0.75]]), torch.ones(1, 2, 3), torch.tensor([[1.0, 2.0]]))
    assert depth.item() == 1.75 and op.item() == 1.0 and var.item() == pytest.approx(0.1875)
    torch.testing.assert_close(rgb, torch.ones(1, 3))


def test_optical_depth_matches_alpha_form():
    tau = torch.rand(4, 9, dtype=torch.float64) * 3
    torch.testing.assert_close(F.weights_from_optical_depth(tau), F.weights_from_alpha(1 - torch.exp(-tau), eps=0))


def test_volsdf_density_is_laplace_cdf():
    beta = 0.01
    d = torch.tensor([-0.05, -0.01, 0.0, 0.01, 0.05], dtype=torch.float64)
    expected = torch.where(d >= 0, 0.5 * torch.exp(-d / beta), 1 - 0.5 * torch.exp(d / beta)) / beta
    torch.testing.assert_close(F.volsdf_density(d, beta), expected)
    x = torch.tensor([0.0], dtype=torch.float64, requires_grad=True)
    F.volsdf_density(x, beta).backward()
    assert x.grad.item() == pytest.approx(-0.5 / beta**2)  # C1 at the surface, not 0 from abs()


def test_neus_alpha_of_linear_section_is_exact():
    """For a linear SDF, alpha = 1 - exp(-∫ rho) with NeuS' rho = max(-dΦ/dt / Φ, 0) (NeuS Eq. 12-13)."""
    s = 50.0
    f_prev, f_next = torch.tensor([0.03]), torch.tensor([-0.01])
    a = F.neus_alpha(f_prev, f_next, s)
    phi = lambda x: 1 / (1 + math.exp(-s * x))  # noqa: E731
    assert a.item() == pytest.approx(1 - phi(-0.01) / phi(0.03), rel=1e-3)


def test_direct_weights_sum_below_one_far_from_the_surface():
    # equal s on every sample (no crossing keeps all): Σ w = S b / (S b + 1e-8), b = σ(s/T) σ(-s/T)
    S = 60
    z = torch.linspace(0.1, 3.0, S, dtype=torch.float64)[None]
    for s in (0.0, 1.0, 2.0, 3.0):
        w = F.direct_weights(torch.full((1, S), s, dtype=torch.float64), z, T)
        b = 1 / (1 + math.exp(-s / T)) / (1 + math.exp(s / T))
        assert w.sum().item() == pytest.approx(S * b / (S * b + 1e-8), rel=1e-9)
    assert w.sum().item() < 1e-3  # s = 3: the 1e-8 dominates, as the docstring says


def test_direct_first_surface_and_no_crossing():
    z = torch.linspace(0.5, 3.0, 26)[None]  # spacing 0.1
    # two surfaces: crossing between z = 1.0 and 1.1, then again at 2.0..2.1; inside in between
    sdf = torch.where(z < 1.05, 1.0, torch.where(z < 2.05, -1.0, 1.0)) * 0.3
    sdf = torch.cat([sdf, torch.full_like(sdf, 0.5)])  # ray 1: no crossing
    zz = z.expand(2, -1)
    w = F.direct_weights(sdf, zz, T)
    assert torch.allclose(w.sum(-1), torch.ones(2))
    z_k = 1.0
    assert (w[0][z[0] >= z_k + T - 1e-6] == 0).all() and (w[0][z[0] < z_k + T - 1e-6] > 0).all()
    assert (w[1] > 0).all()  # fixed: no crossing keeps every sample, equal bell values -> uniform weights
    torch.testing.assert_close(w[1], torch.full((26,), 1 / 26))
    wf = build_renderer(RenderConfig(name="direct", faithful=True))(sdf, zz, None, None, T)
    assert (wf[1][z[0] < z[0, 0] + T - 1e-6] > 0).all() and (wf[1][z[0] >= z[0, 0] + T - 1e-6] == 0).all()
    # a sample exactly at 0 after a positive one closes the crossing
    m = F.first_surface_mask(torch.tensor([[0.5, 0.0, -0.5, -0.5, -0.5]]), torch.tensor([[0.0, 0.1, 0.2, 0.3, 0.4]]),
                             0.15)
    assert m.tolist() == [[True, True, False, False, False]]


@pytest.mark.parametrize("name", sorted(RENDERERS.names()))
def test_gradcheck_float64(name):
    torch.manual_seed(0)
    r = build_renderer(RenderConfig(name=name)).double()
    R, S = 3, 8
    z = torch.sort(torch.rand(R, S, dtype=torch.float64) * 0.4 + 1.8, dim=-1).values
    sdf = (2.0 - z) / T + torch.rand(R, S, dtype=torch.float64) * 0.05 + 0.02  # no sample near 0 (direct's mask)
    sdf.requires_grad_(True)
    dirs = torch.tensor([[0.1, 0.2, 1.0]], dtype=torch.float64).expand(R, 3)
    normals = (torch.tensor([0.0, 0.0, -1.0 / T], dtype=torch.float64) + 0.1 * torch.randn(R, S, 3,
                                                                                          dtype=torch.float64))
    normals.requires_grad_(name == "neus")
    inputs = (sdf, normals) if name == "neus" else (sdf,)

    def fn(*args):
        n = args[1] if name == "neus" else normals
        return r(args[0], z, dirs, n, T)

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5)


# -- render_rays ------------------------------------------------------------------------------------------------


def _plane_rays():
    f = PlaneField(rotation_x(25.0) @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 2.0)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.2, -0.1, 1.0], [-0.3, 0.2, 1.0]], dtype=torch.float64)
    o = torch.zeros(3, 3, dtype=torch.float64)
    t = f.true_depth(o, d)
    bounds = torch.tensor([[-3.0, 3.0], [-3.0, 3.0], [-1.0, 5.0]], dtype=torch.float64)
    z = sample_depths(t, d, o, bounds, SamplingConfig(jitter=False), T)
    return f, o, d, z


def test_field_queried_once_without_normals():
    f, o, d, z = _plane_rays()
    cf = CountingField(f)
    out = render_rays(cf, build_renderer(RenderConfig(name="density")).double(), o, d, z, T)
    assert cf.calls == 1 and out.normals is None
    assert out.sdf.shape == z.shape and out.weights.shape == z.shape and out.rgb.shape == (3, 3)


#: the methods that compute normals (ray_difference takes the slope from the samples: test_neus_normals.py)
WITH_NORMALS = [m for m in NormalsMethod if m is not NormalsMethod.RAY_DIFFERENCE]


@pytest.mark.parametrize("method", WITH_NORMALS)
def test_neus_normals_match_the_analytic_gradient(method):
    f, o, d, z = _plane_rays()
    r = build_renderer(RenderConfig(name="neus", neus=NeusConfig(normals=method))).double()
    out = render_rays(f, r, o, d, z, T)
    expected = (-f.n / T).expand_as(out.normals)  # s = (h - n.x) / T
    torch.testing.assert_close(out.normals, expected, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("method", WITH_NORMALS)
def test_render_rays_inside_no_grad(method):
    f, o, d, z = _plane_rays()
    field = TinyMLPField()
    r = build_renderer(RenderConfig(name="neus", neus=NeusConfig(normals=method))).double()
    with torch.no_grad():
        out = render_rays(field, r, o, d, z, T)
    assert not out.depth.requires_grad and not out.weights.requires_grad and not out.normals.requires_grad
    assert all(p.grad is None for p in field.parameters())
    assert torch.isfinite(out.depth).all()


def test_neus_trains_the_field_through_the_normals():
    """AUTOGRAD (create_graph) and FINITE_DIFFERENCE propagate the loss through the slope; DETACHED does not."""
    f, o, d, z = _plane_rays()
    grads = {}
    for method in NormalsMethod:
        a = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)  # scales the SDF: value and gradient

        def field(x, a=a):
            out = f(x)
            return Out(a * out.sdf, out.rgb_logits)

        r = build_renderer(RenderConfig(name="neus", neus=NeusConfig(normals=method))).double()
        out = render_rays(field, r, o, d, z, T)
        out.depth.sum().backward()
        grads[method] = a.grad.item()
    assert grads[NormalsMethod.AUTOGRAD] == pytest.approx(grads[NormalsMethod.FINITE_DIFFERENCE], rel=1e-4)
    assert grads[NormalsMethod.AUTOGRAD] != pytest.approx(grads[NormalsMethod.AUTOGRAD_DETACHED], rel=1e-3)


def test_neus_gradient_of_sdf_only_and_pose_gradient():
    """Colour logits that vary in space do not change the normals (fix of the reference); pose grads flow."""
    f, o, d, z = _plane_rays()

    def field(x):
        out = f(x)
        return Out(out.sdf, x * 10.0)

    o = o.clone().requires_grad_(True)
    out = render_rays(field, build_renderer(RenderConfig(name="neus")).double(), o, d, z, T)
    torch.testing.assert_close(out.normals, (-f.n / T).expand_as(out.normals))
    out.depth.sum().backward()
    assert torch.isfinite(o.grad).all() and o.grad.abs().sum() > 0


def test_neus_annealing_progress():
    r = build_renderer(RenderConfig(name="neus", neus=NeusConfig(anneal_end=0.5)))
    r.set_progress(0.1)
    assert r.anneal_ratio() == pytest.approx(0.2)
    r.set_progress(2.0)
    assert r.anneal_ratio() == 1.0
    assert build_renderer(RenderConfig(name="neus")).anneal_ratio() == 1.0
    cos = torch.tensor([-1.0, 0.0, 1.0])
    torch.testing.assert_close(F.neus_annealed_cos(cos, 0.0), torch.tensor([-1.0, -0.5, 0.0]))
    torch.testing.assert_close(F.neus_annealed_cos(cos, 1.0), torch.tensor([-1.0, 0.0, 0.0]))


@pytest.mark.parametrize("name", sorted(RENDERERS.names()))
@pytest.mark.parametrize("faithful", [False, True])
def test_every_renderer_renders_and_backpropagates(name, faithful):
    field = TinyMLPField()
    r = build_renderer(RenderConfig(name=name, faithful=faithful, density=DensityConfig(learn_beta=True))).double()
    o = torch.zeros(16, 3, dtype=torch.float64)
    d = torch.cat([torch.randn(16, 2, dtype=torch.float64) * 0.3, torch.ones(16, 1, dtype=torch.float64)], -1)
    depth = torch.rand(16, dtype=torch.float64) + 1.5
    depth[:3] = 0
    bounds = torch.tensor([[-3.0, 3.0], [-3.0, 3.0], [-1.0, 5.0]], dtype=torch.float64)
    z = sample_depths(depth, d, o, bounds, SamplingConfig(), T, torch.Generator().manual_seed(0))
    out = render_rays(field, r, o, d, z, T)
    assert (out.weights >= 0).all() and (out.opacity <= 1 + (1e-4 if faithful else 1e-9)).all()
    loss = compute_losses(out, torch.rand(16, 3, dtype=torch.float64), depth, LossConfig(), T)["total"]
    loss.backward()
    for p in list(field.parameters()) + [p for p in r.parameters() if p.requires_grad]:
        assert p.grad is not None and torch.isfinite(p.grad).all()
    assert sum(p.grad.abs().sum() for p in field.parameters()) > 0


def test_sdf_based_attribute():
    assert SdfToWeights.sdf_based is True
    for name in RENDERERS.names():
        cls = RENDERERS.get(name)
        assert isinstance(cls.sdf_based, bool)
        assert cls.sdf_based == (name != "nerf"), name
        assert build_renderer(RenderConfig(name=name)).sdf_based == (name != "nerf")
