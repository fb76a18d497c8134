"""World points of valid depth pixels: the numba pass against the torch reference (fresh random inputs, invalid
depths, dtypes, devices) and an analytic case."""

import numpy as np
import pytest
import torch

from inrslam.geometry.backproject import world_points, world_points_torch


def _rigid(g: torch.Generator) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = q * torch.sign(torch.det(q))  # a rotation
    c2w[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64) * 2
    return c2w.float()


def _inputs(n_pix=5000, m=3000):
    g = torch.Generator().manual_seed(int(np.random.SeedSequence().generate_state(1)[0]))  # fresh every run
    depth = torch.rand(n_pix, generator=g) * 6
    depth[::11] = 0.0  # holes
    depth[5::97] = float("nan")
    depth[7::89] = 20.0  # beyond d_max
    idx = torch.randint(0, n_pix, (m,), generator=g)
    dirs = torch.cat([torch.rand(m, 2, generator=g) - 0.5, torch.ones(m, 1)], dim=1)
    return depth, idx, dirs, _rigid(g)


def test_matches_the_reference_in_order():
    depth, idx, dirs, c2w = _inputs()
    got = world_points(depth, idx, dirs, c2w, 0.01, 10.0)
    ref = world_points_torch(depth, idx, dirs, c2w, 0.01, 10.0)
    assert got.shape == ref.shape and got.shape[0] > 0
    d = depth[idx]
    assert got.shape[0] == int(((d > 0.01) & (d < 10.0)).sum())  # NaN, holes and far pixels dropped
    # one rounding apart at most (the reference's 3 x 3 product may be ordered differently by another BLAS)
    torch.testing.assert_close(got, ref, rtol=1e-6, atol=1e-6)


def test_analytic_case():
    """Direction (0.5, -0.25, 1) at 2 m, camera turned 90 degrees about z and moved by (1, 2, 3): camera point
    (1, -0.5, 2) -> world (0.5, 1, 2) + (1, 2, 3) = (1.5, 3, 5); the second pixel has no depth."""
    c2w = torch.tensor([[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]])
    depth = torch.tensor([2.0, 0.0])
    dirs = torch.tensor([[0.5, -0.25, 1.0], [0.1, 0.1, 1.0]])
    got = world_points(depth, torch.tensor([0, 1]), dirs, c2w, 0.01, 10.0)
    assert got.tolist() == [[1.5, 3.0, 5.0]]


def test_no_valid_depth_and_other_dtypes():
    depth, idx, dirs, c2w = _inputs()
    assert world_points(torch.zeros_like(depth), idx, dirs, c2w, 0.01, 10.0).shape == (0, 3)
    d64, r64, c64 = depth.double(), dirs.double(), c2w.double()
    assert torch.equal(world_points(d64, idx, r64, c64, 0.01, 10.0), world_points_torch(d64, idx, r64, c64, 0.01, 10.0))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA"))])
def test_runs_on_any_device(device):
    depth, idx, dirs, c2w = (t.to(device) for t in _inputs())
    got = world_points(depth, idx, dirs, c2w, 0.01, 10.0)
    assert got.device.type == device
    torch.testing.assert_close(got, world_points_torch(depth, idx, dirs, c2w, 0.01, 10.0), rtol=1e-6, atol=1e-6)
