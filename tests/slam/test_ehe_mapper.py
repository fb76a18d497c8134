"""EHE per-frame mapping rules (docs/ehe.md §5): adaptive early ending, keyframe rule, keyframe window."""

from __future__ import annotations

import torch

from inrslam.slam.ehe.config import EheConfig
from inrslam.slam.ehe.mapper import EarlyStop, MapResult, needs_keyframe, optimise, select_window, voxel_overlap


def test_early_ending_stops_on_the_second_loss_in_a_row_above_the_running_mean():
    e = EarlyStop()
    # running means before each loss: -, 4, 3.5, 3.63; 3.3 is below: the count starts again
    assert [e.update(x) for x in (4.0, 3.0, 3.9, 3.3)] == [False, False, False, False]
    e = EarlyStop()
    assert [e.update(x) for x in (4.0, 3.0, 3.9, 3.8)] == [False, False, False, True]
    e = EarlyStop()
    assert not any(e.update(10.0 - k) for k in range(50))  # a falling loss never stops


def test_optimise_ends_early_on_the_rule_and_runs_all_iterations_without_it():
    losses = iter([4.0, 3.0, 3.9, 3.8, 1.0, 1.0] * 2)
    p = torch.nn.Parameter(torch.zeros(()))

    class Model:
        def loss(self, *args):
            v = next(losses)
            return {"total": p + v, "mse": torch.tensor(0.01), "depth_l1": torch.tensor(0.0)}

    opt = {"field": torch.optim.SGD([p], lr=1e-3)}  # each step moves p (and the losses) by -0.001
    batch = lambda: (None, None, None, None)  # noqa: E731
    res = optimise(Model(), opt, batch, iters=6, early_stop=True, generator=torch.Generator())
    # the 4th loss (3.8) ends mapping and, as in the original, takes no step: 3 steps
    assert isinstance(res, MapResult) and res.iters == 3 and abs(res.psnr[0] - 20.0) < 1e-5
    assert abs(float(p.detach()) + 0.003) < 1e-7
    losses = iter([4.0, 3.0, 3.9, 3.8, 1.0, 1.0])
    assert optimise(Model(), opt, batch, iters=6, early_stop=False, generator=torch.Generator()).iters == 6


def test_keyframe_rule_by_voxel_overlap_or_frame_gap():
    cfg = EheConfig()
    cur, last = torch.arange(0, 100), torch.arange(40, 200)
    assert voxel_overlap(cur, last) == 0.6 and voxel_overlap(cur[:0], last) == 0.0
    assert not needs_keyframe(0.6, 10, cfg)
    assert needs_keyframe(0.5, 10, cfg)  # below kf_overlap = 0.55
    assert needs_keyframe(0.9, 101, cfg) and not needs_keyframe(0.9, 100, cfg)  # more than 100 frames
    # a frame without valid depth observes no voxel: never a keyframe, however long since the last one
    assert not needs_keyframe(0.0, 101, cfg, n_observed=0) and needs_keyframe(0.0, 1, cfg, n_observed=5)


def test_window_takes_greedy_coverage_first_then_random_keyframes():
    cur = torch.arange(0, 100)
    kfs = [torch.arange(0, 60), torch.arange(50, 100), torch.arange(0, 55), torch.arange(500, 600)] + \
          [torch.arange(1000 + k, 1001 + k) for k in range(8)]
    g = torch.Generator().manual_seed(0)
    w = select_window(cur, kfs, window=4, random_fraction=0.5, generator=g)
    # two coverage picks: kf 0 covers 60 voxels, then kf 1 the other 40; 2 random of the rest
    assert w[:2] == [0, 1] and len(w) == 4 and len(set(w)) == 4 and not {0, 1} & set(w[2:])
    # three coverage picks allowed, but after kfs 0 and 1 nothing is left to cover (kf 2 adds none): coverage stops
    # at two and the other four are random, so kf 2 is only there by chance
    w6 = select_window(cur, kfs, window=6, random_fraction=0.5, generator=torch.Generator().manual_seed(0))
    assert w6[:2] == [0, 1] and len(set(w6)) == 6 and not {0, 1} & set(w6[2:])
    picks = {tuple(select_window(cur, kfs, 6, 0.5, torch.Generator().manual_seed(s))[2:3]) for s in range(20)}
    assert len(picks) > 1  # the third is a random draw, not the greedy kf 2
    assert select_window(cur, kfs[:3], window=4, random_fraction=0.5, generator=g) == [0, 1, 2]
    all_random = select_window(cur, kfs, window=4, random_fraction=1.0, generator=g)
    assert len(set(all_random)) == 4


def test_a_first_frame_without_depth_maps_nothing_and_the_next_frames_go_on():
    """A sensor warming up: frame 0 has no valid depth, so no voxel is allocated and every ray misses; mapping runs
    on no samples (zero losses), logs no PSNR, and frame 1 allocates and maps as usual."""
    import dataclasses

    import numpy as np

    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.slam.systems import system_class

    cfg = load_config(preset="ehe", overrides=["data.max_frames=2", "data.builtin.width=96", "data.builtin.height=72",
                                               "ehe.min_points=2", "ehe.first_iters=2", "ehe.iters=2", "ehe.rays=256",
                                               "mesh.enabled=false", "eval.enabled=false"])
    ds = open_dataset(cfg.data)
    system = system_class(cfg)(cfg, ds)
    blank = dataclasses.replace(ds[0], depth=np.zeros_like(ds[0].depth))
    (map0,) = [r for r in system.process(0, blank) if r["type"] == "map"]
    assert system.field.voxels.n_allocated == 0
    assert map0["loss"] == 0.0 and map0["psnr"] is None and map0["voxels"] == 0
    (map1,) = [r for r in system.process(1, ds[1]) if r["type"] == "map"]
    assert map1["voxels"] > 0 and map1["loss"] > 0 and map1["psnr"] > 10
