"""KernelWorkspace: every piece of scratch the fused kernels keep lives in the layout's one declared workspace (the
layout itself takes no attributes beyond its fields), and copies / pickles of a layout carry none of it."""

import copy
import dataclasses
import pickle

import numpy as np
import pytest
import torch

from inrslam.fields.kernels import KernelWorkspace, TableLayout, function, multilinear
from inrslam.fields.resolution import grid_entries, line_entries, plane_entries, plane_sizes

EXTENT = np.array([1.2, 1.0, 0.8])
LAYOUTS = {
    "hash": lambda: grid_entries(EXTENT, 0.3, 0.05, 3, True, 10, False),  # trilinear kernels
    "planes+lines": lambda: (plane_entries(plane_sizes(EXTENT, 0.3, 0.1, 2, False), False)
                             + line_entries(plane_sizes(EXTENT, 0.3, 0.1, 2, False), False)),  # generic kernels
}


def _every_path(layout: TableLayout, table: torch.Tensor, x: torch.Tensor, monkeypatch) -> dict[str, torch.Tensor]:
    """Forward + backward through every path: sparse (accumulator), sparse (row slots), dense, torch reference."""
    out = {}
    for mode in ("acc", "slot", "dense", "torch"):
        with monkeypatch.context() as m:
            if mode == "slot":
                m.setattr(function, "ACCUMULATOR_MAX_BYTES", 0)
            t = table.detach().clone().requires_grad_()
            p = x.clone().requires_grad_()
            y = multilinear(p, t, layout, "torch" if mode == "torch" else "numba", sparse=mode in ("acc", "slot"))
            y.square().sum().backward()
            out[mode] = torch.cat([y.detach().reshape(-1), p.grad.reshape(-1), t.grad.to_dense().reshape(-1)])
    return out


def _is_empty(ws: KernelWorkspace) -> bool:
    return (ws.slots is None and ws.accumulator is None and ws.sparse_out is None and ws.level_major is None
            and ws.grad_pool.nbytes == 0 and ws.last_grad is None and ws.torch_arrays == {})


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_scratch_lives_in_the_declared_workspace_only(name, monkeypatch):
    layout = TableLayout.build(LAYOUTS[name]())
    assert _is_empty(layout.workspace)
    table = torch.randn(layout.total_rows, 2)
    _every_path(layout, table, torch.rand(200, 3) * 1.2 - 0.1, monkeypatch)
    ws = layout.workspace
    # the layout has no instance dict: its attributes are exactly its declared fields, and none can be added
    assert not hasattr(layout, "__dict__")
    assert set(type(layout).__slots__) == {f.name for f in dataclasses.fields(layout)}
    assert set(type(ws).__slots__) == {f.name for f in dataclasses.fields(ws)}
    with pytest.raises(AttributeError):
        layout._scratch = np.zeros(3)
    with pytest.raises(AttributeError):
        ws._scratch = np.zeros(3)
    # ... and the kernels did keep their scratch, in the workspace
    assert np.all(ws.slots == -1) and ws.slots.shape == (layout.total_rows,)
    assert ws.sparse_out is not None and ws.grad_pool.nbytes > 0 and ws.last_grad is not None
    assert set(ws.torch_arrays) == {"cpu"}
    assert layout.trilinear == (name == "hash")
    if layout.trilinear:  # the accumulator path (hash grids) only exists for trilinear layouts
        acc, _, mark = ws.accumulator
        assert not acc.any() and not mark.any() and ws.level_major is not None  # zeroed again after the drain
    else:
        assert ws.accumulator is None and ws.level_major is None


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_copies_and_pickles_carry_no_scratch(name, monkeypatch):
    layout = TableLayout.build(LAYOUTS[name]())
    table = torch.randn(layout.total_rows, 2)
    x = torch.rand(150, 3) * 1.2 - 0.1
    expected = _every_path(layout, table, x, monkeypatch)
    assert not _is_empty(layout.workspace)
    for other in (copy.copy(layout), copy.deepcopy(layout), pickle.loads(pickle.dumps(layout))):
        assert other.workspace is not layout.workspace and _is_empty(other.workspace)
        assert other.trilinear == layout.trilinear and other.total_rows == layout.total_rows
        for f in dataclasses.fields(layout):
            if isinstance(getattr(layout, f.name), np.ndarray):
                np.testing.assert_array_equal(getattr(other, f.name), getattr(layout, f.name))
        got = _every_path(other, table, x, monkeypatch)  # a copy rebuilds its scratch: the very same results
        assert all(torch.equal(got[k], expected[k]) for k in expected)
