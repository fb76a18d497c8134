"""Top-down picture of a run's trajectory: estimate and ground truth, the estimate coloured by its position error."""

from __future__ import annotations

import os

import numpy as np


def plane_axes(positions: np.ndarray) -> tuple[int, int]:
    """The two world axes along which (N, 3) positions spread most (a top-down view whatever axis is up)."""
    spread = np.nanstd(positions, axis=0)
    a, b = sorted(np.argsort(spread)[-2:].tolist())
    return a, b


def plot_trajectory(est: np.ndarray, gt: np.ndarray, path: str | os.PathLike, title: str = "") -> None:
    """Write a PNG: ground truth (grey) and the estimate coloured by |t_est - t_gt| (cm, unaligned: both start at
    the same pose), seen along the axis of least motion.

    Args: est, gt: (N, 4, 4) camera-to-world, metres (gt NaN where unknown); path: the PNG to write.
    """
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    from inrslam.io.atomic import atomic_path

    te, tg = est[:, :3, 3], gt[:, :3, 3]
    ok = np.isfinite(te).all(axis=1) & np.isfinite(tg).all(axis=1)
    a, b = plane_axes(tg[ok] if ok.any() else te)
    err_cm = np.linalg.norm(te - tg, axis=1) * 100.0
    fig, ax = plt.subplots(figsize=(5.5, 5), dpi=110)
    ax.plot(tg[ok, a], tg[ok, b], color="0.6", lw=2.5, label="ground truth", zorder=1)
    sc = ax.scatter(te[ok, a], te[ok, b], c=err_cm[ok], cmap="viridis", s=9, zorder=2, label="estimate")
    fig.colorbar(sc, ax=ax, label="position error [cm]", shrink=0.8)
    if ok.any():
        ax.plot(*tg[ok][0, [a, b]], "k^", ms=8, label="start", zorder=3)
        title = title or f"largest position error {np.max(err_cm[ok]):.2f} cm"
    ax.set_xlabel("xyz"[a] + " [m]")
    ax.set_ylabel("xyz"[b] + " [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title)
    ax.legend(loc="upper left", bbox_to_anchor=(1.25, 1.0), fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
