"""Mesh evaluation: ray casting (trimesh, embree when available), frustum + occlusion culling, Acc/Comp/Comp%, ICP.

Cameras are camera-to-world (4, 4) in OpenCV axes (x right, y down, z forward), metres; a pixel (u, v) has its
centre at integer coordinates and its ray d = ((u − cx)/fx, (v − cy)/fy, 1) in the camera frame, so the ray
parameter of a hit *is* its z-depth.

Ray casting is naturally double-sided: a ray reports the nearest triangle it crosses whatever the triangle's
winding / normal. That is exactly the reference's "render with original and flipped winding and keep the nearest
depth" (docs/spec.md §8.6 step 2), without rendering twice.

No I/O here: meshes come in as `trimesh.Trimesh`, results go out as arrays, meshes and dicts.

References:
    Azinović et al., "Neural RGB-D Surface Reconstruction", CVPR 2022 (frustum + occlusion culling);
    Wang, Bleja, Agapito, "GO-Surf", 3DV 2022; Zhu et al., "NICE-SLAM", CVPR 2022 and Wang et al., "Co-SLAM",
    CVPR 2023 (`neural_slam_eval`: Acc / Comp / Comp% on 200 k area-weighted surface samples, 5 cm threshold);
    Besl & McKay, "A method for registration of 3-D shapes", TPAMI 1992 (point-to-point ICP).
"""

from __future__ import annotations

import importlib.util
from typing import Optional

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from inrslam.eval.trajectory import align_umeyama, sim3_matrix
from inrslam.geometry.intrinsics import Intrinsics
from inrslam.geometry.pinhole import pixel_directions_np, project_np

# ----------------------------------------------------------------------------------------------------------------
# ray casting


def has_embree() -> bool:
    """True when trimesh can use Intel Embree (package `embreex`) for ray casting."""
    return bool(getattr(trimesh.ray, "has_embree", False))


def ray_intersector(mesh: trimesh.Trimesh):
    """A trimesh ray intersector for `mesh`: Embree when available, else trimesh's pure-numpy one (much slower).

    Raises ImportError naming the fix when neither `embreex` nor `rtree` (needed by the numpy fallback) is installed.
    """
    if has_embree():
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    if importlib.util.find_spec("rtree") is None:
        raise ImportError(
            "mesh ray casting (culling, depth rendering) needs Embree: pip install 'inrslam[embree]' (embreex); "
            "trimesh's slow fallback would need the 'rtree' package, which is not installed either"
        )
    from trimesh.ray.ray_triangle import RayMeshIntersector  # type: ignore[assignment]  # the fallback, same name

    return RayMeshIntersector(mesh)


