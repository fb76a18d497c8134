"""Blocked MLP of the MLP representation (`fields.kernels.blocked_mlp`) vs its plain-autograd reference: outputs and
gradients on fresh random inputs, float64 gradcheck, analytic cases, buffer reuse, dispatch, and the MLP field's
switch `field.decoder_kernel`."""

import copy
import pickle

import numpy as np
import pytest
import torch
from autograd_graph import node_names

from inrslam.fields import kernels
from inrslam.fields.config import FieldConfig, MlpConfig
from inrslam.fields.kernels import blocked_mlp as bm
from inrslam.fields.kernels.blocked_mlp import BlockedMlpFn, MlpScratch, block_rows, blocked_mlp, blocked_mlp_torch
from inrslam.fields.models import MLPField, build_field

CUDA = pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"))
BOX = np.array([[-1.0, 1.0], [-0.5, 1.5], [0.0, 2.0]])


def _net(widths, dtype=torch.float64, seed=None, freq_dim=None):
    """Fresh random parameters (W1, b1, ...) for widths [input, h1, ..., out], and a (3, freq_dim) B if asked (the
    input is then 3 points wide and the first layer reads freq_dim features)."""
    g = torch.Generator().manual_seed(int(np.random.SeedSequence(seed).generate_state(1)[0]))
    params = []
    layer_in = [widths[0] if freq_dim is None else freq_dim] + list(widths[1:-1])
    for a, b in zip(layer_in, widths[1:]):
        params += [torch.randn(b, a, dtype=dtype, generator=g) / a ** 0.5,
                   0.1 * torch.randn(b, dtype=dtype, generator=g)]
    freq = None if freq_dim is None else 3.0 * torch.randn(3, freq_dim, dtype=dtype, generator=g)
    return params, freq, g


def _run(backend, x, params, freq, cot, need_x=True, need_p=True):
    """Output and gradients (x, then each parameter; None where not asked) of one call; need_p: bool or one per
    parameter."""
    need = [need_p] * len(params) if isinstance(need_p, bool) else need_p
    leaves = [x.clone().requires_grad_(need_x)] + [p.clone().requires_grad_(r) for p, r in zip(params, need)]
    out = blocked_mlp(leaves[0], leaves[1:], MlpScratch(), backend, freq=freq)
    if out.requires_grad:
        out.backward(cot)
    return out.detach(), [t.grad for t in leaves]


@pytest.fixture
def small_blocks(monkeypatch):
    """Blocks of 64 rows (the minimum), so that a few hundred samples span several blocks and a partial one."""
    monkeypatch.setattr(bm, "BLOCK_BYTES", 1)
    assert block_rows(256, torch.float32) == 64


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("with_freq", [False, True])
@pytest.mark.parametrize("n", [1, 64, 200])
def test_matches_reference(small_blocks, n, with_freq, dtype):
    params, freq, g = _net([3 if with_freq else 9, 24, 24, 16, 4], dtype, freq_dim=11 if with_freq else None)
    x = torch.randn(n, 3 if with_freq else 9, dtype=dtype, generator=g)
    cot = torch.randn(n, 4, dtype=dtype, generator=g)
    out_r, grads_r = _run("torch", x, params, freq, cot)
    out_b, grads_b = _run("numba", x, params, freq, cot)
    eps = 1e-5 if dtype == torch.float32 else 1e-12  # sums in another order: rounding of the dtype, scaled
    torch.testing.assert_close(out_b, out_r, rtol=eps, atol=eps * max(1.0, float(out_r.abs().max())))
    for gb, gr in zip(grads_b, grads_r):
        torch.testing.assert_close(gb, gr, rtol=10 * eps, atol=10 * eps * max(1.0, float(gr.abs().max())))


def test_trunk_width_shapes_match_reference():
    """The MLP field's own shapes (93 features, 4 x 256 trunk, 64 -> 4 heads) over several default-size blocks."""
    params, freq, g = _net([3, 256, 256, 256, 256, 64, 4], torch.float32, freq_dim=93)
    n = block_rows(256, torch.float32) * 2 + 333
    x = torch.rand(n, 3, generator=g)
    cot = torch.randn(n, 4, generator=g)
    out_r, grads_r = _run("torch", x, params, freq, cot)
    out_b, grads_b = _run("numba", x, params, freq, cot)
    torch.testing.assert_close(out_b, out_r, rtol=1e-4, atol=1e-5)
    for gb, gr in zip(grads_b, grads_r):
        torch.testing.assert_close(gb, gr, rtol=1e-3, atol=1e-4 * max(1.0, float(gr.abs().max())))


