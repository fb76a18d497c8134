"""Fused numba kernels vs the PyTorch reference: outputs, gradients (random cotangent), gradcheck, clamping."""

import numpy as np
import pytest
import torch

from inrslam.fields.config import FieldConfig
from inrslam.fields.kernels import TableLayout, interp_torch, multilinear
from inrslam.fields.models import build_field
from inrslam.fields.resolution import grid_entries, line_entries, plane_entries, plane_sizes

EXTENT = np.array([1.2, 1.0, 0.8])


def entry_sets():
    """name -> entries covering every kernel: dense, hash (hashed + direct levels), faithful grid, planes, lines."""
    return {
        "dense": grid_entries(EXTENT, 0.3, 0.1, 3, False, 19, False),
        "hash": grid_entries(EXTENT, 0.3, 0.05, 3, True, 10, False),  # level 2: 25x21x17 > 2^10 -> hashed
        "dense_faithful": grid_entries(EXTENT, 0.3, 0.1, 2, False, 19, True),
        "hash_faithful": grid_entries(EXTENT, 0.3, 0.05, 2, True, 10, True),
        "planes": plane_entries(plane_sizes(EXTENT, 0.3, 0.1, 2, False), False),
        "planes_faithful": plane_entries(plane_sizes(EXTENT, 0.3, 0.1, 2, True), True),
        "planes+lines": (plane_entries(plane_sizes(EXTENT, 0.3, 0.1, 2, False), False)
                         + line_entries(plane_sizes(EXTENT, 0.3, 0.1, 2, False), False)),
    }


def _case(name, dtype=torch.float32, n=400, feat=3):
    layout = TableLayout.build(entry_sets()[name])
    table = torch.randn(layout.total_rows, feat, dtype=dtype)
    x = torch.rand(n, 3, dtype=dtype) * 1.2 - 0.1  # ~25% of points have some coordinate outside [0,1]
    return layout, table, x


def _grads(backend, layout, table, x, cot, sparse=None):
    t = table.clone().requires_grad_()
    p = x.clone().requires_grad_()
    out = multilinear(p, t, layout, backend, sparse=sparse)
    out.backward(cot)
    gt = t.grad.to_dense() if t.grad.is_sparse else t.grad
    return out.detach(), p.grad, gt


def test_hash_layout_really_hashes():
    layout = TableLayout.build(entry_sets()["hash"])
    assert layout.hashed.tolist() == [False, False, True]
    assert layout.rows[2] == 1024


@pytest.mark.parametrize("name", list(entry_sets()))
@pytest.mark.parametrize("sparse", [False, True])
def test_numba_matches_reference(name, sparse):
    layout, table, x = _case(name)
    cot = torch.randn(x.shape[0], layout.n_entries, table.shape[1])
    o_n, gx_n, gt_n = _grads("numba", layout, table, x, cot, sparse=sparse)
    o_t, gx_t, gt_t = _grads("torch", layout, table, x, cot)
    torch.testing.assert_close(o_n, o_t, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gx_n, gx_t, rtol=1e-5, atol=1e-4 * gx_t.abs().max().item())
    torch.testing.assert_close(gt_n, gt_t, rtol=1e-5, atol=1e-5)
    assert gx_t.abs().sum() > 0 and gt_t.abs().sum() > 0


def test_sparse_grad_has_unique_touched_rows():
    layout, table, x = _case("hash")
    t = table.clone().requires_grad_()
    multilinear(x, t, layout, "numba", sparse=True).sum().backward()
    rows = t.grad._indices()[0]
    assert t.grad.is_sparse and rows.unique().numel() == rows.numel()
    dense = multilinear(x, table.clone().requires_grad_(), layout, "torch")
    t2 = table.clone().requires_grad_()
    interp_torch(x, t2, layout).sum().backward()
    touched_ref = set(torch.nonzero(t2.grad.abs().sum(1) > 0)[:, 0].tolist())
    assert touched_ref <= set(rows.tolist())  # every row with a gradient is reported (plus zero-weight corners)
    assert dense.shape == (x.shape[0], layout.n_entries, table.shape[1])


