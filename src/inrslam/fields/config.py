"""Typed configuration of the scene representation F (docs/spec.md §3)."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field


class Coupling(str, enum.Enum):
    """Geometry/appearance coupling (docs/spec.md §3.8)."""

    COUPLED_BASE = "coupled_base"  # one encoder; SDF and colour decoders read the same features
    COUPLED = "coupled"  # one encoder; SDF decoder emits 1 + geo_feat_dim, colour reads the geometric feature
    DECOUPLED = "decoupled"  # two independent encoders (geometry / appearance)


class KernelChoice(str, enum.Enum):
    """Implementation of the grid / plane / line lookups."""

    AUTO = "auto"  # fused numba kernels for CPU tensors, PyTorch reference otherwise
    TORCH = "torch"  # PyTorch reference (gather + weights), any device
    NUMBA = "numba"  # fused numba CPU kernels (CPU tensors only)


class TouchedRows(str, enum.Enum):
    """Which rows of a table one lazy-Adam step updates (`fields.optim`): the fused backward decides."""

    READ = "read"  # every row read with a non-zero interpolation weight (the default of every F)
    GRADIENT = "gradient"  # only rows with a non-zero gradient: zero-gradient points are skipped in the backward
    # (the two differ for tables with a sparse gradient, more than DENSE_GRAD_MAX_ROWS rows: a dense gradient's zero
    # rows are never updated)


class MlpPrecision(str, enum.Enum):
    """Arithmetic of the MLP representation's layers after the first (`field.mlp.precision`)."""

    FLOAT32 = "float32"  # every layer in float32 (the paper's; bit for bit as ever)
    BFLOAT16 = "bfloat16"  # hidden layers and heads under torch.autocast(bfloat16): products in bfloat16 with
    # float32 accumulation; the Fourier features, the first layer, the outputs and every parameter stay float32


@dataclass
class MlpConfig:
    """Trunk of the MLP representation (`field.mlp.*`, used when `field.encoding` is mlp)."""

    width: int = 256  # width of the trunk
    depth: int = 4  # number of layers of the trunk
    precision: MlpPrecision = MlpPrecision.FLOAT32  # float32 | bfloat16: the trunk's hidden layers and the heads in
    # bfloat16 (autocast; 1.9x per frame on a CPU with AVX-512 BF16, GPUs need bfloat16 arithmetic; docs/speed.md)


@dataclass
class FieldConfig:
    """Scene representation F: encoding, resolutions, decoders, coupling and kernel choice."""

    encoding: str = "dense"  # registry name: mlp | dense | hash | triplane | tensorf | dense+tri | hash+tri
    coupling: Coupling = Coupling.COUPLED_BASE  # geometry/appearance coupling (ignored by hybrids)
    levels: int = 2  # number of resolution levels of grids / planes / lines
    feature_dim: int = 2  # features per vertex and level
    block_coarse: float = 0.24  # coarsest geometry cell size, metres (level 0)
    block_fine: float = 0.02  # finest geometry cell size, metres (last level)
    app_block_coarse: float = 0.24  # coarsest appearance cell size of the decoupled colour encoder, metres
    app_block_fine: float = 0.02  # finest appearance cell size of the decoupled colour encoder, metres
    plane_block_coarse: float = 0.24  # cell size of the hybrids' single tri-plane level, metres
    log2_hashmap_size: int = 19  # hash-grid table size per level = 2^this rows
    geo_feat_dim: int = 15  # geometric feature width passed to the colour decoder in coupled mode
    gamma: str = "identity"  # positional encoding of p̂ fed to decoders: identity | blob | freq
    hidden_dim: int = 32  # hidden width of the grid / plane decoders and of the MLP heads
    truncation: float = 0.1  # SDF truncation T, metres (field SDF is in units of T)
    kernel: KernelChoice = KernelChoice.AUTO  # lookup implementation: auto | torch | numba
    decoder_kernel: KernelChoice = KernelChoice.TORCH  # grid and plane decoders: torch (autograd) | numba (fused,
    # CPU) | auto (numba on CPU); for the MLP representation numba / auto run its float32 network in blocks of
    # samples (`kernels.blocked_mlp`; docs/speed.md)
    faithful: bool = False  # reproduce the original's quirks ([0,1] planes, ΣP⊙Σℓ TensoRF, cubic tcnn grids)
    grid_init: float = 1e-4  # grid features init U(−grid_init, grid_init)
    plane_init_std: float = 0.01  # plane / line features init N(0, plane_init_std²)
    mlp: MlpConfig = field(default_factory=MlpConfig)  # the MLP representation's trunk
