"""Rendering functions G as registered `nn.Module`s: per-sample SDF -> compositing weights.

Every renderer has the same call::

    weights = renderer(sdf, z, dirs, normals, truncation)

    sdf:        (R, S) field SDF in truncation units (metric SDF = s·T)
    z:          (R, S) sorted sample z-depths, metres (ray parameter of `dirs`)
    dirs:       (R, 3) unnormalised world directions (camera z component 1), so a z step Δz is Δz·|d| metres
    normals:    (R, S, 3) ∇_x s (T-units per metre) or None; required when `renderer.needs_normals`
    truncation: T, metres
    -> weights  (R, S) >= 0, Σ_i w_i <= 1

Learnable rendering parameters (β, inv_s) are ordinary `nn.Parameter`s of the module; optimise them with
`renderer_param_groups(renderer, cfg)` (learning rate `RenderConfig.beta_lr`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from inrslam.errors import ConfigError
from inrslam.fields.config import KernelChoice
from inrslam.fields.kernels.function import cpu_floats, resolve_kernel
from inrslam.registry import Registry
from inrslam.rendering import functional as F
from inrslam.rendering.config import NerfActivation, NormalsMethod, RenderConfig
from inrslam.rendering.weights_kernel import density_weights_fused, direct_weights_fused

RENDERERS: Registry[type["SdfToWeights"]] = Registry("renderer")


class SdfToWeights(nn.Module):
    """Base class of rendering functions G.

    Attributes:
        needs_normals: whether `forward` needs SDF gradients (`render_rays` then computes them).
        sdf_based: whether the field's scalar is read as a signed distance (T-units). True for direct, density,
            neus and volsdf; False for nerf, whose scalar is a raw volume density: the SDF losses (free-space,
            centre, tail) and SDF-only uses (zero-level mesh) do not apply to it — pass
            `compute_losses(..., sdf_terms=renderer.sdf_based)`.
        normals_method: how `render_rays` computes them (`NormalsMethod`).
        fd_eps: finite-difference step, metres.
        faithful: reproduce the reference code's quirks.
        kernel: `render.kernel` ("torch", "numba", "auto"): the fused weights of `weights_kernel` where the renderer
            has them (direct, density), and for any renderer without normals the fused sample points of
            `render_samples`.
    """

    needs_normals: bool = False
    sdf_based: bool = True

    def __init__(self, cfg: RenderConfig):
        super().__init__()
        self.faithful = bool(cfg.faithful)
        self.normals_method = NormalsMethod(cfg.neus.normals)
        self.fd_eps = float(cfg.neus.fd_eps)
        self.progress = 1.0
        self.kernel = KernelChoice(cfg.kernel).value

    def fused(self, *tensors: Tensor) -> bool:
        """Whether `render.kernel` runs its fused kernels on these tensors (never inside a second-order scope)."""
        return resolve_kernel(self.kernel, cpu_floats(*tensors), "render.kernel",
                              "CPU float32/float64 tensors of one dtype") == "numba"

    def set_progress(self, progress: float) -> None:
        """Tell the renderer how far the run is (0 = first frame, 1 = last); used by annealing schedules."""
        self.progress = float(min(max(progress, 0.0), 1.0))

    def forward(self, sdf: Tensor, z: Tensor, dirs: Tensor, normals: Tensor | None, truncation: float) -> Tensor:
        raise NotImplementedError


def _scalar_param(value: float, learn: bool) -> nn.Parameter:
    return nn.Parameter(torch.tensor(float(value)), requires_grad=bool(learn))


@RENDERERS.register("direct", help="SDF(direct): Co-SLAM / Azinovic bell weights, first surface, normalised")
class DirectWeights(SdfToWeights):
    """SDF(direct) (docs/spec.md §4.1; Azinović et al., Neural RGB-D Surface Reconstruction, CVPR 2022; Co-SLAM).

    w_i = ŵ_i m_i / (Σ_j ŵ_j m_j + 1e-8),  ŵ_i = σ(s_i/T) σ(-s_i/T),  m_i = 1[z_i < z_k + T],
    k = first sign change of s along the ray. Rays without a sign change keep all samples (the reference uses k = 0,
    docs/spec.md §13.7; reproduced with `faithful`). Normalised: Σ w = 1 (while some sample lies within ~2 T of the
    surface: far from it the 1e-8 dominates), so colour/depth are weighted averages.
    """

    def forward(self, sdf, z, dirs, normals, truncation):
        if self.fused(sdf, z):
            return direct_weights_fused(sdf, z, truncation, no_crossing_keeps_all=not self.faithful)
        return F.direct_weights(sdf, z, truncation, no_crossing_keeps_all=not self.faithful)


@RENDERERS.register("density", help="SDF(density): StyleSDF/ESLAM alpha = 1 - exp(-beta sigmoid(-beta s))")
class DensityWeights(SdfToWeights):
    """SDF(density) (docs/spec.md §4.2; StyleSDF, Or-El et al. CVPR 2022, as used by ESLAM, Johari et al. CVPR 2023).

    α_i = 1 - exp(-β σ(-β s_i)),  w_i = α_i Π_{j<i} (1 - α_j),  β in 1/T-units (default 10, fixed unless
    `render.density.learn_beta`). No sample spacing enters (σ·δ := 1), so the result depends on the sampling
    density: with the paper's 60 samples it saturates ~1-2 cm in front of the surface (measured in tests/rendering).
    """

    def __init__(self, cfg: RenderConfig):
        super().__init__(cfg)
        self.beta = _scalar_param(cfg.density.beta, cfg.density.learn_beta)

    def forward(self, sdf, z, dirs, normals, truncation):
        beta = self.beta.clamp_min(1e-3)
        if self.fused(sdf, beta):
            return density_weights_fused(sdf, beta)
        return F.weights_from_optical_depth(F.density_optical_depth(sdf, beta))


@RENDERERS.register("neus", help="SDF(surface): NeuS with learnable inverse std, metric intervals")
class NeusWeights(SdfToWeights):
    """NeuS (Wang et al., NeurIPS 2021), done right (fixes docs/spec.md §4.3 / §13.2).

    Work in metric SDF f = s·T. Section i = [b_i, b_{i+1}] around sample z_i (mid-point partition,
    `functional.section_bounds`); slope ĉ_i = annealed ⟨d/|d|, ∇f(x_i)⟩ with the *unit ray direction* and the
    gradient of the SDF output only (computed by `render_rays`, `render.neus.normals`);
    f_prev/next = f_i + ĉ_i (b - z_i)|d| (lengths in metres along the ray);
    α_i = clip((Φ(f_prev) - Φ(f_next)) / Φ(f_prev), 0, 1), Φ(x) = σ(inv_s·x), w_i = α_i Π_{j<i}(1 - α_j).

    inv_s (1/m) = exp(log_inv_s), learnable by default. Init `render.neus.init_log_inv_s` = 5: inv_s = 148/m, a 7 mm
    logistic scale, about a third of the surface-sample spacing (20 cm / 11). NeuS starts far softer (its photometric
    training must find the surface); here the SDF is supervised from depth from the first iteration, so we start
    near the converged sharpness that the 60-sample layout can resolve (tests/rendering: 1.8 mm plane/sphere depth
    error at e^5 vs 5 mm at e^6, and one-frame fits reach ~1 cm depth L1 at e^5 vs ~2.4 cm at e^4).

    Normals: `AUTOGRAD` (default; second-order backward through the field, fused on CPU), `FINITE_DIFFERENCE` (6
    extra queries, first-order only), `AUTOGRAD_DETACHED` (the cosine does not train the field) or `RAY_DIFFERENCE`
    (no normals: ĉ_i from the ray's own samples, `functional.ray_slope`; zero extra queries, first-order only).

    Annealing: NeuS anneals the cosine from (cos-1)/2 to -ReLU(-cos) over the first `anneal_end` of training.
    We default to no annealing (`render.neus.anneal_end = 0`): in SLAM the SDF is supervised directly from depth from
    the first iteration, so the 'back-face' smoothing the annealing provides for photometric-only NeuS is not
    needed; `set_progress(frame / last_frame)` drives it when enabled.

    `faithful`: SDF in T-units with inv_s = e^{1.4} per T-unit (fixed), forward intervals δ_i = z_{i+1} - z_i in z
    (δ_N = 1e10), f_prev/next = s_i ∓ ĉ_i δ_i/2, cos with the unnormalised direction, anneal_end 0.1, detached
    gradient. (The reference's use of the ray *origin* in the cosine is not reproduced.)
    """

    needs_normals = True

    def __init__(self, cfg: RenderConfig):
        super().__init__(cfg)
        if self.faithful:
            self.log_inv_s = _scalar_param(1.4, False)
            self.anneal_end = 0.1
            self.normals_method = NormalsMethod.AUTOGRAD_DETACHED
        else:
            self.log_inv_s = _scalar_param(cfg.neus.init_log_inv_s, cfg.neus.learn_s)
            self.anneal_end = float(cfg.neus.anneal_end)
        self.needs_normals = self.normals_method is not NormalsMethod.RAY_DIFFERENCE

    @property
    def inv_s(self) -> Tensor:
        """Inverse standard deviation of the logistic density, 1/m (faithful: per T-unit)."""
        return torch.exp(self.log_inv_s).clamp(1e-6, 1e6)

    def anneal_ratio(self) -> float:
        return 1.0 if self.anneal_end <= 0 else min(self.progress / self.anneal_end, 1.0)

    def forward(self, sdf, z, dirs, normals, truncation):
        if normals is None and self.needs_normals:
            raise ValueError("the neus renderer needs normals (R, S, 3); call it through render_rays")
        if self.faithful:
            cos = (dirs[:, None, :] * normals).sum(-1)
            slope = F.neus_annealed_cos(cos, self.anneal_ratio())
            delta = torch.cat([z[..., 1:] - z[..., :-1], torch.full_like(z[..., :1], 1e10)], dim=-1)
            alpha = F.neus_alpha(sdf - slope * delta * 0.5, sdf + slope * delta * 0.5, self.inv_s)
            return F.weights_from_alpha(alpha, eps=1e-7)  # as the reference: Σw may exceed 1 by ~S·1e-7
        ray_norm = dirs.norm(dim=-1, keepdim=True)
        if self.needs_normals:
            unit = dirs / ray_norm.clamp_min(1e-12)
            cos = (unit[:, None, :] * normals).sum(-1) * truncation  # directional derivative of the metric SDF
        else:
            cos = F.ray_slope(sdf * truncation, z, ray_norm)
        slope = F.neus_annealed_cos(cos, self.anneal_ratio())
        starts, ends = F.section_bounds(z)
        f_prev, f_next = F.neus_section_sdf(sdf * truncation, slope, z, starts, ends, ray_norm)
        alpha = F.neus_alpha(f_prev, f_next, self.inv_s)
        return F.weights_from_alpha(alpha, eps=0.0)


@RENDERERS.register("volsdf", help="VolSDF: Laplace-CDF density of the SDF with learnable beta")
class VolSdfWeights(SdfToWeights):
    """VolSDF (Yariv et al., Volume Rendering of Neural Implicit Surfaces, NeurIPS 2021).

    σ_i = (1/β) Ψ_β(-s_i T) (1/m), τ_i = σ_i δ_i with δ_i the metric length of the sample's mid-point section
    (Δz·|d|), w_i = (1 - e^{-τ_i}) exp(-Σ_{j<i} τ_j). β (metres) = β_min + exp(log_beta), learnable by default.
    """

    def __init__(self, cfg: RenderConfig):
        super().__init__(cfg)
        v = cfg.volsdf
        self.beta_min = float(v.beta_min)
        if v.beta_init <= self.beta_min:
            raise ConfigError(f"render.volsdf.beta_init ({v.beta_init}) must exceed render.volsdf.beta_min "
                              f"({v.beta_min})")
        self.log_beta = _scalar_param(math.log(v.beta_init - self.beta_min), v.learn_beta)

    @property
    def beta(self) -> Tensor:
        """Laplace scale β, metres."""
        return self.beta_min + torch.exp(self.log_beta)

    def forward(self, sdf, z, dirs, normals, truncation):
        starts, ends = F.section_bounds(z)
        delta = (ends - starts) * dirs.norm(dim=-1, keepdim=True)
        sigma = F.volsdf_density(sdf * truncation, self.beta)
        return F.weights_from_optical_depth(sigma * delta)


@RENDERERS.register("nerf", help="plain NeRF volume density: sigma = softplus/relu(raw), metric intervals")
class NerfWeights(SdfToWeights):
    """Plain volume density (NeRF, Mildenhall et al. ECCV 2020): the field's scalar is a raw density.

    σ_i = act(s_i) (1/m; act = softplus or ReLU), τ_i = σ_i δ_i with δ_i the metric length of the sample's
    mid-point section, w_i = (1 - e^{-τ_i}) exp(-Σ_{j<i} τ_j). Not SDF-based (`sdf_based = False`): the SDF losses
    do not apply to it.
    """

    sdf_based = False

    def __init__(self, cfg: RenderConfig):
        super().__init__(cfg)
        self.activation = NerfActivation(cfg.nerf.activation)

    def forward(self, sdf, z, dirs, normals, truncation):
        sigma = torch.nn.functional.softplus(sdf) if self.activation is NerfActivation.SOFTPLUS else torch.relu(sdf)
        starts, ends = F.section_bounds(z)
        delta = (ends - starts) * dirs.norm(dim=-1, keepdim=True)
        return F.weights_from_optical_depth(sigma * delta)


def build_renderer(cfg: RenderConfig) -> SdfToWeights:
    """Instantiate the renderer named `cfg.name` (ConfigError listing the choices if unknown)."""
    if cfg.name not in RENDERERS:
        raise ConfigError(f"render.name: {RENDERERS.unknown_message(cfg.name)}")
    return RENDERERS.get(cfg.name)(cfg)


def renderer_param_groups(renderer: nn.Module, cfg: RenderConfig) -> list[dict]:
    """Optimiser parameter groups for the learnable rendering parameters ([] when none are learnable)."""
    params = [p for p in renderer.parameters() if p.requires_grad]
    return [{"params": params, "lr": cfg.beta_lr}] if params else []
