"""Lazy Adam: touched rows follow Adam, untouched rows are unchanged; dense groups are torch Adam."""

import copy

import numpy as np
import pytest
import torch
from torch import nn

from inrslam.fields import FieldConfig, build_field, make_optimizer
from inrslam.fields.kernels import TableLayout, function, multilinear
from inrslam.fields.kernels.function import unique_rows_of
from inrslam.fields.optim import LazyAdam

BOX = np.array([[-0.6, 0.6], [-0.5, 0.5], [0.0, 0.8]])


def reference_lazy_adam(p, m, v, t, rows, g, lr, b1=0.9, b2=0.999, eps=1e-8):
    """Plain-torch lazy Adam of rows (unique) with gradients g (float64 maths)."""
    p, m, v = p.double(), m.double(), v.double()
    g = g.double()
    m[rows] = b1 * m[rows] + (1 - b1) * g
    v[rows] = b2 * v[rows] + (1 - b2) * g * g
    denom = v[rows].sqrt() / (1 - b2 ** t) ** 0.5 + eps
    p[rows] = p[rows] - lr / (1 - b1 ** t) * m[rows] / denom
    return p.float(), m.float(), v.float()


class Toy(nn.Module):
    """A 2 x (12x12x12) dense grid table (M = 3456 rows) + a small linear decoder."""

    def __init__(self):
        super().__init__()
        ents = [dict(axes=[0, 1, 2], res=[12] * 3, scale=[11.0] * 3, offset=[0.0] * 3, rows=None, hashed=False)] * 2
        self.layout = TableLayout.build(ents)
        self.table = nn.Parameter(torch.randn(self.layout.total_rows, 2))
        self.table._inr_lazy = True
        self.lin = nn.Linear(4, 1)

    def forward(self, x, backend, sparse=True):
        return self.lin(multilinear(x, self.table, self.layout, backend, sparse=sparse).reshape(x.shape[0], -1))


