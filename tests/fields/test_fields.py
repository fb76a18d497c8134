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
    make_optimizer,
    model_size_mb,
    param_count,
)
from inrslam.fields.config import MlpConfig
from inrslam.fields.resolution import grid_entries, plane_sizes

BOX = np.array([[-0.6, 0.6], [-0.5, 0.5], [0.0, 0.8]])  # 1.2 x 1.0 x 0.8 m
SMALL = dict(block_coarse=0.3, block_fine=0.1, app_block_coarse=0.3, app_block_fine=0.1, plane_block_coarse=0.3,
             mlp=MlpConfig(width=32), log2_hashmap_size=8)


# every registered F: an encoding added to the registry is picked up by the generic tests below
ENCODING_NAMES = ENCODINGS.names()
PAPER_ENCODINGS = ["mlp", "dense", "hash", "triplane", "tensorf", "dense+tri", "hash+tri"]


def small(encoding: str, **kw) -> FieldConfig:
    """A tiny field of `encoding` (30 / 10 cm cells, 2^8 hash rows, 32-wide MLP) so the generic tests stay fast."""
    return FieldConfig(encoding=encoding, **{**SMALL, **kw})


def _points(n=256, margin=0.2):
    lo, hi = BOX[:, 0] - margin, BOX[:, 1] + margin
    return torch.from_numpy(lo + (hi - lo) * np.random.default_rng(1).random((n, 3))).float()


def _has_tables(encoding: str) -> bool:
    """Whether the field looks features up in tables (grids / planes / lines), i.e. has kernel choices."""
    return any(n.endswith("table") for n, _ in build_field(small(encoding), BOX).named_parameters())


TABLE_ENCODINGS = [e for e in ENCODING_NAMES if _has_tables(e)]


def _grad(p: torch.Tensor) -> torch.Tensor:
    return p.grad.coalesce().values() if p.grad.is_sparse else p.grad


def test_registry_names():
    assert ENCODING_NAMES[:len(PAPER_ENCODINGS)] == PAPER_ENCODINGS  # the paper's seven, in its order, first
    assert all(e.help for e in ENCODINGS.entries())
    assert "mlp" not in TABLE_ENCODINGS and {"dense", "hash", "triplane", "tensorf"} <= set(TABLE_ENCODINGS)


@pytest.mark.parametrize("coupling", list(Coupling))
@pytest.mark.parametrize("encoding", ENCODING_NAMES)
def test_every_field_builds_evaluates_and_backpropagates(encoding, coupling):
    field = build_field(small(encoding, coupling=coupling), BOX)
    x = _points().requires_grad_()
    out = field(x)
    assert out.sdf.shape == (256,) and out.rgb_logits.shape == (256, 3)
    assert out.sdf.dtype == out.rgb_logits.dtype == torch.float32
    assert torch.isfinite(out.sdf).all() and torch.isfinite(out.rgb_logits).all()
    torch.testing.assert_close(field.sdf(x), out.sdf)
    w = torch.randn(256, 4)
    loss = (out.sdf * w[:, 0]).sum() + (out.rgb_logits * w[:, 1:]).sum() + out.sdf.square().sum()
    loss.backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    for name, p in field.named_parameters():
        assert torch.isfinite(_grad(p)).all(), name
        assert _grad(p).abs().sum() > 0, f"{encoding}/{coupling.value}: no gradient for {name}"
    # the optimiser's groups (dense decoder Adam / lazy table Adam) hold every parameter once, each reached
    groups = make_optimizer(field, lr=1e-2).param_groups
    ids = [id(p) for g in groups for p in g["params"]]
    assert sorted(ids) == sorted(id(p) for p in field.parameters())
    for g in groups:
        assert any(_grad(p).abs().sum() > 0 for p in g["params"]), f"{encoding}: group {g['name']} gets no gradient"
    if encoding in ("triplane", "tensorf"):
        assert out.sdf.abs().max() <= 1.0  # tanh SDF


