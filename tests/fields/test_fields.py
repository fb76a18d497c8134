"""Registry-wide field tests: every F in every coupling mode builds, evaluates, backpropagates."""

import math

import numpy as np
import pytest
import torch

from inrslam.errors import ConfigError
from inrslam.fields import (
    ENCODINGS,
    Coupling,
    FieldConfig,
    KernelChoice,
    build_field,
    model_size_mb,
    param_count,
)
from inrslam.fields.config import MlpConfig
from inrslam.fields.resolution import grid_entries, plane_sizes

BOX = np.array([[-0.6, 0.6], [-0.5, 0.5], [0.0, 0.8]])  # 1.2 x 1.0 x 0.8 m
SMALL = dict(block_coarse=0.3, block_fine=0.1, app_block_coarse=0.3, app_block_fine=0.1, plane_block_coarse=0.3,
             mlp=MlpConfig(width=32), log2_hashmap_size=8)


def _points(n=256, margin=0.2):
    lo, hi = BOX[:, 0] - margin, BOX[:, 1] + margin
    return torch.from_numpy(lo + (hi - lo) * np.random.default_rng(1).random((n, 3))).float()


def test_registry_names():
    assert ENCODINGS.names() == ["mlp", "dense", "hash", "triplane", "tensorf", "dense+tri", "hash+tri"]
    assert all(e.help for e in ENCODINGS.entries())


@pytest.mark.parametrize("coupling", list(Coupling))
@pytest.mark.parametrize("encoding", ["mlp", "dense", "hash", "triplane", "tensorf", "dense+tri", "hash+tri"])
def test_every_field_builds_evaluates_and_backpropagates(encoding, coupling):
    field = build_field(FieldConfig(encoding=encoding, coupling=coupling, **SMALL), BOX)
    x = _points().requires_grad_()
    out = field(x)
    assert out.sdf.shape == (256,) and out.rgb_logits.shape == (256, 3)
    assert torch.isfinite(out.sdf).all() and torch.isfinite(out.rgb_logits).all()
    torch.testing.assert_close(field.sdf(x), out.sdf)
    w = torch.randn(256, 4)
    loss = (out.sdf * w[:, 0]).sum() + (out.rgb_logits * w[:, 1:]).sum() + out.sdf.square().sum()
    loss.backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    for name, p in field.named_parameters():
        g = p.grad.coalesce().values() if p.grad.is_sparse else p.grad
        assert torch.isfinite(g).all(), name
        assert g.abs().sum() > 0, f"{encoding}/{coupling.value}: no gradient for {name}"
    if encoding in ("triplane", "tensorf"):
        assert out.sdf.abs().max() <= 1.0  # tanh SDF


