"""`field.mlp.precision`: the MLP representation's hidden layers and heads in bfloat16 (autocast).

The float32 field is the reference: the bfloat16 one must agree with it to bfloat16's precision (values, input and
parameter gradients, on fresh random points and weights), keep its parameters and outputs float32, run its first
layer in float32, and leave the default bit for bit what it was.
"""

import numpy as np
import pytest
import torch
from torch import nn

from inrslam.config import load_config
from inrslam.errors import ConfigError
from inrslam.fields import FieldConfig, build_field
from inrslam.fields.config import MlpConfig, MlpPrecision
from inrslam.fields.models import MLPField, check_bfloat16

BOX = np.array([[-0.6, 0.6], [-0.5, 0.5], [0.0, 0.8]])
COUPLINGS = ["coupled_base", "coupled", "decoupled"]
CUDA = pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"))


def _pair(coupling: str, width: int = 64, device: str = "cpu") -> tuple[MLPField, MLPField]:
    """A float32 MLP field and a bfloat16 one with the same (fresh random) weights."""
    ref = build_field(FieldConfig(encoding="mlp", coupling=coupling, mlp=MlpConfig(width=width)), BOX)
    low = build_field(FieldConfig(encoding="mlp", coupling=coupling,
                                  mlp=MlpConfig(width=width, precision=MlpPrecision.BFLOAT16)), BOX)
    low.load_state_dict(ref.state_dict())
    assert isinstance(ref, MLPField) and isinstance(low, MLPField)
    return ref.to(device), low.to(device)


def _points(n: int, seed: int, device: str = "cpu") -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(BOX[:, 0]) - 0.1, torch.tensor(BOX[:, 1]) + 0.1
    return (lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)).float().to(device)


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


@pytest.mark.parametrize("device", ["cpu", CUDA])
@pytest.mark.parametrize("coupling", COUPLINGS)
def test_bfloat16_matches_float32_values_and_gradients(coupling, device):
    torch.manual_seed(17)
    ref, low = _pair(coupling, device=device)
    x = _points(2048, 3, device).requires_grad_()
    out_r, out_l = ref(x), low(x)
    assert out_l.sdf.dtype == torch.float32 and out_l.rgb_logits is not None
    assert out_l.rgb_logits.dtype == torch.float32
    # bfloat16 keeps 8 significant bits: the outputs agree to a few parts in a thousand of their scale
    for r, lo in ((out_r.sdf, out_l.sdf), (out_r.rgb_logits, out_l.rgb_logits)):
        r, lo = r.detach(), lo.detach()
        assert float((r - lo).abs().max()) <= 2e-2 * float(r.abs().max()) + 1e-4
        assert _rel(lo, r) < 1e-2
        assert not torch.equal(r, lo)  # the products did run in bfloat16
    # gradients to the points (tracking) and to every parameter (mapping), same random cotangents
    g = torch.Generator().manual_seed(5)
    cs, cc = torch.randn(2048, generator=g).to(device), torch.randn(2048, 3, generator=g).to(device)
    grads = []
    for f, out in ((ref, out_r), (low, out_l)):
        f.zero_grad()
        loss = (out.sdf * cs).sum() + (out.rgb_logits * cc).sum()
        (gx,) = torch.autograd.grad(loss, x, retain_graph=True)
        loss.backward()
        grads.append((gx, {n: p.grad.clone() for n, p in f.named_parameters()}))
    (gx_r, gp_r), (gx_l, gp_l) = grads
    assert _rel(gx_l, gx_r) < 0.1
    for n, gr in gp_r.items():
        assert gp_l[n].dtype == torch.float32, n
        assert _rel(gp_l[n], gr) < 0.1, n


def test_float32_default_is_the_plain_modules():
    """The default path is the modules composed directly, bit for bit (the paper's MLP)."""
    torch.manual_seed(2)
    f = build_field(FieldConfig(encoding="mlp", mlp=MlpConfig(width=48)), BOX)
    assert isinstance(f, MLPField) and f.precision is MlpPrecision.FLOAT32
    x = _points(512, 9)
    feats = f.freq(f.normalise(x))
    t = f.trunk(feats)
    out = f(x)
    assert torch.equal(out.sdf, f.sdf_head(t)[:, 0])
    assert out.rgb_logits is not None and torch.equal(out.rgb_logits, f.rgb_head(t))
    assert torch.equal(f.sdf(x), out.sdf)


