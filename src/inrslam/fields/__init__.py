"""Scene representations F (docs/spec.md §3): encodings (MLP, dense / hash grids, tri-planes, TensoRF, hybrids), their
decoders and coupling modes, fused CPU kernels (``kernels/``), the lazy-Adam optimiser and model size.

    field = build_field(FieldConfig(encoding="hash"), bounds)      # bounds (3,2) metres
    out = field(x)                                                # x (N,3) metres -> sdf (N,) T-units, rgb_logits (N,3)
    opt = make_optimizer(field, lr=0.01)
"""

from inrslam.fields.config import Coupling, FieldConfig, KernelChoice
from inrslam.fields.models import Field, FieldOutput, build_field  # registers every encoding
from inrslam.fields.optim import LazyAdam, make_optimizer
from inrslam.fields.registry import ENCODINGS
from inrslam.fields.size import model_size_mb, param_count

__all__ = [
    "Coupling",
    "ENCODINGS",
    "Field",
    "FieldConfig",
    "FieldOutput",
    "KernelChoice",
    "LazyAdam",
    "build_field",
    "make_optimizer",
    "model_size_mb",
    "param_count",
]
