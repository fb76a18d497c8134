"""The root configuration: one typed tree, the single source of truth for a run."""

from __future__ import annotations

from dataclasses import dataclass, field as _field

from inrslam.data.config import DataConfig
from inrslam.fields.config import FieldConfig
from inrslam.rendering.config import LossConfig, RenderConfig, SamplingConfig
from inrslam.eval.config import EvalConfig
from inrslam.slam.config import MeshConfig, OutputConfig, SlamConfig


@dataclass
class RunConfig:
    """Everything a run needs. Written resolved to `<out>/config.yaml`."""

    data: DataConfig = _field(default_factory=DataConfig)
    field: FieldConfig = _field(default_factory=FieldConfig)
    render: RenderConfig = _field(default_factory=RenderConfig)
    sampling: SamplingConfig = _field(default_factory=SamplingConfig)
    loss: LossConfig = _field(default_factory=LossConfig)
    slam: SlamConfig = _field(default_factory=SlamConfig)
    mesh: MeshConfig = _field(default_factory=MeshConfig)
    eval: EvalConfig = _field(default_factory=EvalConfig)
    output: OutputConfig = _field(default_factory=OutputConfig)
    seed: int = 0  # seed of every random choice (pixels, jitter, initialisation)
    device: str = "auto"  # auto (cuda if available), cpu, cuda, cuda:N
    threads: int = 0  # torch/numba threads (0 = all cores)
    faithful: bool = False  # reproduce the original code's documented quirks (docs/differences.md) everywhere

    def __post_init__(self):
        if self.faithful:
            apply_faithful(self)


def apply_faithful(cfg: RunConfig) -> None:
    """Switch every section to the original code's behaviour (docs/differences.md): [0,1] plane coordinates,
    sum-of-planes x sum-of-lines TensoRF and the cubic tcnn grid rule; the k = 0 SDF(direct) fallback; ±1.5 T
    surface band; one global loss mean; floor-divided default intrinsics."""
    from inrslam.rendering.config import LossReduction

    cfg.field.faithful = True
    cfg.render.faithful = True
    cfg.sampling.band = 1.5
    cfg.loss.reduction = LossReduction.GLOBAL
    cfg.data.faithful_intrinsics = True