@pytest.mark.parametrize("backend,sparse", [("numba", True), ("numba", False), ("torch", None)])
def test_lazy_adam_matches_reference_and_keeps_untouched_rows(backend, sparse):
    torch.manual_seed(0)
    model = Toy()
    opt = make_optimizer(model, lr=0.05)
    assert [g["name"] for g in opt.param_groups] == ["decoder", "tables"]
    twin = copy.deepcopy(model.lin)
    twin_opt = torch.optim.Adam(twin.parameters(), lr=0.05, betas=(0.9, 0.999), eps=1e-8)
    p_ref = model.table.detach().clone()
    m_ref, v_ref = torch.zeros_like(p_ref), torch.zeros_like(p_ref)
    for t in range(1, 5):
        x = torch.rand(40, 3) * (0.3 + 0.2 * t)  # a different region (and touched set) every step
        opt.zero_grad()
        twin_opt.zero_grad()
        model(x, backend, sparse).square().sum().backward()
        # reference gradient of the table (dense) and the touched rows (x reaches beyond the box at t = 4)
        tref = p_ref.clone().requires_grad_()
        twin(multilinear(x, tref, model.layout, "torch").reshape(40, -1)).square().sum().backward()
        rows = torch.nonzero(tref.grad.abs().sum(1) > 0)[:, 0]
        before = model.table.detach().clone()
        opt.step()
        twin_opt.step()
        p_ref, m_ref, v_ref = reference_lazy_adam(p_ref, m_ref, v_ref, t, rows, tref.grad[rows], lr=0.05)
        torch.testing.assert_close(model.table.detach(), p_ref, rtol=1e-5, atol=1e-6)
        untouched = torch.ones(p_ref.shape[0], dtype=torch.bool)
        untouched[rows] = False
        assert untouched.any() and torch.equal(model.table.detach()[untouched], before[untouched])
        for a, b in zip(model.lin.parameters(), twin.parameters()):  # decoder group = torch Adam
            torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
        state = opt.state[model.table]
        torch.testing.assert_close(state["exp_avg"], m_ref, rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(state["exp_avg_sq"], v_ref, rtol=1e-5, atol=1e-9)


def test_lazy_adam_equals_adam_when_every_row_is_touched():
    torch.manual_seed(0)
    p1 = nn.Parameter(torch.randn(50, 3))
    p1._inr_lazy = True
    p2 = nn.Parameter(p1.detach().clone())
    lazy = make_optimizer(nn.ParameterList([p1]), lr=0.01)
    adam = torch.optim.Adam([p2], lr=0.01)
    for _ in range(5):
        g = torch.randn(50, 3)
        # uncoalesced, unique rows
        p1.grad = torch.sparse_coo_tensor(torch.arange(50)[None], g, (50, 3), check_invariants=False)
        p2.grad = g.clone()
        lazy.step()
        adam.step()
    torch.testing.assert_close(p1, p2, rtol=1e-6, atol=1e-7)


def test_duplicate_sparse_rows_are_summed():
    p1 = nn.Parameter(torch.zeros(10, 2))
    p1._inr_lazy = True
    p2 = nn.Parameter(torch.zeros(10, 2))
    p2._inr_lazy = True
    o1, o2 = LazyAdam([dict(params=[p1], lazy=True)], lr=0.1), LazyAdam([dict(params=[p2], lazy=True)], lr=0.1)
    idx = torch.tensor([[3, 7, 3]])
    vals = torch.tensor([[1.0, -2.0], [0.5, 0.5], [2.0, 1.0]])
    p1.grad = torch.sparse_coo_tensor(idx, vals, (10, 2), check_invariants=False)
    p2.grad = torch.sparse_coo_tensor(idx, vals, (10, 2), check_invariants=False).coalesce().to_dense()
    o1.step()
    o2.step()
    torch.testing.assert_close(p1, p2)
    assert p1[3].abs().sum() > 0 and p1[0].abs().sum() == 0


def test_duplicate_rows_are_summed_on_int64_row_slots(monkeypatch):
    """The de-duplication on a table layout's own row slots (``unique_rows_sum``) with int64 slots, as tables of 2^31
    rows or more get them (forced here): the step of the coalesced gradient, and the slots restored to −1."""
    monkeypatch.setattr(function, "INT32_MAX_ROWS", 0)
    model = Toy()
    p1 = model.table
    p2 = nn.Parameter(p1.detach().clone())
    p2._inr_lazy = True
    o1 = LazyAdam([dict(params=[p1], lazy=True)], lr=0.1, layouts={id(p1): model.layout})
    o2 = LazyAdam([dict(params=[p2], lazy=True)], lr=0.1)
    idx = torch.tensor([[3, 3000, 3, 7, 3]])
    vals = torch.randn(5, 2)
    p1.grad = torch.sparse_coo_tensor(idx, vals, p1.shape, check_invariants=False)
    p2.grad = torch.sparse_coo_tensor(idx, vals, p2.shape, check_invariants=False).coalesce()
    o1.step()
    o2.step()
    torch.testing.assert_close(p1, p2)
    slots = model.layout.workspace.slots
    assert slots.dtype == np.int64 and np.all(slots == -1)


def test_state_dict_roundtrip_and_zero_lr():
    torch.manual_seed(0)
    field = build_field(FieldConfig(encoding="hash", block_coarse=0.3, block_fine=0.1, log2_hashmap_size=8), BOX)
    opt = make_optimizer(field, lr=0.01)
    x = torch.rand(200, 3) - 0.5

    def step(f, o):
        o.zero_grad()
        out = f(x)
        (out.sdf.square().sum() + out.rgb_logits.sum()).backward()
        o.step()

    step(field, opt)
    clone = copy.deepcopy(field)
    opt2 = make_optimizer(clone, lr=0.01)
    opt2.load_state_dict(copy.deepcopy(opt.state_dict()))  # as if saved to disk
    step(field, opt)
    step(clone, opt2)
    for a, b in zip(field.parameters(), clone.parameters()):
        torch.testing.assert_close(a, b)
    for g in opt.param_groups:  # tracking: lr = 0 freezes the map
        g["lr"] = 0.0
    before = [p.detach().clone() for p in field.parameters()]
    step(field, opt)
    assert all(torch.equal(a, b) for a, b in zip(before, field.parameters()))


def test_gradient_accumulated_over_two_backward_passes_is_deduplicated():
    """Two fused backward passes into one .grad (rows shared by both) update the table as one pass over both point
    sets: only a gradient straight from one fused backward may skip the optimizer's de-duplication."""
    torch.manual_seed(0)
    model, twin = Toy(), Toy()
    twin.load_state_dict(model.state_dict())
    opt, twin_opt = make_optimizer(model, lr=0.05), make_optimizer(twin, lr=0.05)
    x1, x2 = torch.rand(40, 3) * 0.5, torch.rand(40, 3) * 0.5  # same region: many shared rows
    model(x1, "numba").square().sum().backward()
    model(x2, "numba").square().sum().backward()
    twin(torch.cat([x1, x2]), "numba").square().sum().backward()  # one pass over both: unique rows
    g = model.table.grad
    # a sum of two gradients: not the last fused one
    assert not unique_rows_of(model.layout, g._indices()[0], g._values())
    torch.testing.assert_close(g.to_dense(), twin.table.grad.to_dense(), rtol=1e-5, atol=1e-6)
    opt.step()
    twin_opt.step()
    torch.testing.assert_close(model.table.detach(), twin.table.detach(), rtol=1e-5, atol=1e-6)
