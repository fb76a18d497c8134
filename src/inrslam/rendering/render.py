"""Render a batch of rays through any field F and any rendering function G."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

import torch
from torch import Tensor

from inrslam.fields.kernels import input_grad_only, second_order
from inrslam.fields.kernels.ray_points import ray_points_normalised
from inrslam.rendering.compositing import composite
from inrslam.rendering.config import NormalsMethod


@dataclass
class RenderOutput:
    """Per-ray results of `render_rays` (R rays, S samples).

    Attributes:
        rgb: (R, 3) composited colour in [0, 1] (no background).
        depth: (R,) composited z-depth, metres.
        opacity: (R,) Σ w.
        depth_var: (R,) Σ w (z - depth)², m².
        weights: (R, S) weights from G.
        sdf: (R, S) field SDF, T-units.
        z: (R, S) sample z-depths, metres.
        normals: (R, S, 3) ∇_x sdf (T-units per metre) when the renderer needed them, else None.
    """

    rgb: Tensor
    depth: Tensor
    opacity: Tensor
    depth_var: Tensor
    weights: Tensor
    sdf: Tensor
    z: Tensor
    normals: Optional[Tensor] = None


def ray_points(origins: Tensor, dirs: Tensor, z: Tensor) -> Tensor:
    """x_{r,i} = o_r + z_{r,i} d_r. origins, dirs (R, 3); z (R, S) -> (R, S, 3) metres."""
    return origins[:, None, :] + z[..., None] * dirs[:, None, :]


def _query(field: Callable[[Tensor], Any], points: Tensor) -> tuple[Tensor, Tensor]:
    out = field(points)
    return out.sdf, out.rgb_logits


def sdf_gradient_autograd(
    field: Callable[[Tensor], Any], points: Tensor, create_graph: bool = True, include_rgb: bool = False
) -> tuple[Tensor, Tensor, Tensor]:
    """Query the field and ∇_x s by autograd, also inside `torch.no_grad()`.

    Only the SDF output is differentiated (`include_rgb` = the reference code's sum of all outputs). The points get
    `requires_grad` only locally (a detached copy if they did not need grad already), so no gradient leaks into
    tensors the caller did not ask for. With `create_graph` the field is queried inside `kernels.second_order()`:
    fused CPU lookups then keep their input Jacobian and Hessian cross terms, so that the loss's second-order
    backward stays fused (`MultilinearJacFn`); the gradient itself is taken inside `kernels.input_grad_only()`
    (no table gradients are computed for it).

    Args:
        field: callable (N, 3) -> object with .sdf (N,) and .rgb_logits (N, 3).
        points: (N, 3) metres.
        create_graph: keep the gradient differentiable (second-order backward through the field) when the caller
            has grad enabled; False returns a detached gradient.
    Returns:
        sdf (N,), rgb_logits (N, 3), gradient (N, 3) in T-units per metre. Outputs carry no graph if grad mode was
        off at the call.
    """
    grad_mode = torch.is_grad_enabled()
    with torch.enable_grad():
        x = points if points.requires_grad else points.detach().requires_grad_(True)
        if create_graph and grad_mode:  # fused lookups keep their Jacobian for the second-order backward
            with second_order():
                sdf, logits = _query(field, x)
        else:
            sdf, logits = _query(field, x)
        target = sdf + logits.sum(-1) if include_rgb else sdf
        with input_grad_only():  # only ∂/∂x is asked for: the fused lookups skip their table gradients
            (grad,) = torch.autograd.grad(
                target.sum(), x, create_graph=create_graph and grad_mode, retain_graph=grad_mode, allow_unused=True
            )
    if grad is None:
        grad = torch.zeros_like(points)
    if not (create_graph and grad_mode):
        grad = grad.detach()
    if not grad_mode:
        sdf, logits = sdf.detach(), logits.detach()
    return sdf, logits, grad


def sdf_gradient_fd(field: Callable[[Tensor], Any], points: Tensor, eps: float) -> Tensor:
    """Central-difference ∇_x s = [s(x + ε e_k) - s(x - ε e_k)] / (2ε), k = 1..3 (one batched field query of 6N).

    Args:
        points: (N, 3) metres; eps: ε, metres.
    Returns:
        (N, 3) T-units per metre (differentiable to first order w.r.t. the field parameters).
    """
    offsets = torch.eye(3, device=points.device, dtype=points.dtype) * eps
    shifted = torch.cat([points[None] + offsets[:, None], points[None] - offsets[:, None]], dim=0)  # (6, N, 3)
    sdf, _ = _query(field, shifted.reshape(-1, 3))
    sdf = sdf.reshape(6, -1)
    return ((sdf[:3] - sdf[3:]) / (2.0 * eps)).T


def render_rays(field: Callable[[Tensor], Any], renderer, origins: Tensor, dirs: Tensor, z: Tensor,
                truncation: float) -> RenderOutput:
    """Query F at o + z·d once and composite with G.

    Colour per sample c = sigmoid(rgb_logits); weights = renderer(sdf, z, dirs, normals, T);
    (Ĉ, D̂, O, Var) = `composite(weights, c, z)`. When `renderer.needs_normals`, ∇_x s is computed by autograd
    (differentiable or detached) or finite differences, per `renderer.normals_method`.

    Args:
        field: callable (N, 3) metres -> object with .sdf (N,) T-units and .rgb_logits (N, 3).
        renderer: an `SdfToWeights` module.
        origins: (R, 3) metres; dirs: (R, 3) unnormalised directions (camera z component 1); z: (R, S) metres.
        truncation: T, metres.
    Returns:
        RenderOutput.
    """
    sdf, rgb, weights, normals = render_samples(field, renderer, origins, dirs, z, truncation)
    out_rgb, depth, opacity, depth_var = composite(weights, rgb, z)
    return RenderOutput(out_rgb, depth, opacity, depth_var, weights, sdf, z, normals)


def _fused_points(field, renderer, origins: Tensor, dirs: Tensor, z: Tensor) -> bool:
    """Whether the sample points go through `kernels.ray_points`: the renderer's `render.kernel` picks numba for
    these tensors, the field takes normalised points (`Field.decode_normalised`), and z needs no gradient."""
    fused = getattr(renderer, "fused", None)
    return (fused is not None and hasattr(field, "decode_normalised") and not z.requires_grad
            and fused(origins, dirs, z))


def render_samples(field: Callable[[Tensor], Any], renderer, origins: Tensor, dirs: Tensor, z: Tensor,
                   truncation: float) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """`render_rays` before compositing: sdf (R, S) T-units, colours (R, S, 3), G's weights (R, S) and the normals
    (R, S, 3) or None."""
    R, S = z.shape
    normals = None
    if getattr(renderer, "needs_normals", False):
        points = ray_points(origins, dirs, z).reshape(-1, 3)
        method = NormalsMethod(getattr(renderer, "normals_method", NormalsMethod.AUTOGRAD))
        faithful = bool(getattr(renderer, "faithful", False))
        if method is NormalsMethod.FINITE_DIFFERENCE:
            sdf, logits = _query(field, points)
            normals = sdf_gradient_fd(field, points, float(renderer.fd_eps))
        else:
            sdf, logits, normals = sdf_gradient_autograd(
                field, points, create_graph=method is NormalsMethod.AUTOGRAD, include_rgb=faithful
            )
        normals = normals.reshape(R, S, 3)
    elif _fused_points(field, renderer, origins, dirs, z):  # `render.kernel`: p̂ in one pass (bit-identical values)
        f: Any = field  # a `Field`: `_fused_points` checked that it takes normalised points
        lo, ext = f.box(z.dtype)
        out = f.decode_normalised(ray_points_normalised(origins, dirs, z, lo, ext))
        sdf, logits = out.sdf, out.rgb_logits
    else:
        sdf, logits = _query(field, ray_points(origins, dirs, z).reshape(-1, 3))
    sdf = sdf.reshape(R, S)
    rgb = torch.sigmoid(logits.reshape(R, S, 3))
    return sdf, rgb, renderer(sdf, z, dirs, normals, truncation), normals