@pytest.mark.parametrize("need_x,need_p", [(True, False), (False, True),
                                           (False, [False, False, True, True, False, True]),
                                           (True, [True, False, False, False, False, False])])
def test_only_requested_gradients(small_blocks, need_x, need_p):
    params, freq, g = _net([3, 20, 20, 5], freq_dim=7)
    x = torch.randn(150, 3, dtype=torch.float64, generator=g)
    cot = torch.randn(150, 5, dtype=torch.float64, generator=g)
    _, grads_r = _run("torch", x, params, freq, cot, need_x, need_p)
    _, grads_b = _run("numba", x, params, freq, cot, need_x, need_p)
    wanted = [need_x] + [need_p if isinstance(need_p, bool) else need_p[i] for i in range(len(params))]
    for gb, gr, w in zip(grads_b, grads_r, wanted):
        assert (gb is None) == (not w)
        if w:
            torch.testing.assert_close(gb, gr, rtol=1e-11, atol=1e-11 * max(1.0, float(gr.abs().max())))


@pytest.mark.parametrize("with_freq", [False, True])
def test_gradcheck_float64(small_blocks, with_freq):
    params, freq, g = _net([3 if with_freq else 5, 6, 6, 2], freq_dim=4 if with_freq else None)
    x = torch.randn(130, 3 if with_freq else 5, dtype=torch.float64, generator=g, requires_grad=True)
    leaves = [p.clone().requires_grad_(True) for p in params]
    scratch = MlpScratch()
    assert torch.autograd.gradcheck(lambda x, *p: BlockedMlpFn.apply(x, *p, freq, scratch), (x, *leaves))


def test_analytic_linear_and_relu():
    """One hidden unit: y = 2 relu(x1 - x2 + 0.5) + 1. Values and gradients by hand, including a pre-activation of
    exactly 0 (no gradient passes, as in torch's ReLU) and a negative one."""
    w1, b1 = torch.tensor([[1.0, -1.0]]), torch.tensor([0.5])
    w2, b2 = torch.tensor([[2.0]]), torch.tensor([1.0])
    x = torch.tensor([[1.0, 0.0], [0.0, 0.5], [0.0, 2.0]], requires_grad=True)
    y = blocked_mlp(x, [w1, b1, w2, b2], MlpScratch(), "numba")
    assert torch.equal(y.detach(), torch.tensor([[4.0], [1.0], [1.0]]))
    y.sum().backward()
    assert torch.equal(x.grad, torch.tensor([[2.0, -2.0], [0.0, 0.0], [0.0, 0.0]]))


def test_analytic_fourier_features():
    """sin(x B) with B = [[pi/2], [0], [0]] and an identity output layer: y = sin(pi x/2), dy/dx = pi/2 cos(pi x/2)."""
    b = torch.tensor([[np.pi / 2], [0.0], [0.0]], dtype=torch.float64)
    w, bias = torch.eye(1, dtype=torch.float64), torch.zeros(1, dtype=torch.float64)
    x = torch.tensor([[0.0, 5.0, 6.0], [1.0, 0.0, 0.0], [1.0 / 3.0, 1.0, 1.0]], dtype=torch.float64,
                     requires_grad=True)
    y = blocked_mlp(x, [w, bias], MlpScratch(), "numba", freq=b)
    torch.testing.assert_close(y.detach()[:, 0], torch.tensor([0.0, 1.0, 0.5], dtype=torch.float64))
    y.sum().backward()
    expected = torch.zeros(3, 3, dtype=torch.float64)
    expected[:, 0] = torch.tensor([np.pi / 2, 0.0, np.pi / 2 * np.cos(np.pi / 6)], dtype=torch.float64)
    torch.testing.assert_close(x.grad, expected)


