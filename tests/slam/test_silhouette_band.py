"""A shorter SDF band behind the depth at silhouettes only (`loss.silhouette_behind`): the near side of a depth edge
is found, its rays carry their band end through the keyframe store into the loss, and nothing changes when off."""

from __future__ import annotations

import torch

from inrslam.config import load_config
from inrslam.datasets import open_dataset
from inrslam.rendering.config import LossConfig
from inrslam.rendering.losses import compute_losses, sdf_masks
from inrslam.rendering.render import RenderOutput
from inrslam.slam.frame_tensors import silhouettes
from inrslam.slam.keyframes import KeyframeStore
from inrslam.slam.system import SlamSystem

TINY = ["data.max_frames=2", "data.builtin.width=96", "data.builtin.height=72", "slam.init_iters=3",
        "slam.track_iters=2", "slam.map_iters=2", "mesh.enabled=false", "eval.enabled=false",
        "output.tensorboard=false"]


def test_silhouettes_mark_the_near_side_within_the_radius():
    d = torch.full((5, 8), 1.0)
    d[:, 5:] = 3.0  # an object (1 m) in front of a wall (3 m): the edge between columns 4 and 5
    d[0, 0] = 0.0  # a hole: never a silhouette, nor does its 0 count as far
    d[4, 1] = 1.05  # 5 cm bump: below the 10 cm jump
    s = silhouettes(d, 0.1, 2)
    want = torch.zeros(5, 8, dtype=torch.bool)
    want[:, 3:5] = True  # near side, up to 2 pixels from the far pixels; the far side is not a silhouette
    assert torch.equal(s, want)
    assert torch.equal(silhouettes(d, 0.1, 1)[:, 4], torch.ones(5, dtype=torch.bool))
    assert not silhouettes(d, 0.1, 1)[:, 3].any()
    assert not silhouettes(d, 2.5, 2).any()  # a 2 m step is below a 2.5 m jump
    assert silhouettes(d, 0.01, 1)[3, 1]  # the 5 cm bump's neighbour is 5 cm nearer: above a 1 cm jump


def test_keyframe_edge_pixels_take_both_sides_or_the_near_side_only():
    from types import SimpleNamespace

    from inrslam.slam.frame_tensors import FrameTensors

    d = torch.full((4, 6), 1.0)
    d[:, 4:] = 3.0  # edge between columns 3 and 4
    ft = FrameTensors.__new__(FrameTensors)
    ft.intr, ft.depth = SimpleNamespace(height=4, width=6), d.reshape(-1)
    cols = lambda idx: sorted(set((idx % 6).tolist()))  # noqa: E731
    assert cols(ft.edge_pixels(0.05)) == [3, 4]
    assert cols(ft.edge_pixels(0.05, near_only=True)) == [3]
    assert ft.edge_pixels(2.5).numel() == 0


def test_per_ray_band_end_matches_the_scalar_one_ray_by_ray():
    g = torch.Generator().manual_seed(0)
    D = torch.rand(6, generator=g) + 1.0
    z = D[:, None] + (torch.rand(6, 20, generator=g) - 0.5) * 0.4
    behind = torch.tensor([1.0, 0.3, 0.0, 0.5, 1.0, 0.3])
    per_ray = sdf_masks(z, D, 0.1, 0.4, behind)
    for r in range(6):
        one = sdf_masks(z[r:r + 1], D[r:r + 1], 0.1, 0.4, float(behind[r]))
        assert all(torch.equal(a[r:r + 1], b) for a, b in zip(per_ray, one))
    # a sample 0.6 T behind its depth trains at band end 1, not at 0.3; None = cfg.behind for every ray
    z1, D1 = torch.tensor([[0.9, 1.0, 1.06]]), torch.tensor([1.0])
    for end, trained in ((1.0, True), (0.3, False)):
        sdf = torch.zeros(1, 3, requires_grad=True)
        out = RenderOutput(rgb=torch.zeros(1, 3), depth=D1, opacity=torch.ones(1), depth_var=torch.zeros(1),
                           weights=torch.zeros(1, 3), sdf=sdf, z=z1)
        compute_losses(out, torch.zeros(1, 3), D1, LossConfig(), 0.1, behind=torch.tensor([end]))["total"].backward()
        assert bool(sdf.grad[0, 2] != 0) is trained


def test_keyframe_store_keeps_band_ends_through_sampling_and_checkpoints():
    store = KeyframeStore()
    g = torch.Generator().manual_seed(1)
    for k in range(3):
        n = 50 + 10 * k
        store.add(k, torch.randn(n, 3), torch.rand(n, 3), torch.full((n,), float(k + 1)),
                  behind=torch.full((n,), 0.1 * (k + 1)))
    idx = store.sample_index(40, g)
    slot, _, _, depth = store.take(idx)
    assert torch.allclose(store.behind_of(idx), 0.1 * depth)  # each ray kept its own keyframe's value
    assert torch.equal(slot + 1, depth.long())
    copy = KeyframeStore()
    copy.load_state_dict(store.state_dict())
    assert torch.equal(copy.behind_of(idx), store.behind_of(idx))
    plain = KeyframeStore()
    plain.add(0, torch.randn(5, 3), torch.rand(5, 3), torch.ones(5))
    assert plain.behind_of(idx[:3].clamp_max(4)) is None and "behind" not in plain.state_dict()
    try:
        plain.add(1, torch.randn(5, 3), torch.rand(5, 3), torch.ones(5), behind=torch.ones(5))
    except ValueError as e:
        assert "every keyframe or for none" in str(e)
    else:
        raise AssertionError("mixing keyframes with and without band ends must fail")


def test_slam_gives_silhouette_rays_their_band_only_when_asked():
    def run(extra):
        cfg = load_config(preset="paper", overrides=TINY + extra)
        system = SlamSystem(cfg, open_dataset(cfg.data))
        for i in range(2):
            system.process(i)
        return system

    plain = run([])
    assert plain.store.behind is None
    sil = run(["loss.silhouette_behind=0.3", "loss.silhouette_radius=1"])
    b = sil.store.behind[: sil.store.n_rays]
    assert bool(((b == 0.3) | (b == 1.0)).all()) and bool((b == 0.3).any()) and bool((b == 1.0).any())
    frame = sil.dataset[0]
    want = silhouettes(torch.as_tensor(frame.depth, dtype=torch.float32), 0.1, 1)
    n0 = int((sil.store.slot[: sil.store.n_rays] == 0).sum())
    dirs = sil.store.dirs[:n0]
    u = torch.round(dirs[:, 0] * frame.intrinsics.fx + frame.intrinsics.cx).long()
    v = torch.round(dirs[:, 1] * frame.intrinsics.fy + frame.intrinsics.cy).long()
    assert torch.equal(b[:n0] == 0.3, want[v, u])  # exactly the silhouette pixels of keyframe 0
    # the shorter band changes the map (same seed, same rays otherwise)
    pa = torch.cat([p.detach().reshape(-1) for p in plain.model.field.parameters()])
    ps = torch.cat([p.detach().reshape(-1) for p in sil.model.field.parameters()])
    assert not torch.equal(pa, ps)
