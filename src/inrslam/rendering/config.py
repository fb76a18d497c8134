"""Typed options of the rendering package: rendering function G, ray sampling, losses.

Defaults are the `paper` preset (Hua & Wang, CVPR 2024, supplementary + system spec) with the bugs of docs/spec.md §13
fixed; `faithful` values are noted per field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

from inrslam.fields.config import KernelChoice


class NormalsMethod(str, Enum):
    """How SDF gradients are obtained for renderers that need them (NeuS)."""

    AUTOGRAD = "autograd"  # exact gradient, differentiable (create_graph) so the loss trains the field through it
    AUTOGRAD_DETACHED = "autograd_detached"  # exact gradient, treated as a constant (as the reference code)
    FINITE_DIFFERENCE = "finite_difference"  # central differences, 6 extra field queries, first-order autograd only
    #: no gradient at all: NeuS's slope ⟨d/|d|, ∇f⟩ from the ray's own samples, (f_{i+1} - f_{i-1}) / metric step
    #: (`functional.ray_slope`); zero extra queries, first-order autograd only
    RAY_DIFFERENCE = "ray_difference"


class NerfActivation(str, Enum):
    """Map from the field's raw scalar to a volume density (1/m) for the plain `nerf` renderer."""

    SOFTPLUS = "softplus"
    RELU = "relu"


class SamplingVariant(str, Enum):
    """Depth-guided sampling layout (docs/spec.md §5.1 / §7.8)."""

    NONE = "none"  # n_free samples on [near, far_factor*D] + n_surface samples in D +- band*T
    SAMPLING = "sampling"  # 'sampling variant' of supp. Table 3: all n_free+n_surface samples on [near, far_factor*D]


class LossReduction(str, Enum):
    """How per-sample SDF errors are averaged (docs/spec.md §6 vs supplementary Eqs. (3), (5))."""

    PER_RAY = "per_ray"  # mean over the masked samples of each ray, then mean over rays having such samples (Eqs.)
    GLOBAL = "global"  # one mean over all masked samples of the batch (the reference code)


@dataclass
class DensityConfig:
    """SDF(density) options (`render.density.*`, used when `render.name` is density)."""

    beta: float = 10.0  # sharpness beta of alpha = 1 - exp(-beta*sigmoid(-beta*s)), 1/T-units
    learn_beta: bool = False  # optimise beta (the reference code never does, docs/spec.md §3.11)


@dataclass
class NeusConfig:
    """NeuS options (`render.neus.*`, used when `render.name` is neus)."""

    init_log_inv_s: float = 5.0  # initial log of the inverse std inv_s (1/m); e^5 = 148/m ~ 7 mm
    learn_s: bool = True  # optimise inv_s (the reference keeps it fixed)
    normals: NormalsMethod = NormalsMethod.AUTOGRAD  # how the slope is computed: autograd | autograd_detached |
    #   finite_difference | ray_difference (see NormalsMethod)
    fd_eps: float = 0.005  # finite-difference step, metres
    anneal_end: float = 0.0  # cos annealing length as a fraction of the run (0 = true cosine from start)


@dataclass
class VolSdfConfig:
    """VolSDF options (`render.volsdf.*`, used when `render.name` is volsdf)."""

    beta_init: float = 0.01  # initial Laplace scale beta, metres
    learn_beta: bool = True  # optimise beta
    beta_min: float = 1e-4  # lower bound of beta, metres


@dataclass
class NerfConfig:
    """Plain NeRF options (`render.nerf.*`, used when `render.name` is nerf)."""

    activation: NerfActivation = NerfActivation.SOFTPLUS  # raw scalar -> density (1/m)


@dataclass
class RenderConfig:
    """Rendering function G: per-sample SDF -> compositing weights (registry `RENDERERS`). The keys at this level
    apply to every renderer; each sub-section only to the renderer it is named after (setting another renderer's
    section is a `ConfigError`, see `inrslam.config.variants`)."""

    name: str = "density"  # renderer: direct | density | neus | volsdf | nerf
    beta_lr: float = 1e-3  # learning rate of every learnable rendering parameter (beta, inv_s, VolSDF beta)
    faithful: bool = False  # reproduce the reference code's quirks (direct k=0 fallback, NeuS units/annealing)
    kernel: KernelChoice = KernelChoice.TORCH  # points + direct/density weights: torch | numba (fused, CPU) | auto
    density: DensityConfig = field(default_factory=DensityConfig)  # SDF(density)
    neus: NeusConfig = field(default_factory=NeusConfig)  # NeuS
    volsdf: VolSdfConfig = field(default_factory=VolSdfConfig)  # VolSDF
    nerf: NerfConfig = field(default_factory=NerfConfig)  # plain NeRF density


@dataclass
class SamplingConfig:
    """Samples along each ray (docs/spec.md §5.1) and pixels per image (docs/spec.md §5.2)."""

    n_free: int = 48  # samples on [near, far_factor * D] for rays with depth
    n_surface: int = 12  # samples on D +- band*T for rays with depth
    n_uniform: int = 60  # samples on [near, AABB exit + 0.01] when no ray of the batch has depth
    near: float = 0.0  # first sample z-depth, metres
    far_factor: float = 1.2  # free-space samples end at far_factor * D
    band: float = 1.0  # surface band half-width in units of T (reference code / faithful: 1.5)
    jitter: bool = True  # stratified jitter of the merged samples (fresh every call)
    variant: SamplingVariant = SamplingVariant.NONE  # sampling layout variant (docs/spec.md §7.8)


@dataclass
class LossConfig:
    """Weights and masks of the training loss (docs/spec.md §6, supplementary Eqs. (1)-(6))."""

    color: float = 5.0  # lambda_p, weight of the colour MSE
    depth: float = 1.0  # lambda_g, weight of the depth MSE (rays with depth)
    free_space: float = 10.0  # lambda_fs, weight of the free-space SDF term
    center: float = 50.0  # lambda_c, weight of the SDF term within +-center_band*T of the depth
    tail: float = 200.0  # lambda_t, weight of the SDF term in the rest of the +-T band
    center_band: float = 0.4  # half-width of the centre band in units of T
    behind: float = 1.0  # the SDF terms reach this far behind the observed depth, units of T (1 = the paper's band)
    silhouette_behind: float = 1.0  # `behind` for rays at depth silhouettes only (SLAM mapping; 1 = off), units of T
    silhouette_jump: float = 0.1  # a silhouette pixel: a pixel within `silhouette_radius` is this much farther, metres
    silhouette_radius: int = 2  # pixels (Chebyshev) searched for the farther neighbour
    free_space_target: float = 1.0  # free-space SDF target, T-units ('loss variant' of docs/spec.md §7.8: 0.1)
    reduction: LossReduction = LossReduction.PER_RAY  # averaging of the SDF terms
    kernel: KernelChoice = KernelChoice.TORCH  # compositing + losses: torch (autograd) | numba (fused, CPU) | auto
