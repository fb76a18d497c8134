"""Depth-edge pixels in the keyframe ray store (`slam.keyframe_edge_fraction`): the silhouettes where held-out depth
errs most get rays of their own."""

from __future__ import annotations

import torch

from inrslam.config import load_config
from inrslam.datasets import open_dataset
from inrslam.slam.frame_tensors import depth_edges
from inrslam.slam.system import SlamSystem

TINY = ["data.max_frames=1", "data.builtin.width=96", "data.builtin.height=72", "slam.init_iters=2",
        "mesh.enabled=false", "eval.enabled=false", "output.tensorboard=false"]


def test_depth_edges_mark_both_sides_of_a_step_and_ignore_holes():
    d = torch.ones(4, 6)
    d[:, 4:] = 2.0  # a 1 m step between columns 3 and 4
    d[1, 1] = 0.0  # a hole is not an edge, nor are its neighbours
    d[3, 0] = 1.03  # a 3 cm bump is below the 5 cm jump
    e = depth_edges(d, 0.05)
    want = torch.zeros(4, 6, dtype=torch.bool)
    want[:, 3:5] = True
    assert torch.equal(e, want)
    assert depth_edges(d, 0.01)[3, 0] and depth_edges(d, 0.01)[2, 0]  # ... but above a 1 cm one


def test_keyframe_store_takes_edge_pixels_only_when_asked():
    def first_keyframe(extra):
        cfg = load_config(preset="paper", overrides=TINY + extra)
        system = SlamSystem(cfg, open_dataset(cfg.data))
        system.process(0)
        return system

    plain = first_keyframe([])
    n = round(0.05 * 96 * 72)
    assert plain.store.n_rays == n
    edged = first_keyframe(["slam.keyframe_edge_fraction=0.02"])
    m = round(0.02 * 96 * 72)
    assert edged.store.n_rays == n + m
    # the random part is the same rays; the extra ones lie on depth edges of frame 0
    assert torch.equal(edged.store.depth[:n], plain.store.depth[:n])
    frame = edged.dataset[0]
    edges = depth_edges(torch.as_tensor(frame.depth, dtype=torch.float32), 0.05)
    W = frame.intrinsics.width
    dirs = edged.store.dirs[n:n + m]
    u = torch.round(dirs[:, 0] * frame.intrinsics.fx + frame.intrinsics.cx).long()
    v = torch.round(dirs[:, 1] * frame.intrinsics.fy + frame.intrinsics.cy).long()
    assert bool(edges.reshape(-1)[v * W + u].all())
    depth = torch.as_tensor(frame.depth, dtype=torch.float32).reshape(-1)
    assert torch.equal(edged.store.depth[n:n + m], depth[v * W + u])
