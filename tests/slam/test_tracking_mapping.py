"""Tracking and mapping/BA against a stub scene model whose loss is a known function of the camera poses."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from inrslam.slam.config import SlamConfig
from inrslam.slam.keyframes import KeyframeStore
from inrslam.slam.mapping import map_frame
from inrslam.slam.tracking import track_frame


class StubModel(nn.Module):
    """loss = mean over rays of |camera centre of the ray - target of its depth tag|^2 + w^2.

    Each ray's `depth` value tags which target it is pulled towards (so keyframe rays and current-frame rays can
    have different targets); `w` is a scene parameter that mapping optimises and tracking must not touch."""

    def __init__(self, targets: torch.Tensor):
        super().__init__()
        self.targets = targets  # (T, 3)
        self.w = nn.Parameter(torch.tensor(1.0))
        self.renderer = SimpleNamespace(set_progress=lambda p: None)
        self.calls = 0

    def loss(self, c2w, dirs, rgb, depth, generator, behind=None):
        self.calls += 1
        centres = c2w[..., :3, 3].expand(dirs.shape[0], 3)
        tgt = self.targets[depth.long()]
        total = ((centres - tgt) ** 2).sum(-1).mean() + self.w**2
        out = SimpleNamespace(depth=depth.clone(), rgb=rgb)
        return {"total": total, "color": ((rgb - 0.5) ** 2).mean()}, out


def rays(n, tag):
    return torch.zeros(n, 3), torch.full((n, 3), 0.5), torch.full((n,), float(tag))


def test_tracking_moves_towards_minimum_and_keeps_map_frozen():
    model = StubModel(torch.tensor([[0.01, -0.02, 0.015]]))
    cfg = SlamConfig(track_iters=50, track_lr=1e-3)
    res = track_frame(model, torch.eye(4), *rays(8, 0), cfg, None, max_jump=0.5)
    assert res.fallback is None
    assert torch.linalg.norm(res.c2w[:3, 3] - model.targets[0]) < 0.5 * torch.linalg.norm(model.targets[0])
    assert model.w.grad is None and model.w.requires_grad  # no gradient into the map, flag restored


def test_tracking_best_pose_includes_final_update_unless_faithful():
    target = torch.tensor([[0.01, 0.0, 0.0]])
    cfg = SlamConfig(track_iters=1, track_lr=1e-3)
    ours = track_frame(StubModel(target), torch.eye(4), *rays(4, 0), cfg, None, max_jump=0.5)
    orig = track_frame(StubModel(target), torch.eye(4), *rays(4, 0),
                       dataclasses.replace(cfg, eval_final_pose=False), None, max_jump=0.5)
    # one Adam step moves x by lr towards the target: only the evaluation of the final pose can keep it
    assert ours.c2w[0, 3].item() == pytest.approx(1e-3, rel=1e-3)
    assert torch.equal(orig.c2w, torch.eye(4))
    # `iters` counts the pose updates made: track_iters either way (the faithful loop logged one fewer)
    for final in (True, False):
        res = track_frame(StubModel(target), torch.eye(4), *rays(4, 0),
                          dataclasses.replace(cfg, track_iters=20, eval_final_pose=final), None, max_jump=0.5)
        assert res.iters == 20
    nan = track_frame(StubModel(torch.tensor([[float("nan"), 0.0, 0.0]])), torch.eye(4), *rays(4, 0), cfg, None,
                      max_jump=0.5)
    assert nan.iters == 0  # the first loss was NaN: no update made


def test_tracking_rejects_pose_jumps_and_nan():
    model = StubModel(torch.tensor([[5.0, 0.0, 0.0]]))
    cfg = SlamConfig(track_iters=30, track_lr=0.5)
    res = track_frame(model, torch.eye(4), *rays(4, 0), cfg, None, max_jump=0.5)
    assert res.fallback == "pose_jump" and torch.equal(res.c2w, torch.eye(4))
    far = track_frame(StubModel(torch.tensor([[5.0, 0.0, 0.0]])), torch.eye(4), *rays(4, 0), cfg, None, max_jump=0.0)
    assert far.fallback is None and far.c2w[0, 3] > 0.5  # 0: never rejected (the original's behaviour)
    nan_model = StubModel(torch.tensor([[float("nan"), 0.0, 0.0]]))
    res = track_frame(nan_model, torch.eye(4), *rays(4, 0), cfg, None, max_jump=0.5)
    assert res.fallback == "nan_loss" and torch.equal(res.c2w, torch.eye(4))


def make_store(k):
    store = KeyframeStore()
    for slot in range(k):
        store.add(5 * slot, *rays(50, 0))
    return store


def test_mapping_fixes_first_keyframe_and_steps_poses_every_5_iterations():
    targets = torch.tensor([[0.02, 0.0, 0.0], [0.0, 0.0, 0.0]])
    kf = torch.eye(4).repeat(3, 1, 1)
    g = torch.Generator().manual_seed(0)
    cfg = SlamConfig(map_iters=4, ba_pose_every=5, map_pixels=32, ba_lr=1e-3)
    model = StubModel(targets)
    opt = {"scene": torch.optim.Adam(model.parameters(), lr=0.01)}
    res = map_frame(model, opt, make_store(3), kf, torch.eye(4), lambda n: rays(n, 1), cfg, g)
    # 4 iterations < ba_pose_every: no pose step yet, but the scene parameter was stepped every iteration
    assert torch.equal(res.kf_c2w, kf) and torch.equal(res.cur_c2w, torch.eye(4))
    assert model.w.item() == pytest.approx(1.0 - 4 * 0.01, abs=1e-4)
    res = map_frame(model, opt, make_store(3), kf, torch.eye(4), lambda n: rays(n, 1),
                    dataclasses.replace(cfg, map_iters=10), g)
    assert torch.equal(res.kf_c2w[0], kf[0])  # keyframe 0 is fixed
    # other keyframes moved towards their rays' target (+x), two pose steps of ~lr each
    assert res.kf_c2w[1, 0, 3].item() == pytest.approx(2e-3, rel=0.05)
    assert res.kf_c2w[2, 0, 3].item() == pytest.approx(2e-3, rel=0.05)
    assert torch.allclose(res.cur_c2w, torch.eye(4), atol=1e-6)  # current rays' target is where it already is


def test_mapping_without_ba_for_a_single_keyframe_and_current_ray_count():
    targets = torch.tensor([[0.02, 0.0, 0.0], [0.0, 0.0, 0.0]])
    seen = []

    def cur(n):
        seen.append(n)
        return rays(n, 1)

    cfg = SlamConfig(map_iters=5, ba_pose_every=5, map_pixels=64, map_current_min=10)
    model = StubModel(targets)
    opt = {"scene": torch.optim.Adam(model.parameters(), lr=0.01)}
    res = map_frame(model, opt, make_store(1), torch.eye(4)[None], torch.eye(4), cur, cfg, torch.Generator())
    assert torch.equal(res.kf_c2w[0], torch.eye(4)) and torch.equal(res.cur_c2w, torch.eye(4))
    assert seen == [64] * 5  # max(map_pixels // #KF, map_current_min) current-frame rays per iteration
    seen.clear()
    map_frame(model, opt, make_store(8), torch.eye(4).repeat(8, 1, 1), torch.eye(4), cur, cfg, torch.Generator())
    assert seen == [10] * 5


def test_mapping_skips_non_finite_losses_without_touching_the_map():
    model = StubModel(torch.tensor([[float("nan"), 0.0, 0.0]]))
    opt = {"scene": torch.optim.Adam(model.parameters(), lr=0.01)}
    cfg = SlamConfig(map_iters=3, map_pixels=8)
    res = map_frame(model, opt, make_store(2), torch.eye(4).repeat(2, 1, 1), torch.eye(4), lambda n: rays(n, 0),
                    cfg, torch.Generator())
    assert res.skipped == 3 and model.w.item() == 1.0


def test_loss_plateaued_on_analytic_histories():
    from inrslam.slam.mapping import loss_plateaued

    geometric = [0.9**k for k in range(200)]  # window means fall by 0.9^10 = 0.35 every 10 iterations: never flat
    assert not any(loss_plateaued(geometric[:n], 10, 0.01) for n in range(1, 201))
    # loss 1 / (k + 1): the mean of window j (iterations 10 j .. 10 j + 9) is about 1 / (10 (j + 1/2)), so two
    # consecutive windows differ by a factor (j + 1/2) / (j + 3/2) > 0.99 first at j = 99: the check after
    # iteration 10 (j + 2) = 1010
    harmonic = [1.0 / (k + 1) for k in range(5000)]
    assert next(n for n in range(1, 5001) if loss_plateaued(harmonic[:n], 10, 0.01)) == 1010
    flat = [1.0] * 40
    assert [n for n in range(1, 41) if loss_plateaued(flat[:n], 10, 0.01)] == [20, 30, 40]  # every window, from two
    assert not loss_plateaued([float("nan")] * 20, 10, 0.01)  # no finite loss: not a plateau
    assert not loss_plateaued(flat[:20], 0, 0.01)


def test_initialisation_stops_once_the_loss_is_flat():
    from inrslam.slam.mapping import initialise, loss_plateaued

    # loss = 1 + w^2 (the fixed camera sits 1 m from its target): Adam (lr 0.1) drives w to 0, then the loss is flat
    model = StubModel(torch.tensor([[1.0, 0.0, 0.0]]))
    opt = {"scene": torch.optim.Adam(model.parameters(), lr=0.1)}
    rays0 = lambda n: (torch.eye(4),) + rays(n, 0)  # noqa: E731
    full = initialise(model, opt, rays0, 300, 8, None)
    assert len(full) == 300
    model = StubModel(torch.tensor([[1.0, 0.0, 0.0]]))
    opt = {"scene": torch.optim.Adam(model.parameters(), lr=0.1)}
    early = initialise(model, opt, rays0, 300, 8, None, stop_window=20, stop_tol=0.01)
    assert 40 <= len(early) < 300 and len(early) % 20 == 0
    assert early == full[:len(early)]  # the same steps, fewer of them
    assert loss_plateaued(early, 20, 0.01) and not any(loss_plateaued(early[:n], 20, 0.01) for n in range(len(early)))
