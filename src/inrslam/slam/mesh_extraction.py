"""Mesh extraction: marching cubes on the field's SDF over the scene box (spec §8.5)."""

from __future__ import annotations

import numpy as np
import torch
import trimesh
from skimage import measure


@torch.no_grad()
def extract_mesh(field, bounds: np.ndarray, resolution: float = 0.02, chunk: int = 65536, color: bool = True) -> trimesh.Trimesh | None:
    """Marching cubes at SDF = 0 on a regular grid with `resolution` metres spacing inside `bounds`.

    Points per axis: round(L_a / resolution) + 1, both box ends included. Vertex colours are sigmoid(colour
    logits) of the field at the vertices. Returns None when the SDF has no zero crossing in the box.
    """
    bounds = np.asarray(bounds, dtype=np.float64)
    dev = next(iter(field.buffers()), torch.zeros(1)).device
    n = [int(round((b[1] - b[0]) / resolution + 0.0005)) + 1 for b in bounds]
    axes = [np.linspace(b[0], b[1], k) for b, k in zip(bounds, n)]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    pts = np.stack([gx, gy, gz], -1).reshape(-1, 3).astype(np.float32)
    sdf = np.empty(pts.shape[0], dtype=np.float32)
    for s in range(0, pts.shape[0], chunk):
        p = torch.from_numpy(pts[s:s + chunk]).to(dev)
        sdf[s:s + chunk] = field.sdf(p).float().cpu().numpy()
    vol = sdf.reshape(n)
    if not (np.nanmin(vol) < 0 < np.nanmax(vol)):
        return None
    spacing = tuple((b[1] - b[0]) / (k - 1) for b, k in zip(bounds, n))
    verts, faces, _, _ = measure.marching_cubes(vol, level=0.0, spacing=spacing)
    verts = verts + bounds[:, 0]
    # skimage orients faces toward increasing values (free space is positive): flip to face outward of the solid
    faces = faces[:, ::-1]
    colors = None
    if color and len(verts):
        cols = []
        for s in range(0, verts.shape[0], chunk):
            p = torch.from_numpy(verts[s:s + chunk].astype(np.float32)).to(dev)
            cols.append(torch.sigmoid(field(p).rgb_logits).float().cpu().numpy())
        c = np.concatenate(cols)
        colors = np.concatenate([(c * 255).clip(0, 255).astype(np.uint8), np.full((len(c), 1), 255, np.uint8)], 1)
    return trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colors, process=False)