def test_nan_input_as_reference():
    params, _, g = _net([4, 8, 2], torch.float32)
    x = torch.randn(10, 4, generator=g)
    x[3, 1] = float("nan")
    cot = torch.randn(10, 2, generator=g)
    out_r, grads_r = _run("torch", x, params, None, cot)
    out_b, grads_b = _run("numba", x, params, None, cot)
    torch.testing.assert_close(out_b, out_r, equal_nan=True)
    assert torch.isnan(out_b[3]).all() and not torch.isnan(out_b[[0, 1, 2, 4]]).any()
    for gb, gr in zip(grads_b, grads_r):
        torch.testing.assert_close(gb, gr, equal_nan=True)


def test_no_grad_and_repeat_bit_for_bit(small_blocks):
    params, freq, g = _net([3, 16, 16, 3], torch.float32, freq_dim=8)
    x = torch.randn(300, 3, generator=g)
    scratch = MlpScratch()
    first = blocked_mlp(x, params, scratch, "numba", freq=freq).clone()
    with torch.no_grad():
        again = blocked_mlp(x.requires_grad_(True), params, scratch, "numba", freq=freq)
    assert torch.equal(again, first)
    assert torch.equal(blocked_mlp(x, params, scratch, "numba", freq=freq), first)


def test_buffers_reused_only_when_free(small_blocks):
    """Two graphs alive at once keep their own activations (both backwards right); once freed, the next call
    reuses the kept buffers (the pool does not grow)."""
    params, freq, g = _net([3, 16, 16, 2], freq_dim=5)
    leaves = [p.clone().requires_grad_(True) for p in params]
    scratch = MlpScratch()
    xa, xb = (torch.randn(200, 3, dtype=torch.float64, generator=g) for _ in range(2))
    ya = blocked_mlp(xa, leaves, scratch, "numba", freq=freq)
    yb = blocked_mlp(xb, leaves, scratch, "numba", freq=freq)
    for x, y in ((xa, ya), (xb, yb)):
        got = torch.autograd.grad(y.sum(), leaves)
        ref = torch.autograd.grad(blocked_mlp_torch(x, leaves, freq).sum(), leaves)
        for a, b in zip(got, ref):
            torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-11 * max(1.0, float(b.abs().max())))
    del ya, yb, got
    held = scratch.pool.nbytes
    for _ in range(3):
        y = blocked_mlp(xa, leaves, scratch, "numba", freq=freq)
        y.sum().backward()
        del y
    assert scratch.pool.nbytes == held


def test_second_order_runs_the_reference():
    """Inside `kernels.second_order()` (NeuS normals trained through) the reference runs: the gradient is itself
    differentiable."""
    params, freq, g = _net([3, 8, 1], freq_dim=4)
    x = torch.randn(20, 3, dtype=torch.float64, generator=g, requires_grad=True)
    leaves = [p.clone().requires_grad_(True) for p in params]
    with kernels.second_order():
        y = blocked_mlp(x, leaves, MlpScratch(), "numba", freq=freq)
    assert y.grad_fn is not None and not any("BlockedMlp" in n for n in node_names(y.grad_fn))
    (gx,) = torch.autograd.grad(y.sum(), x, create_graph=True)
    (gw,) = torch.autograd.grad(gx.pow(2).sum(), leaves[0])
    assert gw is not None and gw.abs().sum() > 0


def test_errors_name_the_problem():
    params, _, _ = _net([4, 8, 2], torch.float32)
    with pytest.raises(ValueError, match="do not chain"):
        blocked_mlp(torch.zeros(5, 3), params, MlpScratch(), "numba")
    with pytest.raises(ValueError, match=r"freq \(4, 8\) must be \(3, F\)"):
        blocked_mlp(torch.zeros(5, 3), params, MlpScratch(), "numba", freq=torch.zeros(4, 8))
    with pytest.raises(ValueError, match="weight, bias"):
        blocked_mlp(torch.zeros(5, 4), params[:3], MlpScratch(), "numba")
    with pytest.raises(ValueError, match="decoder kernel 'numba' needs CPU"):
        blocked_mlp(torch.zeros(5, 4, dtype=torch.float64), params, MlpScratch(), "numba")
    with pytest.raises(ValueError, match="unknown decoder kernel"):
        blocked_mlp(torch.zeros(5, 4), params, MlpScratch(), "fast")