@pytest.mark.parametrize("encoding", ["dense", "hash", "triplane", "tensorf", "hash+tri"])
def test_fused_and_reference_fields_agree(encoding):
    torch.manual_seed(3)
    cfg = FieldConfig(encoding=encoding, coupling=Coupling.COUPLED, kernel=KernelChoice.NUMBA, **SMALL)
    fused = build_field(cfg, BOX)
    ref = build_field(FieldConfig(**{**cfg.__dict__, "kernel": KernelChoice.TORCH}), BOX)
    ref.load_state_dict(fused.state_dict())
    for n_, p in fused.named_parameters():  # make the grid features large enough to matter
        if n_.endswith("table"):
            p.data.normal_(0, 0.5)
    ref.load_state_dict(fused.state_dict())
    x = _points()
    grads = []
    for f in (fused, ref):
        xr = x.clone().requires_grad_()
        out = f(xr)
        (out.sdf.sum() + out.rgb_logits.square().sum()).backward()
        grads.append((out.sdf.detach(), xr.grad, {n: (p.grad.to_dense() if p.grad.is_sparse else p.grad)
                                                  for n, p in f.named_parameters()}))
    torch.testing.assert_close(grads[0][0], grads[1][0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(grads[0][1], grads[1][1], rtol=1e-4, atol=1e-4)
    for n in grads[0][2]:
        torch.testing.assert_close(grads[0][2][n], grads[1][2][n], rtol=1e-4, atol=1e-5, msg=n)


def test_outside_points_read_the_box_face():
    field = build_field(FieldConfig(encoding="hash", **SMALL), BOX)
    inside = torch.tensor([[0.6, 0.0, 0.4], [0.1, -0.5, 0.8]])
    outside = torch.tensor([[5.0, 0.0, 0.4], [0.1, -9.0, 30.0]])
    feats_in = field.encoder(field.normalise(inside))
    feats_out = field.encoder(field.normalise(outside))
    torch.testing.assert_close(feats_in, feats_out)
    out = field(torch.tensor([[1e6, -1e6, 1e6]]))
    assert torch.isfinite(out.sdf).all() and torch.isfinite(out.rgb_logits).all()


def test_fixed_resolution_is_cubic_in_metres():
    ents = grid_entries(np.array([6.0, 5.0, 3.0]), 0.24, 0.02, 2, False, 19, False)
    assert [e["res"] for e in ents] == [[26, 22, 14], [301, 251, 151]]
    cells = [[6.0 / (e["res"][0] - 1), 5.0 / (e["res"][1] - 1), 3.0 / (e["res"][2] - 1)] for e in ents]
    assert np.allclose(cells[1], 0.02) and max(cells[0]) <= 0.24 and min(cells[0]) > 0.22


def test_faithful_resolution_matches_spec_table():
    # spec §3.1: Replica room0 11.8 x 8.7 x 6.8 -> dense R0 = 49, R1 = 590 (cubic over the normalised box)
    ents = grid_entries(np.array([11.8, 8.7, 6.8]), 0.24, 0.02, 2, False, 19, True)
    assert [e["res"][0] for e in ents] in ([49, 589], [49, 590])
    assert all(len(set(e["res"])) == 1 for e in ents)
    # thin_geometry 3.6 x 1.4 x 3.8: coarse per axis 15, 5, 15; fine 180, 70, 190
    sizes = plane_sizes(np.array([3.6, 1.4, 3.8]), 0.24, 0.02, 2, True)
    assert sizes[0] == [15, 5, 15] and abs(sizes[1][0] - 180) <= 1 and abs(sizes[1][2] - 190) <= 1


def test_faithful_planes_touch_only_the_upper_half():
    """Bug 1 reproduced in faithful mode only: [0,1] coordinates in a [-1,1] sampler reach only the vertices
    i >= (R-1)/2 of every plane axis; the default maps the box to the full plane."""
    for faithful in (True, False):
        field = build_field(FieldConfig(encoding="triplane", faithful=faithful, levels=1, block_fine=0.2), BOX)
        x = torch.from_numpy(BOX[:, 0] + (BOX[:, 1] - BOX[:, 0]) * np.random.default_rng(0).random((20000, 3)))
        field(x.float()).sdf.sum().backward()
        g = field.encoder.table.grad
        g = g.to_dense() if g.is_sparse else g
        touched = int((g.abs().sum(1) > 0).sum())
        spec = field.encoder.spec
        if faithful:
            first = (spec.res[:, :2] - 1) // 2  # lowest reachable vertex per axis
            expected = int(np.prod(spec.res[:, :2] - first, axis=1).sum())
        else:
            expected = spec.total_rows
        assert touched == expected
        assert (touched < 0.5 * spec.total_rows) == faithful


def test_tensorf_vm_vs_faithful_combination():
    torch.manual_seed(0)
    cfg = FieldConfig(encoding="tensorf", **SMALL)
    vm = build_field(cfg, BOX).encoder
    x = torch.rand(64, 3)
    f = vm.lookup(x).reshape(64, -1, 3, cfg.feature_dim)  # (N, 2L, 3, F): planes then lines
    L = cfg.levels
    planes, lines = f[:, :L], f[:, L:]
    torch.testing.assert_close(vm(x), (planes * lines).sum(2).reshape(64, -1))
    vm.faithful = True
    torch.testing.assert_close(vm(x), (planes.sum(2) * lines.sum(2)).reshape(64, -1))


def test_model_size_hash_tri_16x2_by_hand():
    """Faithful Hash+Tri 16x2 on NeuralRGBD green_room (8.2 x 3.3 x 4.9 m): tcnn level sizes by hand."""
    bounds = np.array([[-2.6, 5.6], [-0.3, 3.0], [0.2, 5.1]])
    field = build_field(FieldConfig(encoding="hash+tri", levels=16, faithful=True), bounds)
    ext = bounds[:, 1] - bounds[:, 0]
    n0 = max(math.floor(e / 0.24) for e in ext)  # 34
    nf = max(math.floor(e / 0.02) for e in ext)  # 409 (8.2/0.02 truncates to 409.99.. -> 409)
    assert (n0, nf) == (34, 409)
    grid = 0
    for lvl in range(16):
        r = math.ceil(n0 * (nf / n0) ** (lvl / 15) - 1) + 1
        grid += min((r ** 3 + 7) // 8 * 8, 2 ** 19) * 2
    nx, ny, nz = (math.floor(e / 0.24) for e in ext)  # 34, 13, 20
    planes = (nx * ny + nx * nz + ny * nz) * 2
    decoders = (16 * 2 + 2 + 3) * 32 + 32 * 1 + (3 + 16 * 2) * 32 + 32 * 3  # no biases
    assert param_count(field) == grid + planes + decoders
    assert model_size_mb(field) == pytest.approx((grid + planes + decoders) * 4 / 2**20)
    assert model_size_mb(field, with_optimizer=True) == pytest.approx(3 * model_size_mb(field))
    assert 45 < model_size_mb(field) < 52  # 48.9 MiB; the 7-scene mean is 41.7 (paper: 42.45)


def test_fourier_matrix_is_fixed_and_not_counted():
    field = build_field(FieldConfig(encoding="mlp"), BOX)
    assert "freq.B" in dict(field.named_buffers())
    assert all(p is not field.freq.B for p in field.parameters())
    assert float(field.freq.B.std()) == pytest.approx(25.0, rel=0.2)


def test_blob_encoding_partition_of_unity_and_gradients():
    field = build_field(FieldConfig(encoding="dense", gamma="blob", **SMALL), BOX)
    p = torch.rand(100, 3, requires_grad=True)
    enc = field.gamma(p).reshape(100, 3, 16)
    torch.testing.assert_close(enc.sum(-1), torch.ones(100, 3))  # the kernel integrates to 1 over the bins
    assert enc.argmax(-1).eq((p.detach() * 16).floor().long().clamp(max=15)).float().mean() > 0.95
    enc.square().sum().backward()
    assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0


def test_bad_config_raises_config_error():
    with pytest.raises(ConfigError, match="did you mean 'hash'"):
        build_field(FieldConfig(encoding="hsah"), BOX)
    with pytest.raises(ConfigError, match="bounds"):
        build_field(FieldConfig(), np.array([[0, 1], [1, 0], [0, 1]]))
    with pytest.raises(ConfigError, match="gamma"):
        build_field(FieldConfig(gamma="fourier", **SMALL), BOX)


def test_numba_kernel_rejects_non_cpu_dtype():
    field = build_field(FieldConfig(encoding="dense", kernel=KernelChoice.NUMBA, **SMALL), BOX).to(torch.float16)
    with pytest.raises(ValueError, match="float32/float64"):
        field(torch.zeros(2, 3, dtype=torch.float16))


def test_float64_field_gradcheck_on_fused_path():
    field = build_field(FieldConfig(encoding="hash+tri", **SMALL), BOX).double()
    x = (torch.from_numpy(BOX[:, 0] + 0.1 + (BOX[:, 1] - BOX[:, 0] - 0.2) * np.random.default_rng(2).random((6, 3)))
         .requires_grad_())
    assert torch.autograd.gradcheck(lambda x: field.sdf(x), (x,), eps=1e-6, atol=1e-6)
