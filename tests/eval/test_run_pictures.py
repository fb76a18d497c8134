"""The pictures of a run directory: the held-out panel (observed | rendered | depth | error) and the trajectory
plot, on analytic inputs."""

from __future__ import annotations

import numpy as np
from matplotlib import colormaps

from inrslam.eval.heldout import DEPTH_ERROR_MAX, heldout_panel


def test_panel_layout_scales_and_masks():
    rng = np.random.default_rng(7)
    H, W = 6, 5
    gt_rgb, rgb = rng.random((H, W, 3)), rng.random((H, W, 3))
    gt_depth = np.full((H, W), 2.0)
    gt_depth[0, 0] = 0.0  # no measurement
    gt_depth[1, 1] = 4.0  # the largest observed depth: top of the depth scale
    depth = gt_depth.copy()
    depth[2, 2] += DEPTH_ERROR_MAX  # an error at the top of the error scale
    depth[3, 3] += DEPTH_ERROR_MAX / 2
    p = heldout_panel(gt_rgb, rgb, depth, gt_depth)
    assert p.shape == (H, 4 * W, 3) and p.dtype == np.uint8
    to8 = lambda x: (np.asarray(x) * 255 + 0.5).astype(np.uint8)  # noqa: E731
    assert np.array_equal(p[:, :W], to8(gt_rgb)) and np.array_equal(p[:, W:2 * W], to8(rgb))
    depth_panel, err_panel = p[:, 2 * W:3 * W], p[:, 3 * W:]
    assert np.array_equal(depth_panel[1, 1], to8(colormaps["turbo"](1.0)[:3]))
    assert np.array_equal(depth_panel[4, 4], to8(colormaps["turbo"](0.5)[:3]))  # 2 m of 4 m
    assert np.array_equal(err_panel[2, 2], to8(colormaps["magma"](1.0)[:3]))
    half = abs(depth[3, 3] - gt_depth[3, 3]) / DEPTH_ERROR_MAX  # 0.5 up to rounding
    assert abs(half - 0.5) < 1e-9 and np.array_equal(err_panel[3, 3], to8(colormaps["magma"](half)[:3]))
    assert np.array_equal(err_panel[4, 4], to8(colormaps["magma"](0.0)[:3]))  # exact depth: bottom of the scale
    assert not err_panel[0, 0].any()  # unmeasured pixel: black


def test_trajectory_plot_looks_down_the_axis_of_least_motion(tmp_path):
    from inrslam.eval.trajectory_plot import plane_axes, plot_trajectory

    t = np.linspace(0, 2 * np.pi, 40)
    pos = np.stack([np.cos(t), 0.01 * np.sin(3 * t), 2 * np.sin(t)], axis=1)  # a loop in x-z, y nearly still
    assert plane_axes(pos) == (0, 2)
    gt = np.tile(np.eye(4), (40, 1, 1))
    gt[:, :3, 3] = pos
    est = gt.copy()
    est[:, 0, 3] += 0.01
    est[5] = np.nan  # an unprocessed frame is left out
    plot_trajectory(est, gt, tmp_path / "t.png")
    from PIL import Image

    img = np.asarray(Image.open(tmp_path / "t.png").convert("L"))
    assert img.std() > 5  # something drawn