def test_scratch_copies_and_pickles_empty():
    scratch = MlpScratch()
    params, _, _ = _net([4, 8, 2], torch.float32)
    blocked_mlp(torch.randn(50, 4), params, scratch, "numba")
    assert scratch.pool.nbytes > 0
    for other in (copy.deepcopy(scratch), pickle.loads(pickle.dumps(scratch))):
        assert other.pool.nbytes == 0 and other.pool.max_buffers == scratch.pool.max_buffers


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_auto_falls_back_to_the_reference_off_cpu_or_float16(device):
    params, freq, g = _net([3, 8, 2], torch.float32, freq_dim=4)
    x = torch.randn(30, 3, generator=g)
    params, freq, x = [p.to(device) for p in params], freq.to(device), x.to(device)
    if device == "cpu":  # a dtype the blocked path does not take
        params, freq, x = [p.half() for p in params], freq.half(), x.half()
    y = blocked_mlp(x, params, MlpScratch(), "auto", freq=freq)
    assert torch.equal(y, blocked_mlp_torch(x, params, freq))


# --- the MLP field's switch ---------------------------------------------------------------------------------------

def _field_pair(coupling: str, dtype: torch.dtype = torch.float32) -> tuple[MLPField, MLPField]:
    torch.manual_seed(int(np.random.SeedSequence().generate_state(1)[0]) % (2 ** 31))
    ref = build_field(FieldConfig(encoding="mlp", coupling=coupling, mlp=MlpConfig(width=64)), BOX).to(dtype)
    fused = copy.deepcopy(ref)
    fused.decoder_backend = "numba"
    assert isinstance(ref, MLPField) and isinstance(fused, MLPField)
    return ref, fused


@pytest.mark.parametrize("coupling", ["coupled_base", "coupled", "decoupled"])
@pytest.mark.parametrize("train_weights", [False, True])
def test_field_matches_plain_modules(coupling, train_weights):
    """`field.decoder_kernel=numba` on the MLP field against the plain modules (its `torch` value), every coupling,
    in tracking (map frozen: gradient to the points only) and mapping (every parameter) form."""
    ref, fused = _field_pair(coupling, torch.float64)
    g = torch.Generator().manual_seed(3)
    x = (torch.rand(700, 3, generator=g, dtype=torch.float64) * 2 - 0.5).requires_grad_(True)
    cs, cc = torch.randn(700, generator=g, dtype=torch.float64), torch.randn(700, 3, generator=g, dtype=torch.float64)
    results = []
    for f in (ref, fused):
        f.requires_grad_(train_weights)
        f.zero_grad()
        out = f(x)
        loss = (out.sdf * cs).sum() + (out.rgb_logits * cc).sum()
        (gx,) = torch.autograd.grad(loss, x, retain_graph=train_weights)
        if train_weights:
            loss.backward()
        results.append((out.sdf.detach(), out.rgb_logits.detach(), gx,
                        [p.grad for p in f.parameters()] if train_weights else []))
    (s_r, c_r, gx_r, gp_r), (s_f, c_f, gx_f, gp_f) = results
    for a, b in [(s_f, s_r), (c_f, c_r), (gx_f, gx_r)] + list(zip(gp_f, gp_r)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10 * max(1.0, float(b.abs().max())))
    with torch.no_grad():
        sdf_r, sdf_f = ref.sdf(x), fused.sdf(x)
    torch.testing.assert_close(sdf_f, sdf_r, rtol=1e-10,
                               atol=1e-10 * max(1.0, float(sdf_r.abs().max())))


def test_field_switch_runs_the_blocked_network():
    ref, fused = _field_pair("coupled_base")
    x = torch.rand(100, 3, requires_grad=True)
    assert any("BlockedMlp" in n for n in node_names(fused(x).sdf.grad_fn))
    assert not any("BlockedMlp" in n for n in node_names(ref(x).sdf.grad_fn))
    low = build_field(FieldConfig(encoding="mlp", decoder_kernel="numba", mlp=MlpConfig(width=32,
                                                                                        precision="bfloat16")), BOX)
    assert not any("BlockedMlp" in n for n in node_names(low(x).sdf.grad_fn))  # bfloat16 keeps autocast