def test_first_layer_float32_rest_bfloat16():
    """The first layer reads the Fourier features (the position's phases) in float32; later layers in bfloat16."""
    torch.manual_seed(4)
    _, low = _pair("coupled_base")
    seen: dict[str, torch.dtype] = {}

    def hook(name: str):
        def record(mod: nn.Module, inp: tuple, out: torch.Tensor) -> None:
            seen[name] = out.dtype
        return record

    hooks = [m.register_forward_hook(hook(name)) for name, m in low.named_modules() if isinstance(m, nn.Linear)]
    low(_points(64, 1))
    for h in hooks:
        h.remove()
    assert seen["trunk.0"] == torch.float32
    assert seen["trunk.2"] == seen["trunk.6"] == seen["sdf_head.2"] == seen["rgb_head.2"] == torch.bfloat16
    assert all(p.dtype == torch.float32 for p in low.parameters())


def test_bfloat16_exact_where_bfloat16_is_exact():
    """Analytic case: at p̂ = 0 every Fourier feature is sin(0) = 0, and with weights 0.25 and biases 0.5 every
    product and sum below is exact in bfloat16, so the bfloat16 field gives the exact value."""
    cfg = FieldConfig(encoding="mlp", mlp=MlpConfig(width=8, depth=2, precision=MlpPrecision.BFLOAT16),
                      hidden_dim=4)
    low = build_field(cfg, BOX)
    assert isinstance(low, MLPField)
    with torch.no_grad():
        for m in low.modules():
            if isinstance(m, nn.Linear):
                m.weight.fill_(0.25)
                m.bias.fill_(0.5)
    x = torch.tensor(BOX[:, 0], dtype=torch.float32)[None]  # p̂ = 0: Fourier features all 0
    out = low(x)
    # trunk: h1 = 0.5 (8 units); h2 = 8 * 0.25 * 0.5 + 0.5 = 1.5; head: 8 * 0.25 * 1.5 + 0.5 = 3.5; 4 * 0.25 * 3.5
    # + 0.5 = 4.0 for the SDF and every colour logit (colour head reads the trunk: coupled_base)
    assert out.sdf.item() == 4.0
    assert out.rgb_logits is not None and torch.equal(out.rgb_logits, torch.full((1, 3), 4.0))


def test_bfloat16_deterministic_and_trains():
    """Same inputs, same bits; an Adam step on a bfloat16 field lowers an SDF loss as the float32 one does."""
    torch.manual_seed(8)
    ref, low = _pair("coupled_base", width=32)
    x = _points(1024, 4)
    assert torch.equal(low(x).sdf, low(x).sdf)
    target = (x[:, 2] - 0.4) / 0.1  # a plane z = 0.4 m, truncation units
    final = []
    for f in (ref, low):
        opt = torch.optim.Adam(f.parameters(), lr=5e-3)
        first = None
        for _ in range(60):
            loss = ((f.sdf(x) - target) ** 2).mean()
            first = float(loss.detach()) if first is None else first
            opt.zero_grad()
            loss.backward()
            opt.step()
        assert float(loss.detach()) < 0.2 * first
        final.append(float(loss.detach()))
    assert final[1] < 2 * final[0]


def test_config_key_and_bad_value():
    cfg = load_config(preset="paper", overrides=["field.encoding=mlp", "field.mlp.precision=bfloat16"])
    assert cfg.field.mlp.precision is MlpPrecision.BFLOAT16
    assert load_config(preset="paper").field.mlp.precision is MlpPrecision.FLOAT32
    with pytest.raises(ConfigError, match="field.mlp.precision") as err:
        load_config(preset="paper", overrides=["field.encoding=mlp", "field.mlp.precision=float16"])
    assert "bfloat16" in str(err.value)  # names the choices


def test_bfloat16_on_a_gpu_without_it_is_a_config_error(monkeypatch):
    """A GPU without bfloat16 arithmetic gets a one-line error naming the key; CPUs and capable GPUs pass."""
    check_bfloat16("cpu")
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: True)
    check_bfloat16("cuda")
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: False)
    with pytest.raises(ConfigError, match="field.mlp.precision.*float32"):
        check_bfloat16("cuda")
    check_bfloat16("cpu")