@pytest.mark.parametrize("name", ["dense", "hash", "dense_faithful", "hash_faithful"])
def test_merged_clamp_equals_two_clamps(name):
    """The trilinear kernels clamp u once to [lo, hi] instead of p̂ to [0,1] and then u to [0, R−1]: the same
    corner, weight and du/dp̂ for points inside, on and outside the box (float32 inputs, as the kernels see them)."""
    from inrslam.fields.kernels.generic import _axis
    from inrslam.fields.kernels.trilinear import _axis_lean

    layout = TableLayout.build(entry_sets()[name])
    rng = np.random.default_rng(0)
    edges = [-1.0, -1e-7, 0.0, 1e-7, 0.5, 1.0 - 1e-7, 1.0, 1.0 + 1.2e-7, 2.0]
    ps = np.concatenate([edges, rng.uniform(-0.2, 1.2, 300)]).astype(np.float32).astype(np.float64)
    for e in range(layout.n_entries):
        for a in range(3):
            args = (layout.scale[e, a], layout.offset[e, a], layout.res[e, a])
            vertices = (np.arange(layout.res[e, a]) - layout.offset[e, a]) / layout.scale[e, a]  # p̂ of grid vertices
            for p in np.concatenate([ps, vertices[(vertices >= 0) & (vertices <= 1)]]):
                assert _axis(p, *args) == _axis_lean(p, args[0], args[1], layout.lo[e, a], layout.hi[e, a], args[2])


@pytest.mark.parametrize("parts", [1, 2, 3])
@pytest.mark.parametrize("name", ["dense", "hash", "dense_faithful"])
def test_row_partitioned_sparse_backward_matches_reference(monkeypatch, name, parts):
    """The slot-based sparse table backward of large trilinear tables (fine dense grids), split into row parts
    (4-row blocks dealt round-robin here, so every part owns rows all over each level), gives the reference
    gradient with every touched row reported once."""
    from inrslam.fields.kernels import function

    monkeypatch.setattr(function, "ACCUMULATOR_MAX_BYTES", 0)  # force the slot kernel, not the accumulator
    monkeypatch.setattr(function, "PART_LOG2", 2)
    monkeypatch.setattr(function, "_row_parts", lambda layout: parts)
    layout, table, x = _case(name, n=300, feat=2)
    cot = torch.randn(x.shape[0], layout.n_entries, table.shape[1])
    t = table.clone().requires_grad_()
    multilinear(x, t, layout, "numba", sparse=True).backward(cot)
    rows = t.grad._indices()[0]
    assert rows.unique().numel() == rows.numel()
    _, _, gt_ref = _grads("torch", layout, table, x, cot)
    torch.testing.assert_close(t.grad.to_dense(), gt_ref, rtol=1e-5, atol=1e-5)
    assert np.all(layout.workspace.slots == -1)  # the slot scratch is restored for the next call
    # each row is summed over the points in order whatever the split: bitwise the same gradient as one part
    monkeypatch.setattr(function, "_row_parts", lambda layout: 1)
    t1 = table.clone().requires_grad_()
    multilinear(x, t1, layout, "numba", sparse=True).backward(cot)
    assert torch.equal(t1.grad.to_dense(), t.grad.to_dense())


@pytest.mark.parametrize("n_rows,expected", [(1, np.int32), ((1 << 31) - 1, np.int32), (1 << 31, np.int64),
                                             ((1 << 31) + 1, np.int64), (1 << 40, np.int64)])
def test_row_index_dtype_widens_at_2_31_rows(n_rows, expected):
    """Row numbers and slots of the sparse backward (both below the table's rows) stay int32 while they fit, and are
    int64 for a table of 2^31 rows or more (a pure function of the size: nothing is allocated)."""
    from inrslam.fields.kernels.function import row_index_dtype

    dtype = row_index_dtype(n_rows)
    assert dtype == np.dtype(expected)
    assert np.iinfo(dtype).max >= n_rows - 1  # the largest row number and the largest slot fit


