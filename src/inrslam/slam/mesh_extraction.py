"""Mesh extraction: marching cubes on the field's SDF over the scene box (docs/spec.md §8.5)."""

from __future__ import annotations

import itertools

import numpy as np
import torch
import trimesh
from skimage import measure


def _module_device(module) -> torch.device:
    """Device of the module's first parameter or buffer (CPU for a module with neither)."""
    for t in itertools.chain(module.parameters(), module.buffers()):
        return t.device
    return torch.device("cpu")


@torch.no_grad()
def sdf_volume(field, axes: list[np.ndarray], chunk: int = 65536, device: torch.device | None = None) -> np.ndarray:
    """Field SDF on the grid axes[0] x axes[1] x axes[2] ('ij' order) as a float32 (nx, ny, nz) array.

    The query points are built one x-slab (as many x-slices as fit in `chunk` points, at least one) at a time and
    sent to the field in batches of at most `chunk` points, so the extra memory is O(slab), not O(grid): only the
    output volume is allocated at full size.
    """
    device = _module_device(field) if device is None else device
    nx, ny, nz = (len(a) for a in axes)
    vol = np.empty((nx, ny, nz), dtype=np.float32)
    flat = vol.reshape(-1)  # a view: writes land in vol
    plane = ny * nz
    slab = max(1, chunk // max(plane, 1))
    yz = np.empty((ny, nz, 2), dtype=np.float32)
    yz[..., 0] = axes[1][:, None]
    yz[..., 1] = axes[2][None, :]
    for i0 in range(0, nx, slab):
        i1 = min(i0 + slab, nx)
        pts = np.empty((i1 - i0, ny, nz, 3), dtype=np.float32)
        pts[..., 0] = axes[0][i0:i1, None, None]
        pts[..., 1:] = yz
        rows = pts.reshape(-1, 3)
        base = i0 * plane
        for s in range(0, rows.shape[0], chunk):
            p = torch.from_numpy(rows[s:s + chunk]).to(device)
            flat[base + s:base + s + p.shape[0]] = field.sdf(p).float().cpu().numpy()
    return vol


@torch.no_grad()
def extract_mesh(field, bounds: np.ndarray, resolution: float = 0.02, chunk: int = 65536,
                 color: bool = True) -> trimesh.Trimesh | None:
    """Marching cubes at SDF = 0 on a regular grid with `resolution` metres spacing inside `bounds`.

    Points per axis: round(L_a / resolution) + 1, both box ends included. Faces are oriented outward of the solid
    (normals point from negative SDF towards positive, i.e. into free space), which is how skimage orders them.
    Vertex colours are sigmoid(colour logits) of the field at the vertices. The field is queried on the device of
    its first parameter or buffer (CPU if it has none). Returns None when the SDF has no zero crossing in the box.
    """
    bounds = np.asarray(bounds, dtype=np.float64)
    dev = _module_device(field)
    n = [int(round((b[1] - b[0]) / resolution + 0.0005)) + 1 for b in bounds]
    axes = [np.linspace(b[0], b[1], k) for b, k in zip(bounds, n)]
    vol = sdf_volume(field, axes, chunk, dev)
    if not (np.nanmin(vol) < 0 < np.nanmax(vol)):
        return None
    spacing = tuple((b[1] - b[0]) / (k - 1) for b, k in zip(bounds, n))
    verts, faces, _, _ = measure.marching_cubes(vol, level=0.0, spacing=spacing)
    verts = verts + bounds[:, 0]
    colors = None
    if color and len(verts):
        cols = []
        for s in range(0, verts.shape[0], chunk):
            p = torch.from_numpy(verts[s:s + chunk].astype(np.float32)).to(dev)
            cols.append(torch.sigmoid(field(p).rgb_logits).float().cpu().numpy())
        c = np.concatenate(cols)
        colors = np.concatenate([(c * 255).clip(0, 255).astype(np.uint8), np.full((len(c), 1), 255, np.uint8)], 1)
    return trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colors, process=False)
