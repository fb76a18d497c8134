"""The fused depth-guided sampler (`rendering.sampling_kernel`, `sample_depths(kernel=...)`) is bit-identical to
the torch reference: same samples, same random draws, for every layout, dtype and thread count."""

from __future__ import annotations

import itertools

import pytest
import torch

from inrslam.fields.kernels.threads import thread_scope
from inrslam.rendering.config import SamplingConfig
from inrslam.rendering.sampling import sample_depths

BOUNDS = [[-3.0, 3.0], [-2.0, 3.0], [-1.0, 4.0]]


def rays(seed: int, dtype, R: int = 131, no_depth: bool = False):
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(R, generator=g, dtype=dtype) * 4
    depth[::5] = 0  # rays without depth sample uniformly to the box exit
    depth[3] = 0.05  # free-space span below `near`: clamped
    depth[4] = float("nan")  # invalid depth: sampled as a ray without depth by both
    depth[6] = float("inf")  # infinite depth: inf and NaN samples, in the same places
    if no_depth:
        depth[:] = 0
    dirs = torch.cat([torch.rand(R, 2, generator=g, dtype=dtype) - 0.5, torch.ones(R, 1, dtype=dtype)], dim=1)
    return depth, dirs, torch.randn(R, 3, generator=g, dtype=dtype), torch.tensor(BOUNDS, dtype=dtype)


LAYOUTS = list(itertools.product([(48, 12), (7, 1), (5, 0)], [True, False], ["none", "sampling"], [0.0, 0.3]))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("counts,jitter,variant,near", LAYOUTS)
def test_fused_samples_equal_the_reference_bit_for_bit(dtype, counts, jitter, variant, near):
    cfg = SamplingConfig(n_free=counts[0], n_surface=counts[1], jitter=jitter, variant=variant, near=near)
    for seed, no_depth in ((0, False), (1, False), (2, True)):
        depth, dirs, origins, bounds = rays(seed, dtype, no_depth=no_depth)
        ref = sample_depths(depth, dirs, origins, bounds, cfg, 0.1, torch.Generator().manual_seed(seed), "torch")
        got = sample_depths(depth, dirs, origins, bounds, cfg, 0.1, torch.Generator().manual_seed(seed), "numba")
        assert got.dtype == ref.dtype and got.shape == ref.shape
        torch.testing.assert_close(got, ref, rtol=0, atol=0, equal_nan=True)  # bit for bit, NaN where torch has one
        finite = torch.isfinite(got).all(dim=1)
        assert bool((got[finite, 1:] >= got[finite, :-1]).all())  # sorted, also after the jitter


def test_the_random_stream_continues_as_with_the_reference():
    """Both paths draw the same uniforms from the caller's generator: what it gives next is the same."""
    depth, dirs, origins, bounds = rays(4, torch.float32)
    cfg = SamplingConfig()
    after = []
    for kernel in ("torch", "numba"):
        g = torch.Generator().manual_seed(9)
        sample_depths(depth, dirs, origins, bounds, cfg, 0.1, g, kernel)
        after.append(torch.rand(5, generator=g))
    assert torch.equal(after[0], after[1])


def test_fused_samples_do_not_depend_on_the_thread_count():
    depth, dirs, origins, bounds = rays(5, torch.float32, R=2000)
    outs = []
    for n in (1, 2):
        with thread_scope(n):
            outs.append(sample_depths(depth, dirs, origins, bounds, SamplingConfig(), 0.1,
                                      torch.Generator().manual_seed(0), "numba"))
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_kernel_choice_and_devices(device):
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    depth, dirs, origins, bounds = (x.to(device) for x in rays(6, torch.float32))
    cfg = SamplingConfig()
    ref = sample_depths(depth, dirs, origins, bounds, cfg, 0.1, torch.Generator().manual_seed(0), "torch")
    auto = sample_depths(depth, dirs, origins, bounds, cfg, 0.1, torch.Generator().manual_seed(0))  # "auto"
    torch.testing.assert_close(auto, ref, rtol=0, atol=0, equal_nan=True)
    if device == "cuda":
        with pytest.raises(ValueError, match="sampling kernel 'numba' needs CPU"):
            sample_depths(depth, dirs, origins, bounds, cfg, 0.1, None, "numba")
    with pytest.raises(ValueError, match="unknown sampling kernel 'fast'"):
        sample_depths(depth, dirs, origins, bounds, cfg, 0.1, None, "fast")