@pytest.mark.parametrize("name,parts", [("dense", 1), ("dense", 2), ("hash", 2), ("planes+lines", 1)])
def test_int64_row_indices_give_the_int32_gradient(monkeypatch, name, parts):
    """The row-slot sparse backwards (trilinear, whole levels and row parts; generic) with int64 row numbers and slots,
    as tables of 2^31 rows or more get them (forced here on a small table): bit for bit the int32 gradient, the
    reference's, and the slot map restored to −1."""
    from inrslam.fields.kernels import function

    monkeypatch.setattr(function, "ACCUMULATOR_MAX_BYTES", 0)  # force the slot kernel, not the accumulator
    monkeypatch.setattr(function, "PART_LOG2", 2)
    monkeypatch.setattr(function, "_row_parts", lambda layout: parts)
    layout, table, x = _case(name, n=300, feat=2)
    cot = torch.randn(x.shape[0], layout.n_entries, table.shape[1])
    grads = {}
    for index in (np.int32, np.int64):
        if index is np.int64:
            monkeypatch.setattr(function, "INT32_MAX_ROWS", 0)  # every table counts as large
        t = table.clone().requires_grad_()
        multilinear(x, t, layout, "numba", sparse=True).backward(cot)
        ws = layout.workspace
        assert ws.slots.dtype == ws.sparse_out[0].dtype == np.dtype(index)
        assert np.all(ws.slots == -1)
        grads[index] = t.grad
    assert torch.equal(grads[np.int64]._indices(), grads[np.int32]._indices())
    assert torch.equal(grads[np.int64]._values(), grads[np.int32]._values())
    _, _, gt_ref = _grads("torch", layout, table, x, cot)
    torch.testing.assert_close(grads[np.int64].to_dense(), gt_ref, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("backend", ["torch", "numba"])
@pytest.mark.parametrize("name", ["dense", "hash", "planes_faithful", "planes+lines"])
def test_gradcheck_float64(backend, name):
    layout, table, _ = _case(name, dtype=torch.float64, n=12, feat=2)
    x = (torch.rand(12, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    table.requires_grad_()
    assert torch.autograd.gradcheck(lambda p, t: multilinear(p, t, layout, backend, sparse=False), (x, table),
                                    eps=1e-6, atol=1e-5, fast_mode=True)


def test_double_backward_through_fused_kernel_matches_reference():
    """create_graph (e.g. losses on SDF normals) differentiates the reference inside the fused backward."""
    layout, table, _ = _case("dense", dtype=torch.float64, n=50)
    x = torch.rand(50, 3, dtype=torch.float64) * 0.9 + 0.05
    res = {}
    for backend in ("numba", "torch"):
        t = table.clone().requires_grad_()
        p = x.clone().requires_grad_()
        out = multilinear(p, t, layout, backend, sparse=False)
        (gx,) = torch.autograd.grad(out.square().sum(), p, create_graph=True)
        gx.square().sum().backward()
        res[backend] = (gx.detach(), t.grad)
    torch.testing.assert_close(res["numba"][0], res["torch"][0])
    torch.testing.assert_close(res["numba"][1], res["torch"][1])


@pytest.mark.parametrize("backend", ["torch", "numba"])
@pytest.mark.parametrize("name", ["dense", "hash", "planes", "planes+lines"])
def test_outside_points_are_clamped(backend, name):
    layout, table, _ = _case(name)
    x = torch.tensor([[-3.0, 0.5, 0.5], [0.2, 7.0, 0.4], [0.3, 0.6, -1e3], [2.0, -2.0, 5.0]])
    p = x.clone().requires_grad_()
    out = multilinear(p, table, layout, backend)
    ref = multilinear(x.clamp(0, 1), table, layout, backend)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, ref)
    out.sum().backward()
    outside = (x < 0) | (x > 1)
    assert torch.all(p.grad[outside] == 0)  # no gradient along clamped axes
    assert p.grad[~outside].abs().sum() > 0


def test_vertex_aligned_full_plane_mapping():
    """Fixed mode: p̂ = 0 / 1 reads the first / last vertex exactly; faithful mode reads the plane centre at p̂ = 0."""
    sizes = [[5, 4, 3]]
    for faithful, expect_col in ((False, 0), (True, 2)):
        layout = TableLayout.build(plane_entries(sizes, faithful)[:1])  # the xy plane, 5 x 4 vertices
        table = torch.arange(20, dtype=torch.float32)[:, None]  # row = j * 5 + i
        out = multilinear(torch.zeros(1, 3), table, layout, "numba")
        j = 0 if not faithful else 1.5  # (4-1)/2
        assert out.item() == pytest.approx(j * 5 + expect_col)
    layout = TableLayout.build(plane_entries(sizes, False)[:1])
    assert multilinear(torch.ones(1, 3), torch.arange(20.0)[:, None], layout, "numba").item() == pytest.approx(19.0)


def test_hash_index_matches_tcnn_formula():
    """A hashed level reads row (i ⊕ j·2654435761 ⊕ k·805459861) mod 2^b of integer vertex (i,j,k)."""
    ent = dict(axes=[0, 1, 2], res=[101, 101, 101], scale=[100.0] * 3, offset=[0.0] * 3, rows=1 << 8, hashed=True)
    layout = TableLayout.build([ent])
    table = torch.randn(256, 1)
    i, j, k = 37, 58, 91
    x = torch.tensor([[i / 100, j / 100, k / 100]], dtype=torch.float64)
    expected = table[(i ^ (j * 2654435761) ^ (k * 805459861)) % 256]
    for backend in ("numba", "torch"):
        assert multilinear(x, table.double(), layout, backend).item() == pytest.approx(expected.item(), rel=1e-6)


@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("name", ["dense", "hash", "planes+lines"])
def test_nan_points_get_nan_features_and_no_gradient(backend, name):
    layout, table, x = _case(name)
    x[7, 1] = float("nan")
    x[30, 0] = float("nan")
    cot = torch.randn(x.shape[0], layout.n_entries, table.shape[1])
    out, gx, gt = _grads(backend, layout, table, x, cot)
    ok = torch.ones(x.shape[0], dtype=torch.bool)
    ok[[7, 30]] = False
    assert torch.isnan(out[~ok]).all() and torch.isfinite(out[ok]).all()
    o_ref, gx_ref, gt_ref = _grads("torch", layout, table, x[ok], cot[ok])  # the same without the NaN points
    torch.testing.assert_close(out[ok], o_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gt, gt_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gx[ok], gx_ref, rtol=1e-5, atol=1e-4 * gx_ref.abs().max().item())
    assert torch.all(gx[~ok] == 0)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        multilinear(x[:, :2], table, layout, backend)


@pytest.mark.parametrize("name", ["dense", "hash"])
def test_cancelling_infinities_take_the_nan_safe_path_with_the_same_result(name):
    """+inf and -inf coordinates sum to NaN, so the one-sum NaN test sends the points through the NaN-safe path, which
    finds no NaN row: features and gradients equal the reference's, where ±inf clamps to the box."""
    from inrslam.fields.kernels.function import _may_have_nan

    layout, table, x = _case(name)
    assert not _may_have_nan(x)
    x[3, 0], x[4, 2] = float("inf"), float("-inf")
    assert _may_have_nan(x) and not bool(torch.isnan(x).any())
    cot = torch.randn(x.shape[0], layout.n_entries, table.shape[1])
    out, gx, gt = _grads("numba", layout, table, x, cot)
    o_ref, gx_ref, gt_ref = _grads("torch", layout, table, x, cot)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, o_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gt, gt_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gx, gx_ref, rtol=1e-5, atol=1e-4 * gx_ref.abs().max().item())
    y = torch.zeros(5, 3)
    y[2, 1] = float("nan")
    assert _may_have_nan(y)


@pytest.mark.parametrize("name", ["dense", "hash", "planes+lines"])
def test_kernels_called_directly_with_nan_stay_in_bounds(name):
    """The raw numba kernels map a NaN coordinate to the box's low face (a defined row) instead of indexing out of
    range (``multilinear`` never passes them one)."""
    from inrslam.fields.kernels import generic, trilinear
    from inrslam.fields.kernels.function import _meta, tri_meta

    layout, table, x = _case(name)
    x[:, 0] = float("nan")
    xn, tab = x.numpy(), table.numpy()
    low = x.clone()
    low[:, 0] = 0.0
    expected = interp_torch(low, table, layout)
    out = np.zeros((x.shape[0], layout.n_entries, tab.shape[1]), np.float32)
    if layout.trilinear:
        no_jac = np.empty((0, layout.n_entries, tab.shape[1], 3), np.float32)
        trilinear.tri_forward(xn, tab, *tri_meta(layout), out, no_jac)
        grad = np.zeros_like(tab)
        trilinear.tri_backward_table_dense(xn, np.ones_like(out), *tri_meta(layout), grad)
        assert np.isfinite(grad).all()
    else:
        generic.interp_forward(xn, tab, *_meta(layout), out)
    torch.testing.assert_close(torch.from_numpy(out), expected, rtol=1e-5, atol=1e-5)


def test_reference_table_gradient_is_the_same_on_every_run():
    """The reference path's table gradient (many points per row) is summed in a fixed order: same bits each run."""
    layout, table, x = _case("hash", n=6000, feat=2)
    cot = torch.randn(x.shape[0], layout.n_entries, 2)
    grads = {_grads("torch", layout, table, x, cot)[2].numpy().tobytes() for _ in range(5)}
    assert len(grads) == 1


def _corner_loop(layout, xn, tab, g):
    """The generic kernels' corner loop (before lines and planes were unrolled), transliterated to numpy scalars
    with numba's arithmetic (float64 weights times the table's dtype; products of two float32 values in float32):
    the forward (N,E,F), the input gradient (N,3) float64, the table gradient (M,F) of cotangent g and, per entry,
    the rows with a non-zero weight in first-touch order (those the sparse table gradient reports)."""
    from inrslam.fields.kernels.function import _meta
    from inrslam.fields.kernels.generic import _corner, _setup
    from inrslam.fields.kernels.indexing import vertex_row

    ndim, axes, res, scale, offset, stride, hashed, rows, row_off = _meta(layout)
    N, E, F = xn.shape[0], layout.n_entries, tab.shape[1]
    out, gx, gt = np.zeros((N, E, F), tab.dtype), np.zeros((N, 3)), np.zeros_like(tab)
    touched: list[list[int]] = [[] for _ in range(E)]
    f64 = np.float64
    for n in range(N):
        for e in range(E):
            d, i0, i1, i2, w0, w1, w2, d0, d1, d2 = _setup(xn, n, e, ndim, axes, res, scale, offset)
            gu = [0.0, 0.0, 0.0]
            for c in range(1 << d):
                b0, b1, b2, t0, t1, t2 = _corner(c, d, w0, w1, w2)
                wt = f64(t0) * f64(t1) * f64(t2)
                r = row_off[e] + vertex_row(hashed[e], rows[e], i0 + b0, i1 + b1, i2 + b2, *stride[e])
                if wt == 0.0:
                    touched[e].append(-1)  # counted below, not a row
                elif r not in touched[e]:
                    touched[e].append(r)
                dot = f64(0.0)
                for f in range(F):
                    out[n, e, f] = f64(out[n, e, f]) + wt * f64(tab[r, f])
                    gt[r, f] = f64(gt[r, f]) + wt * f64(g[n, e, f])
                    dot = dot + f64(tab[r, f] * g[n, e, f])
                s = [1.0 if b else -1.0 for b in (b0, b1, b2)]
                gu[0] += dot * s[0] * t1 * t2
                gu[1] += dot * t0 * s[1] * t2
                gu[2] += dot * t0 * t1 * s[2]
            for k, dk in enumerate((d0, d1, d2)[:d]):
                gx[n, axes[e, k]] += gu[k] * dk
    zero_weight = sum(t.count(-1) for t in touched)
    return out, gx, gt, [[r for r in t if r >= 0] for t in touched], zero_weight


def _bits(a):
    """The array's bits (unsigned integers of its width): -0.0 and +0.0 differ."""
    return a.view(np.uint32 if a.dtype == np.float32 else np.uint64)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_unrolled_lines_and_planes_are_bit_identical_to_the_corner_loop(dtype):
    """Lines and planes run unrolled in the generic kernels (forward, input gradient, sparse table gradient): bit
    for bit the corner loop's results, so `paper` runs with tri-plane / TensoRF fields keep their bits. Points inside,
    outside, on grid vertices (zero-weight corners) and with a NaN coordinate."""
    from inrslam.fields.kernels import generic
    from inrslam.fields.kernels.function import _meta, _sparse_out, row_slots

    layout = TableLayout.build(entry_sets()["planes+lines"])
    rng = np.random.default_rng()
    tab = rng.standard_normal((layout.total_rows, 2)).astype(dtype)
    xn = rng.uniform(-0.1, 1.1, (60, 3)).astype(dtype)
    xn[:10] = np.round(xn[:10] * 6) / 6
    xn[10, 1] = np.nan
    g = rng.standard_normal((60, layout.n_entries, 2)).astype(dtype)
    out_ref, gx_ref, gt_ref, touched, zero_weight = _corner_loop(layout, xn, tab, g)
    assert zero_weight > 0  # the case the sparse gradient must skip occurs
    out = np.zeros_like(out_ref)
    generic.interp_forward(xn, tab, *_meta(layout), out)
    gx = np.zeros((60, 3))
    generic.interp_backward_x(xn, tab, g, *_meta(layout), gx)
    cap_off, out_rows, out_vals = _sparse_out(layout, 60, 2, dtype)
    counts = np.zeros(layout.n_entries, np.int64)
    generic.interp_backward_table_sparse(xn, g, *_meta(layout), row_slots(layout), cap_off, out_rows, out_vals,
                                         counts)
    gt = np.zeros_like(tab)
    for e in range(layout.n_entries):
        sl = slice(cap_off[e], cap_off[e] + counts[e])
        assert out_rows[sl].tolist() == touched[e]  # zero-weight corners are not reported (lazy Adam skips them)
        gt[out_rows[sl]] = out_vals[sl]
    for a, b in ((out, out_ref), (gx, gx_ref), (gt, gt_ref)):
        assert np.array_equal(_bits(a), _bits(b))
    assert np.abs(gx).sum() > 0 and np.all(np.isfinite(out))


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_auto_runs_the_reference_on_half_precision_tables(dtype):
    """`kernel=auto` picks numba only for float32 / float64 tables (it used to pick it and then refuse)."""
    bounds = np.array([[0.0, 1.0]] * 3)
    x = torch.rand(16, 3, generator=torch.Generator().manual_seed(3)).to(dtype)
    out = {}
    for kernel in ("auto", "torch"):
        torch.manual_seed(0)
        field = build_field(FieldConfig(encoding="dense", kernel=kernel), bounds).to(dtype)
        out[kernel] = field(x).sdf
    assert out["auto"].dtype == dtype and torch.equal(out["auto"], out["torch"])
    with pytest.raises(ValueError, match="float32/float64 tables"):
        torch.manual_seed(0)
        build_field(FieldConfig(encoding="dense", kernel="numba"), bounds).to(dtype)(x)