def _ray_params(mesh: trimesh.Trimesh, origins: np.ndarray, dirs: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Ray parameter t of the intersection of ray (o + t d) with the plane of triangle `tri` (float64, exact).

    t = ((p0 − o) · n) / (d · n), p0 a triangle corner, n its normal; NaN for a degenerate / parallel triangle.
    """
    n = mesh.face_normals[tri]
    p0 = mesh.triangles[tri, 0]
    den = np.einsum("ij,ij->i", dirs, n)
    num = np.einsum("ij,ij->i", p0 - origins, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / den
    t[~np.isfinite(t) | (np.abs(den) < 1e-15)] = np.nan
    return t


def cast_rays(
    mesh: trimesh.Trimesh,
    origins: np.ndarray,
    dirs: np.ndarray,
    double_sided: bool = True,
    intersector=None,
) -> np.ndarray:
    """Nearest hit of each ray o + t d (t > 0) with the mesh.

    Args:
        mesh: triangle mesh.
        origins: (N, 3) metres.  dirs: (N, 3), any non-zero length (t is measured in units of |d|).
        double_sided: True (default) = any face counts (ray casting is double-sided by nature); False = only faces
            whose normal points towards the ray origin (d · n < 0) can be hit, back faces are transparent.
        intersector: optional prebuilt `ray_intersector(mesh)` to reuse across calls.
    Returns:
        (N,) float64 ray parameter t of the nearest hit, +inf where the ray hits nothing.
    """
    origins = np.ascontiguousarray(origins, dtype=np.float64)
    dirs = np.ascontiguousarray(dirs, dtype=np.float64)
    n = origins.shape[0]
    out = np.full(n, np.inf)
    if n == 0 or len(mesh.faces) == 0:
        return out
    isect = intersector if intersector is not None else ray_intersector(mesh)
    if double_sided:
        tri, ray = isect.intersects_id(origins, dirs, multiple_hits=False)[:2]
    else:
        tri, ray = isect.intersects_id(origins, dirs, multiple_hits=True)[:2]
        front = np.einsum("ij,ij->i", dirs[ray], mesh.face_normals[tri]) < 0
        tri, ray = tri[front], ray[front]
    tri = np.asarray(tri, dtype=np.int64)
    ray = np.asarray(ray, dtype=np.int64)
    t = _ray_params(mesh, origins[ray], dirs[ray], tri)
    ok = np.isfinite(t) & (t > 0)
    np.minimum.at(out, ray[ok], t[ok])
    return out


def pixel_rays(c2w: np.ndarray, intr: Intrinsics, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World rays through pixels (u, v) (OpenCV, centres at integers); dirs have camera-frame z = 1.

    Returns origins (N, 3) and directions (N, 3) = R ((u − cx)/fx, (v − cy)/fy, 1).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    d = pixel_directions_np(intr.fx, intr.fy, intr.cx, intr.cy, u, v)
    dirs = d @ c2w[:3, :3].T
    origins = np.broadcast_to(c2w[:3, 3], dirs.shape).copy()
    return origins, dirs


def render_mesh_depth(
    mesh: trimesh.Trimesh, c2w: np.ndarray, intrinsics: Intrinsics, double_sided: bool = True, intersector=None
) -> np.ndarray:
    """Z-depth image of a mesh by ray casting one ray per pixel centre.

        D(v, u) = z of the nearest intersection of the ray through (u, v),  0 where the ray hits nothing.

    Args:
        mesh: triangle mesh, metres.
        c2w: (4, 4) camera-to-world, OpenCV axes.
        intrinsics: pinhole intrinsics (image size width x height).
        double_sided: nearest hit regardless of face orientation (default; matches the reference's two-pass
            double-sided rasterisation). False: back faces are invisible.
        intersector: optional prebuilt `ray_intersector(mesh)`.
    Returns:
        (H, W) float64 z-depth in metres, 0 = no hit.
    """
    H, W = intrinsics.height, intrinsics.width
    v, u = np.mgrid[0:H, 0:W]
    o, d = pixel_rays(c2w, intrinsics, u.ravel(), v.ravel())
    t = cast_rays(mesh, o, d, double_sided=double_sided, intersector=intersector)
    t[~np.isfinite(t)] = 0.0
    return t.reshape(H, W)


# ----------------------------------------------------------------------------------------------------------------
# culling


def visibility_counts(
    vertices: np.ndarray,
    c2ws: np.ndarray,
    intrinsics: Intrinsics,
    mesh: Optional[trimesh.Trimesh] = None,
    eps: float = 0.03,
    intersector=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex count of cameras that have it in their frustum, and that observe it (not occluded).

    For vertex X and camera (R, c): x = Rᵀ(X − c), u = fx x/z + cx, v = fy y/z + cy;
        in frustum  ⇔  z > 0, 0 ≤ u ≤ W − 1, 0 ≤ v ≤ H − 1;
        observed    ⇔  in frustum and z < D(round(v), round(u)) + eps,
    with D the (double-sided) z-depth of `mesh` rendered from that camera (a pixel without hit counts as
    infinitely far). Only the pixels some in-frustum vertex falls on are ray cast — identical to rendering the
    full depth map and reading it, but cheaper. Cameras with non-finite poses are skipped.

    Args:
        vertices: (V, 3) metres.  c2ws: (N, 4, 4) OpenCV camera-to-world.  intrinsics: image size and K.
        mesh: occluding mesh; None = frustum test only (observed count = in-frustum count).
        eps: metres, occlusion tolerance.
    Returns:
        in_frustum_count (V,) int, observed_count (V,) int.
    """
    X = np.asarray(vertices, dtype=np.float64)
    H, W = intrinsics.height, intrinsics.width
    n_in = np.zeros(len(X), dtype=np.int64)
    n_obs = np.zeros(len(X), dtype=np.int64)
    if mesh is not None and intersector is None and len(mesh.faces):
        intersector = ray_intersector(mesh)
    for c2w in np.asarray(c2ws, dtype=np.float64).reshape(-1, 4, 4):
        if not np.all(np.isfinite(c2w)):
            continue
        R, c = c2w[:3, :3], c2w[:3, 3]
        u, v, z = project_np((X - c) @ R, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
        inside = (z > 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        idx = np.nonzero(inside)[0]
        if idx.size == 0:
            continue
        n_in[idx] += 1
        if mesh is None:
            n_obs[idx] += 1
            continue
        ui = np.rint(u[idx]).astype(np.int64)
        vi = np.rint(v[idx]).astype(np.int64)
        pix, inv = np.unique(vi * W + ui, return_inverse=True)
        o, d = pixel_rays(c2w, intrinsics, pix % W, pix // W)
        depth = cast_rays(mesh, o, d, double_sided=True, intersector=intersector)
        obs = z[idx] < depth[inv.ravel()] + eps
        n_obs[idx[obs]] += 1
    return n_in, n_obs


GT_CULL_MAX_EDGE = 0.05
"""Metres: `--cull-gt` splits ground-truth triangles to at most this edge length before culling (GT meshes often model
a wall as two triangles). The kept GT then overshoots the seen region by less than one such edge."""


def subdivide_to_edge(mesh: trimesh.Trimesh, max_edge: float) -> trimesh.Trimesh:
    """`mesh` with every triangle that has an edge longer than `max_edge` (m) split into four, repeatedly, until none
    has (`trimesh.remesh.subdivide_to_size`). Returns `mesh` itself when no edge is longer; vertex colours are not
    carried over to a split mesh (the metrics use geometry only)."""
    if max_edge <= 0:
        raise ValueError(f"subdivide_to_edge: max_edge must be > 0, got {max_edge}")
    if len(mesh.faces) == 0:
        return mesh
    longest = float(mesh.edges_unique_length.max())
    if longest <= max_edge:
        return mesh
    iters = int(np.ceil(np.log2(longest / max_edge))) + 2
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge, max_iter=iters)
    return trimesh.Trimesh(v, f, process=False)


def cull_mesh(
    mesh: trimesh.Trimesh,
    c2ws: np.ndarray,
    intrinsics: Intrinsics,
    every: int = 2,
    eps: float = 0.03,
    occlusion: bool = True,
) -> trimesh.Trimesh:
    """Remove the parts of a mesh no camera saw: frustum + occlusion culling (Neural-RGBD / GO-Surf, docs/spec.md §8.6).

    1. cameras c2ws[::every] (ground-truth poses in the benchmark; non-finite ones skipped);
    2. per vertex, count cameras with it in frustum and cameras observing it (`visibility_counts`, occluder =
       the mesh itself, ray cast double-sided, eps tolerance);
    3. keep a face iff (some vertex has in-frustum count > 0) and (some vertex has observed count > 0);
    4. drop unreferenced vertices (vertex colours follow).
    Visibility is decided per vertex, so a large triangle whose corners no camera sees goes although its middle is
    seen: split such meshes first (`subdivide_to_edge`; `--cull-gt` does so for the GT mesh).
    With `occlusion=False` only the frustum test is applied. The Co-SLAM "virtual camera" variant is the same
    with extra (virtual) poses appended to `c2ws` (`EvalConfig.virtual_cameras`, `inrslam.eval.run.culling_cameras`).

    Args:
        mesh: mesh to cull (not modified), metres.
        c2ws: (N, 4, 4) camera-to-world, OpenCV axes.
        intrinsics: pinhole intrinsics of the cameras.
        every: use every n-th camera (reference: `--skip 2`).
        eps: metres, occlusion tolerance (reference: 0.03).
        occlusion: also remove faces hidden behind other surfaces (reference: `--remove_occlusion`).
    Returns:
        a new culled `trimesh.Trimesh` (possibly empty).
    """
    if every < 1:
        raise ValueError(f"cull_mesh: every must be >= 1, got {every}")
    cams = np.asarray(c2ws, dtype=np.float64).reshape(-1, 4, 4)[::every]
    n_in, n_obs = visibility_counts(mesh.vertices, cams, intrinsics, mesh if occlusion else None, eps)
    faces = np.asarray(mesh.faces)
    keep = (n_in[faces] > 0).any(1) & (n_obs[faces] > 0).any(1)
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out


# ----------------------------------------------------------------------------------------------------------------
# ICP and 3-D metrics


def icp_point_to_point(
    src: np.ndarray,
    dst: np.ndarray,
    max_corr: float = 0.1,
    max_iter: int = 30,
    init: Optional[np.ndarray] = None,
    rel_tol: float = 1e-6,
) -> tuple[np.ndarray, dict]:
    """Rigid point-to-point ICP (Besl & McKay 1992) aligning `src` onto `dst`, as Open3D's default registration.

    Iterate: y_i = nearest dst point of T x_i; keep pairs with |T x_i − y_i| < max_corr; T ← Umeyama(T x, y) · T
    (rotation + translation, no scale). Stops after `max_iter` iterations or when both the fitness (inlier
    fraction) and the inlier RMSE change by less than `rel_tol` (relative), Open3D's convergence rule.

    Args:
        src: (N, 3), dst: (M, 3) points, metres.
        max_corr: metres, maximum correspondence distance.
        init: (4, 4) initial transform (identity by default).
    Returns:
        T (4, 4) mapping src into dst's frame, and {"fitness", "inlier_rmse", "iterations"} (fitness and inlier
        RMSE of the returned T).
    """
    src = np.asarray(src, dtype=np.float64)
    tree = cKDTree(np.asarray(dst, dtype=np.float64))
    T = np.eye(4) if init is None else np.asarray(init, dtype=np.float64).copy()
    fitness = rmse = 0.0
    it = 0
    for it in range(1, max_iter + 1):
        x = src @ T[:3, :3].T + T[:3, 3]
        d, j = tree.query(x, distance_upper_bound=max_corr)
        ok = np.isfinite(d)
        if ok.sum() < 3:
            break
        new_fit = ok.mean()
        new_rmse = float(np.sqrt(np.mean(d[ok] ** 2)))
        R, t, _ = align_umeyama(x[ok], tree.data[j[ok]], with_scale=False)
        T = sim3_matrix(R, t) @ T
        converged = (it > 1 and abs(new_fit - fitness) <= rel_tol * max(fitness, 1e-12)
                     and abs(new_rmse - rmse) <= rel_tol * max(rmse, 1e-12))
        fitness, rmse = float(new_fit), new_rmse
        if converged:
            break
    d, _ = tree.query(src @ T[:3, :3].T + T[:3, 3], distance_upper_bound=max_corr)  # the returned T's, as Open3D
    ok = np.isfinite(d)
    fitness = float(ok.mean()) if len(ok) else 0.0
    rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else 0.0  # no inliers: 0, as Open3D reports
    return T, {"fitness": float(fitness), "inlier_rmse": float(rmse), "iterations": it}


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int) -> np.ndarray:
    """(n, 3) points sampled uniformly by area on the mesh surface (trimesh, seeded)."""
    if len(mesh.faces) == 0 or mesh.area <= 0:
        raise ValueError("sample_surface: mesh has no faces / zero area (nothing to evaluate)")
    pts, _ = trimesh.sample.sample_surface(mesh, int(n), seed=int(seed))
    return np.asarray(pts, dtype=np.float64)


def mesh_metrics(
    rec: trimesh.Trimesh,
    gt: trimesh.Trimesh,
    n_samples: int = 200_000,
    threshold: float = 0.05,
    icp: bool = False,
    seed: int = 0,
    icp_max_corr: float = 0.1,
) -> dict:
    """Accuracy, completion and completion ratio between a reconstructed and a ground-truth mesh.

    With R = n_samples points sampled (area-weighted) on `rec` (seed) and G = n_samples on `gt` (seed + 1):
        Acc  = (1/|R|) Σ_{r∈R} min_{g∈G} |r − g|       (m)
        Comp = (1/|G|) Σ_{g∈G} min_{r∈R} |g − r|       (m)
        Comp% = (1/|G|) #{g ∈ G : min_r |g − r| < threshold}     (fraction 0–1)
    as NICE-SLAM / Co-SLAM's `neural_slam_eval`. If `icp`, the reconstruction is first moved by point-to-point
    ICP from its vertices to the GT vertices (max correspondence `icp_max_corr`, identity init) — the reference
    does this by default, we do not (docs/spec.md §8.7, §13.22).

    Args:
        rec, gt: meshes in metres (the reconstruction is usually culled first, `cull_mesh`).
        n_samples: points per surface.  threshold: metres.  icp: enable ICP.  seed: sampling seed.
    Returns:
        dict(acc_m, comp_m, comp_ratio, icp_applied, icp_transform (4x4 nested list or None), icp_info or None).
    """
    T = None
    info = None
    if icp:
        T, info = icp_point_to_point(rec.vertices, gt.vertices, max_corr=icp_max_corr)
        rec = rec.copy()
        rec.apply_transform(T)
    r = sample_surface(rec, n_samples, seed)
    g = sample_surface(gt, n_samples, seed + 1)
    d_rg, _ = cKDTree(g).query(r)
    d_gr, _ = cKDTree(r).query(g)
    return {
        "acc_m": float(d_rg.mean()),
        "comp_m": float(d_gr.mean()),
        "comp_ratio": float((d_gr < threshold).mean()),
        "icp_applied": bool(icp),
        "icp_transform": None if T is None else T.tolist(),
        "icp_info": info,
    }