@pytest.mark.parametrize("encoding", ENCODING_NAMES)
def test_every_field_is_deterministic_per_seed(encoding):
    def build(seed):
        torch.manual_seed(seed)
        return build_field(small(encoding), BOX)

    x = _points(64)
    a, b, c = build(0), build(0), build(1)
    for (na, pa), (nb, pb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert na == nb and torch.equal(pa, pb), na
    oa, ob, oc = a(x), b(x), c(x)
    assert torch.equal(oa.sdf, ob.sdf) and torch.equal(oa.rgb_logits, ob.rgb_logits)
    assert not torch.equal(oa.sdf, oc.sdf) and not torch.equal(oa.rgb_logits, oc.rgb_logits)


@pytest.mark.parametrize("encoding", ENCODING_NAMES)
def test_every_field_depends_only_on_the_position_in_its_box(encoding):
    """The same seed over a translated box gives the same field, translated (points in and outside the box)."""
    shift = torch.tensor([2.5, -1.0, 0.75])
    fields = []
    for box in (BOX, BOX + shift.numpy()[:, None]):
        torch.manual_seed(0)
        fields.append(build_field(small(encoding), box))
    x = _points(128)
    a, b = fields[0](x), fields[1](x + shift)
    torch.testing.assert_close(b.sdf, a.sdf, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(b.rgb_logits, a.rgb_logits, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("encoding", ENCODING_NAMES)
def test_every_field_is_finite_far_outside_its_box(encoding):
    field = build_field(small(encoding), BOX)
    x = torch.tensor([[1e6, -1e6, 1e6], [-40.0, 0.0, 0.4], [0.0, 0.0, 1e3]], requires_grad=True)
    out = field(x)
    assert torch.isfinite(out.sdf).all() and torch.isfinite(out.rgb_logits).all()
    (out.sdf.sum() + out.rgb_logits.sum()).backward()
    assert torch.isfinite(x.grad).all()
    assert all(torch.isfinite(_grad(p)).all() for p in field.parameters())


@pytest.mark.parametrize("encoding", ENCODING_NAMES)
def test_every_field_rejects_bad_bounds(encoding):
    for bad in (np.array([[0, 1], [1, 0], [0, 1]]), np.array([[0, 1], [0, np.nan], [0, 1]]), np.zeros((2, 2))):
        with pytest.raises(ConfigError, match="field bounds"):
            build_field(small(encoding), bad)


@pytest.mark.parametrize("encoding", ENCODING_NAMES)
def test_every_field_trains_and_counts_its_size(encoding):
    """A few steps of the field's own optimiser fit a target; the model size counts every parameter."""
    field = build_field(small(encoding), BOX)
    n = sum(p.numel() for p in field.parameters())
    assert param_count(field) == n > 0 and model_size_mb(field) == pytest.approx(4 * n / 2**20)
    x = _points(128)
    target = 0.5 * torch.sin(4 * x).sum(-1)

    def loss():
        out = field(x)
        return (out.sdf - target).square().mean() + (out.rgb_logits - 0.3).square().mean()

    opt = make_optimizer(field, lr=1e-2)
    before = float(loss().detach())
    for _ in range(10):
        opt.zero_grad()
        loss().backward()
        opt.step()
    assert float(loss().detach()) < 0.9 * before


@pytest.mark.parametrize("encoding", TABLE_ENCODINGS)
def test_fused_and_reference_fields_agree(encoding):
    torch.manual_seed(3)
    cfg = small(encoding, coupling=Coupling.COUPLED, kernel=KernelChoice.NUMBA)
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


@pytest.mark.parametrize("encoding", TABLE_ENCODINGS)
def test_outside_points_read_the_box_face(encoding):
    """Every table lookup of the field clamps p̂ to the unit box: an outside point reads the nearest face."""
    field = build_field(small(encoding), BOX)
    encoders = [m for m in field.modules() if isinstance(getattr(m, "table", None), torch.nn.Parameter)]
    assert encoders
    inside = torch.tensor([[0.6, 0.0, 0.4], [0.1, -0.5, 0.8]])
    outside = torch.tensor([[5.0, 0.0, 0.4], [0.1, -9.0, 30.0]])
    for enc in encoders:
        torch.testing.assert_close(enc(field.normalise(inside)), enc(field.normalise(outside)))


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
        layout = field.encoder.layout
        if faithful:
            first = (layout.res[:, :2] - 1) // 2  # lowest reachable vertex per axis
            expected = int(np.prod(layout.res[:, :2] - first, axis=1).sum())
        else:
            expected = layout.total_rows
        assert touched == expected
        assert (touched < 0.5 * layout.total_rows) == faithful


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
    # values `load_config` refuses are refused when a FieldConfig is built in code, too (not a late traceback)
    with pytest.raises(ConfigError, match=r"field\.geo_feat_dim: expected a positive integer, got -1"):
        build_field(FieldConfig(encoding="dense", coupling="coupled", geo_feat_dim=-1, **SMALL), BOX)
    with pytest.raises(ConfigError, match=r"field\.grid_init: expected a finite number >= 0"):
        build_field(FieldConfig(grid_init=-1e-4, **SMALL), BOX)
    with pytest.raises(ConfigError, match=r"field\.plane_init_std: expected a finite number >= 0, got nan"):
        build_field(FieldConfig(encoding="triplane", plane_init_std=float("nan"), **SMALL), BOX)
    with pytest.raises(ConfigError, match=r"field\.mlp\.precision: 'fp16' is not one of float32, bfloat16"):
        build_field(FieldConfig(encoding="mlp", mlp=MlpConfig(precision="fp16")), BOX)


def test_numba_kernel_rejects_non_cpu_dtype():
    field = build_field(FieldConfig(encoding="dense", kernel=KernelChoice.NUMBA, **SMALL), BOX).to(torch.float16)
    with pytest.raises(ValueError, match="float32/float64"):
        field(torch.zeros(2, 3, dtype=torch.float16))


def test_float64_field_gradcheck_on_fused_path():
    field = build_field(FieldConfig(encoding="hash+tri", **SMALL), BOX).double()
    x = (torch.from_numpy(BOX[:, 0] + 0.1 + (BOX[:, 1] - BOX[:, 0] - 0.2) * np.random.default_rng(2).random((6, 3)))
         .requires_grad_())
    assert torch.autograd.gradcheck(lambda x: field.sdf(x), (x,), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("encoding", ["dense", "hash", "dense+tri"])
def test_faithful_grid_on_a_box_smaller_than_two_coarse_cells_is_a_config_error(encoding):
    # the original's rule gives the coarsest level one cell per axis (scale 0): no grid to build
    small = np.array([[0.0, 0.4], [0.0, 0.3], [0.0, 0.3]])
    with pytest.raises(ConfigError, match=r"field.faithful=true: the scene box's longest side \(0.400 m\) is under "
                                          r"twice the cell size \(0.24 m\)"):
        build_field(FieldConfig(encoding=encoding, faithful=True), small)
    assert build_field(FieldConfig(encoding=encoding, faithful=True, block_coarse=0.15), small) is not None
    # one level is the fine level alone: the coarse cell size plays no part
    one = build_field(FieldConfig(encoding=encoding, faithful=True, levels=1), small)
    assert one.sdf(torch.from_numpy(small.mean(1, keepdims=True).T.repeat(5, 0)).float()).shape == (5,)
    with pytest.raises(ConfigError, match=r"under twice the cell size \(0.25 m\)"):
        build_field(FieldConfig(encoding=encoding, faithful=True, levels=1, block_fine=0.25), small)
