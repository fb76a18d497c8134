"""A small picture of a triangle mesh (a run directory's `mesh.png`): a numpy software rasteriser, no GPU, no files.

Orthographic view from 60 degrees above the horizontal of the world's up axis (the viewer's overview direction);
back faces are culled, so the ceiling and the near walls of a room (their normals point into the room, away from
the viewer outside) drop out and the inside shows. Triangles are rasterised at pixel centres with a z-buffer;
colours are the vertex colours interpolated across each triangle, times a Lambert shade of the face.
"""

from __future__ import annotations

import math

import numpy as np

from inrslam.errors import DataError

THUMBNAIL_SIZE = (480, 360)  # (width, height) pixels of mesh.png
ELEVATION_DEG = 60.0  # view direction above the horizontal of the up axis
BACKGROUND = (44, 48, 56)  # dark slate: light walls and floors stand out
DEFAULT_COLOR = (0.72, 0.72, 0.72)  # meshes without vertex colours
AMBIENT = 0.35  # shade of a face seen edge-on; 1 for a face lit head-on
MARGIN = 0.04  # empty border, fraction of the picture's size
_FRAGMENTS_PER_CHUNK = 1 << 20  # candidate pixels tested at once (bounds the temporaries to about 100 MB)


def up_direction(poses: np.ndarray) -> np.ndarray:
    """The world axis (+-x, +-y, +-z as a (3,) unit vector) closest to the cameras' mean up direction (-y of each
    camera in OpenCV axes); +z without a finite pose.

    Args: poses: (N, 4, 4) camera-to-world (rows with a NaN are ignored).
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    p = p[np.isfinite(p.reshape(len(p), -1)).all(axis=1)]
    up = -p[:, :3, 1].mean(axis=0) if len(p) else np.array([0.0, 0.0, 1.0])
    axis = int(np.argmax(np.abs(up)))
    out = np.zeros(3)
    out[axis] = 1.0 if up[axis] >= 0 or not np.isfinite(up[axis]) else -1.0
    return out


def horizontal_direction(up: np.ndarray) -> np.ndarray:
    """A (3,) unit vector perpendicular to `up`: the sum of the two other world axes for an axis-aligned up (the
    diagonal of a room's floor plan), made perpendicular for any other."""
    up = _unit(up, "up")
    flat = np.ones(3) - np.abs(up)
    flat = flat - up * float(flat @ up)
    if np.linalg.norm(flat) < 1e-9:  # cannot happen for a unit `up`, kept for safety
        flat = np.eye(3)[int(np.argmin(np.abs(up)))]
    return flat / np.linalg.norm(flat)


def view_direction(up: np.ndarray, elevation_deg: float = ELEVATION_DEG) -> np.ndarray:
    """(3,) unit vector from the scene towards the viewer: `elevation_deg` above the horizontal of `up`."""
    el = math.radians(elevation_deg)
    return math.cos(el) * horizontal_direction(up) + math.sin(el) * _unit(up, "up")


def view_basis(up: np.ndarray, elevation_deg: float = ELEVATION_DEG) -> np.ndarray:
    """(3, 3) rows right, image-up, forward (into the screen) of the orthographic view; right stays horizontal."""
    up = _unit(up, "up")
    toward = view_direction(up, elevation_deg)
    right = np.cross(up, horizontal_direction(up))
    return np.stack([right, np.cross(toward, right), -toward])


def rasterise(xy: np.ndarray, depth: np.ndarray, faces: np.ndarray, colors: np.ndarray, shade: np.ndarray,
              size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffered triangles, sampled at pixel centres (pixel (col, row) covers [col, col+1) x [row, row+1)).

    Args:
        xy: (V, 2) vertex positions in pixels (x right, y down); depth: (V,) larger = farther.
        faces: (F, 3) vertex indices; colors: (V, 3) in [0, 1]; shade: (F,) factor on the face's colours.
        size: (width, height).
    Returns:
        rgb (H, W, 3) float in [0, 1] (0 where nothing is drawn) and face (H, W) int64: the visible face, -1 for
        none. A pixel centre on an edge belongs to both triangles; the nearer one (then the lower index) wins.
    """
    W, H = int(size[0]), int(size[1])
    rgb = np.zeros((H, W, 3))
    face_buf = np.full(H * W, -1, dtype=np.int64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(faces):
        return rgb, face_buf.reshape(H, W)
    tri = np.asarray(xy, dtype=np.float64)[faces]  # (F, 3, 2)
    lo = np.clip(np.ceil(tri.min(axis=1) - 0.5), 0, [W, H]).astype(np.int64)  # first pixel centre inside the box
    hi = np.clip(np.floor(tri.max(axis=1) - 0.5), -1, [W - 1, H - 1]).astype(np.int64)
    span = hi - lo + 1  # pixels of the box along x and y
    side = span.max(axis=1)
    area = ((tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1])
            - (tri[:, 2, 0] - tri[:, 0, 0]) * (tri[:, 1, 1] - tri[:, 0, 1]))
    keep = (span.min(axis=1) > 0) & (area != 0)
    z = np.asarray(depth, dtype=np.float64)[faces]  # (F, 3)
    pix, zs, fid, bary = [], [], [], []
    box = 1
    while keep.any():  # boxes of up to box x box pixels together: 1, 2, 4, ... (most triangles cover a pixel or two)
        sel = np.flatnonzero(keep & (side <= box))
        keep[sel] = False
        oy, ox = np.divmod(np.arange(box * box), box)
        step = max(1, _FRAGMENTS_PER_CHUNK // (box * box))
        for s in range(0, len(sel), step):
            f = sel[s: s + step]
            px, py = lo[f, 0:1] + ox, lo[f, 1:2] + oy  # (n, box^2) candidate pixels
            cx, cy = px + 0.5, py + 0.5
            t = tri[f]
            x0, y0, x1, y1, x2, y2 = (t[:, k, c][:, None] for k in range(3) for c in range(2))
            w0 = ((x1 - cx) * (y2 - cy) - (x2 - cx) * (y1 - cy)) / area[f, None]
            w1 = ((x2 - cx) * (y0 - cy) - (x0 - cx) * (y2 - cy)) / area[f, None]
            w2 = 1.0 - w0 - w1
            eps = -1e-9  # pixel centres on a shared edge: covered by both triangles, never by neither
            inside = (px <= hi[f, 0:1]) & (py <= hi[f, 1:2]) & (w0 >= eps) & (w1 >= eps) & (w2 >= eps)
            rows, cols = np.nonzero(inside)
            pix.append(py[rows, cols] * W + px[rows, cols])
            zs.append(w0[rows, cols] * z[f[rows], 0] + w1[rows, cols] * z[f[rows], 1] + w2[rows, cols] * z[f[rows], 2])
            fid.append(f[rows])
            bary.append(np.stack([w0[rows, cols], w1[rows, cols], w2[rows, cols]], axis=1))
        box *= 2
    if not pix:
        return rgb, face_buf.reshape(H, W)
    pix_a, z_a, fid_a, bary_a = np.concatenate(pix), np.concatenate(zs), np.concatenate(fid), np.concatenate(bary)
    order = np.lexsort((fid_a, z_a, pix_a))  # per pixel: nearest first, ties to the lower face index
    first = order[np.r_[True, pix_a[order][1:] != pix_a[order][:-1]]]
    won_pix, won_face, w = pix_a[first], fid_a[first], np.clip(bary_a[first], 0.0, 1.0)
    col = np.einsum("nk,nkc->nc", w, np.asarray(colors, dtype=np.float64)[faces[won_face]])
    rgb.reshape(-1, 3)[won_pix] = np.clip(col * np.asarray(shade, dtype=np.float64)[won_face, None], 0.0, 1.0)
    face_buf[won_pix] = won_face
    return rgb, face_buf.reshape(H, W)


def mesh_thumbnail(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None,
                   up: np.ndarray | tuple = (0.0, 0.0, 1.0), size: tuple[int, int] = THUMBNAIL_SIZE,
                   elevation_deg: float = ELEVATION_DEG) -> np.ndarray:
    """The mesh seen from `elevation_deg` above the horizontal of `up`, fitted into the picture.

    Args:
        vertices: (V, 3) metres; faces: (F, 3) vertex indices, counter-clockwise seen from the side the normal
            points to (marching cubes: into free space), which is the side drawn.
        colors: (V, 3) or (V, 4) vertex colours, uint8 0..255 or float 0..1 (alpha ignored); None: light grey.
        up: (3,) the world's up direction (`up_direction` of the cameras); size: (width, height) pixels.
    Returns:
        (H, W, 3) uint8, BACKGROUND where no front face is seen. Faces with a non-finite vertex are left out.
    Raises:
        DataError (one line) for arrays of the wrong shape, face indices out of range or a zero `up`.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3:
        raise DataError(f"mesh thumbnail: vertices must be (V, 3), got shape {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or (F.size and not np.issubdtype(F.dtype, np.integer)):
        raise DataError(f"mesh thumbnail: faces must be (F, 3) integer vertex indices, got shape {F.shape} "
                        f"of {F.dtype}")
    if F.size and (F.min() < 0 or F.max() >= len(V)):
        raise DataError(f"mesh thumbnail: face indices must lie in 0..{len(V) - 1}, got {F.min()}..{F.max()}")
    W, H = int(size[0]), int(size[1])
    if W < 1 or H < 1:
        raise DataError(f"mesh thumbnail: size must be positive (width, height), got {size}")
    cols = _colors(colors, len(V))
    basis = view_basis(np.asarray(up, dtype=np.float64), elevation_deg)
    finite = np.asarray(np.isfinite(V).all(axis=1))
    F = F.astype(np.int64)
    F = F[finite[F].all(axis=1)]
    picture = np.empty((H, W, 3))
    picture[:] = np.asarray(BACKGROUND) / 255.0
    if len(F):
        normal = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        toward = -basis[2]
        front = normal @ toward > 0
        F, normal = F[front], normal[front]
    if len(F):
        cam = V @ basis.T  # (V, 3): right, image-up, depth
        used = np.unique(F)
        lo, hi = cam[used, :2].min(axis=0), cam[used, :2].max(axis=0)
        scale = min((W * (1 - 2 * MARGIN)) / max(hi[0] - lo[0], 1e-12), (H * (1 - 2 * MARGIN)) / max(hi[1] - lo[1],
                                                                                                         1e-12))
        mid = (lo + hi) / 2.0
        xy = np.stack([(cam[:, 0] - mid[0]) * scale + W / 2.0, H / 2.0 - (cam[:, 1] - mid[1]) * scale], axis=1)
        light = _unit(toward + 0.35 * basis[0] + 0.35 * basis[1], "light")  # a little from the upper right
        unit_n = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
        shade = AMBIENT + (1.0 - AMBIENT) * np.abs(unit_n @ light)
        rgb, face = rasterise(xy, cam[:, 2], F, cols, shade, (W, H))
        drawn = face >= 0
        picture[drawn] = rgb[drawn]
    return (picture * 255.0 + 0.5).astype(np.uint8)


def _colors(colors, n: int) -> np.ndarray:
    """(n, 3) float colours in [0, 1] from uint8 / float, RGB / RGBA, or None (grey)."""
    if colors is None:
        return np.tile(np.asarray(DEFAULT_COLOR, dtype=np.float64), (n, 1))
    c = np.asarray(colors)
    if c.ndim != 2 or c.shape[0] != n or c.shape[1] not in (3, 4):
        raise DataError(f"mesh thumbnail: colours must be ({n}, 3) or ({n}, 4), got shape {c.shape}")
    c = c[:, :3].astype(np.float64)
    return c / 255.0 if np.issubdtype(np.asarray(colors).dtype, np.integer) else np.clip(c, 0.0, 1.0)


def _unit(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(v))
    if not math.isfinite(n) or n == 0.0:
        raise DataError(f"mesh thumbnail: {name} direction must be a finite non-zero (3,) vector, got {v.tolist()}")
    return v / n
