"""Scene representations F: encoder(s) + decoders -> (SDF in truncation units, colour logits) (docs/spec.md §3).

Every field normalises world points x (metres) to p̂ = (x − b_min)/(b_max − b_min); encoders clamp p̂ to the
unit box for their table lookups (border extension: an outside point reads the nearest box face, with zero
gradient along the clamped axes), while the positional encoding γ sees the unclamped p̂.
"""

from __future__ import annotations

import contextlib
import enum
import math
from dataclasses import replace
from typing import Any, NamedTuple, Optional, cast

import numpy as np
import torch
from torch import nn

from inrslam.errors import ConfigError
from inrslam.fields.config import Coupling, FieldConfig, KernelChoice, MlpPrecision
from inrslam.fields.encoders import GridEncoder, TableEncoder, TensoRFEncoder, TriPlaneEncoder
from inrslam.fields.gamma import FourierFeatures, make_gamma
from inrslam.fields.kernels.blocked_mlp import MlpScratch, blocked_mlp
from inrslam.fields.kernels.function import cpu_floats
from inrslam.fields.kernels.mlp import mlp2, mlp2_pair, resolve_backend
from inrslam.fields.kernels.mlp3 import mlp3
from inrslam.fields.registry import ENCODINGS
from inrslam.fields.resolution import plane_sizes


class FieldOutput(NamedTuple):
    """Raw field outputs at N points."""

    sdf: torch.Tensor  # (N,) SDF in truncation units (metric SDF = sdf · truncation)
    rgb_logits: Optional[torch.Tensor]  # (N,3) colour logits (sigmoid at render time); None from ``Field.sdf``


def grid_decoder(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    """"Grid decoder" (docs/spec.md §3.4): Linear(in→h) ReLU Linear(h→out), no biases."""
    return nn.Sequential(nn.Linear(in_dim, hidden, bias=False), nn.ReLU(), nn.Linear(hidden, out_dim, bias=False))


def run_grid_decoder(net: nn.Sequential, x: torch.Tensor, backend: str) -> torch.Tensor:
    """A `grid_decoder` on x (N, in) -> (N, out): backend "torch" runs the module itself (bit-for-bit as ever),
    "numba" / "auto" the fused kernel `mlp2` (`field.decoder_kernel`)."""
    if backend == "torch":
        return net(x)
    first, last = cast(nn.Linear, net[0]), cast(nn.Linear, net[2])
    return mlp2(x, first.weight, last.weight, backend)


def plane_decoder(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    """"Decomp decoder" (docs/spec.md §3.6): Linear(in→h) ReLU Linear(h→h) ReLU Linear(h→out), with biases."""
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, out_dim))


def run_plane_decoder(net: nn.Sequential, x: torch.Tensor, backend: str) -> torch.Tensor:
    """A `plane_decoder` on x (N, in) -> (N, out): backend "torch" runs the module itself (bit-for-bit as ever),
    "numba" / "auto" the fused kernel `mlp3` (`field.decoder_kernel`)."""
    if backend == "torch":
        return net(x)
    l1, l2, l3 = (cast(nn.Linear, net[k]) for k in (0, 2, 4))
    return mlp3(x, l1.weight, l1.bias, l2.weight, l2.bias, l3.weight, l3.bias, backend)


def mlp_trunk(in_dim: int, width: int, depth: int) -> nn.Sequential:
    """depth × (Linear, ReLU) of the given width (docs/spec.md §3.3; the configured skip never triggers)."""
    layers: list[nn.Module] = []
    for i in range(depth):
        layers += [nn.Linear(in_dim if i == 0 else width, width), nn.ReLU()]
    return nn.Sequential(*layers)


class Field(nn.Module):
    """Base scene representation. ``forward(x (N,3) m) -> FieldOutput``; ``sdf(x) -> (N,)`` T-units.

    Buffers: ``bounds (3,2)`` metres. Attribute ``truncation`` (m).
    """

    bounds: torch.Tensor  # (3,2) metres, buffer

    def __init__(self, cfg: FieldConfig, bounds: np.ndarray):
        super().__init__()
        self.cfg = replace(cfg)
        self.truncation = float(cfg.truncation)
        b = np.asarray(bounds, dtype=np.float64)
        self.register_buffer("bounds", torch.tensor(b, dtype=torch.float32))
        self.extent = b[:, 1] - b[:, 0]  # (3,) metres, float64 (resolution rules)
        self.decoder_backend = KernelChoice(cfg.decoder_kernel).value  # grid and plane decoders (`decode`)

    def box(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """(b_min, b_max − b_min), each (3,) metres in `dtype`: the normalisation p̂ = (x − b_min)/(b_max − b_min)."""
        b = self.bounds.to(dtype)
        return b[:, 0], b[:, 1] - b[:, 0]

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        """p̂ = (x − b_min)/(b_max − b_min), (N,3), not clamped."""
        lo, ext = self.box(x.dtype)
        return (x - lo) / ext

    def forward(self, x: torch.Tensor) -> FieldOutput:
        return self._decode(self.normalise(x), need_rgb=True)

    def decode_normalised(self, p: torch.Tensor) -> FieldOutput:
        """F at points already normalised (p̂ (N,3), e.g. by `kernels.ray_points`): `forward` without `normalise`."""
        return self._decode(p, need_rgb=True)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """SDF only (skips the colour branch), (N,) truncation units."""
        return self._decode(self.normalise(x), need_rgb=False).sdf

    def _decode(self, p: torch.Tensor, need_rgb: bool) -> FieldOutput:
        raise NotImplementedError

    def decode(self, net: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
        """Decoder `net` on x (N, in) -> (N, out) by `field.decoder_kernel`: grid decoders (Linear-ReLU-Linear, no
        biases) and plane decoders (three layers with biases)."""
        if len(net) == 5:
            return run_plane_decoder(net, x, self.decoder_backend)
        return run_grid_decoder(net, x, self.decoder_backend)


class EncoderField(Field):
    """Encoder + decoders with the three coupling modes of docs/spec.md §3.8.

    coupled_base: s = D_s([f, γ]), c = D_c([γ, f]);  coupled: [s, g] = D_s([f, γ]), c = D_c([g, γ]) (g 15-d);
    decoupled: s = D_s([f_geo, γ]), c = D_c([γ, f_app]) with an independent appearance encoder.
    """

    plane_style = False  # plane decoders (biases, 3 layers, tanh on the SDF output)

    def make_encoder(self, coarse: float, fine: float) -> TableEncoder:
        raise NotImplementedError

    def __init__(self, cfg: FieldConfig, bounds: np.ndarray):
        super().__init__(cfg, bounds)
        self.coupling = Coupling(cfg.coupling)
        self.gamma = make_gamma(cfg.gamma)
        self.encoder = self.make_encoder(cfg.block_coarse, cfg.block_fine)
        self.app_encoder = (self.make_encoder(cfg.app_block_coarse, cfg.app_block_fine)
                            if self.coupling is Coupling.DECOUPLED else None)
        dec = plane_decoder if self.plane_style else grid_decoder
        f, gd, h = self.encoder.out_dim, self.gamma.out_dim, cfg.hidden_dim
        g = cfg.geo_feat_dim if self.coupling is Coupling.COUPLED else 0
        self.sdf_net = dec(f + gd, h, 1 + g)
        if self.coupling is Coupling.COUPLED:
            self.rgb_net = dec(g + gd, h, 3)
        elif self.coupling is Coupling.DECOUPLED:
            self.rgb_net = dec(gd + cast(TableEncoder, self.app_encoder).out_dim, h, 3)
        else:
            self.rgb_net = dec(gd + f, h, 3)

    def _decode(self, p: torch.Tensor, need_rgb: bool) -> FieldOutput:
        gam = self.gamma(p)
        feat = self.encoder(p)
        if need_rgb and self.coupling is Coupling.COUPLED_BASE and not self.plane_style:
            pair = self._decode_pair(feat, gam)
            if pair is not None:
                return pair
        h = self.decode(self.sdf_net, torch.cat([feat, gam], dim=-1))
        if self.plane_style:
            h = torch.tanh(h)
        if not need_rgb:
            return FieldOutput(h[:, 0], None)
        if self.coupling is Coupling.COUPLED:
            rgb_in = torch.cat([h[:, 1:], gam], dim=-1)
        elif self.coupling is Coupling.DECOUPLED:
            rgb_in = torch.cat([gam, cast(TableEncoder, self.app_encoder)(p)], dim=-1)
        else:
            rgb_in = torch.cat([gam, feat], dim=-1)
        return FieldOutput(h[:, 0], self.decode(self.rgb_net, rgb_in))

    def _decode_pair(self, feat: torch.Tensor, gam: torch.Tensor) -> FieldOutput | None:
        """coupled_base with the fused decoders: D_s([f, γ]) and D_c([γ, f]) as one `mlp2_pair` call on [f, γ] (the
        colour decoder's first-layer columns reordered to match; f and γ are never concatenated); None where the
        decoders run in autograd."""
        sdf1, sdf2 = cast(nn.Linear, self.sdf_net[0]), cast(nn.Linear, self.sdf_net[2])
        rgb1, rgb2 = cast(nn.Linear, self.rgb_net[0]), cast(nn.Linear, self.rgb_net[2])
        ng = gam.shape[1]
        w1c = torch.cat([rgb1.weight[:, ng:], rgb1.weight[:, :ng]], dim=1)  # columns [γ, f] -> [f, γ]
        out = mlp2_pair(feat, gam, sdf1.weight, sdf2.weight, w1c, rgb2.weight, self.decoder_backend)
        return None if out is None else FieldOutput(out[0][:, 0], out[1])


def check_bfloat16(device_type: str) -> None:
    """A `ConfigError` for `field.mlp.precision=bfloat16` on a CUDA GPU without bfloat16 arithmetic (before Ampere),
    where autocast would fail mid-run."""
    if device_type == "cuda" and not torch.cuda.is_bf16_supported():
        raise ConfigError("config key 'field.mlp.precision': bfloat16 needs a GPU with bfloat16 arithmetic (Ampere or "
                          "later); this one has none: use float32")


@ENCODINGS.register("mlp", help="4x256 MLP on Gaussian Fourier features (iMAP-like)")
class MLPField(Field):
    """F = MLP (docs/spec.md §3.3): x = sin(p̂ᵀB) (93-d), trunk depth × width ReLU, SDF head width→h→1(+g).

    Colour: coupled_base reads the trunk output; coupled reads [g, x]; decoupled has its own trunk on x.
    With `field.decoder_kernel` auto / numba, float32 queries on the CPU run as one blocked network
    (`kernels.blocked_mlp`); `torch` (the `paper` preset) runs the modules themselves.
    """

    def __init__(self, cfg: FieldConfig, bounds: np.ndarray):
        super().__init__(cfg, bounds)
        self.coupling = Coupling(cfg.coupling)
        self.freq = FourierFeatures()
        d, w, h = self.freq.out_dim, cfg.mlp.width, cfg.hidden_dim
        g = cfg.geo_feat_dim if self.coupling is Coupling.COUPLED else 0
        self.trunk = mlp_trunk(d, w, cfg.mlp.depth)
        self.sdf_head = nn.Sequential(nn.Linear(w, h), nn.ReLU(), nn.Linear(h, 1 + g))
        self.rgb_trunk = mlp_trunk(d, w, cfg.mlp.depth) if self.coupling is Coupling.DECOUPLED else None
        rgb_in = g + d if self.coupling is Coupling.COUPLED else w
        self.rgb_head = nn.Sequential(nn.Linear(rgb_in, h), nn.ReLU(), nn.Linear(h, 3))
        self.precision = MlpPrecision(cfg.mlp.precision)
        self._bf16_checked = ""  # device type on which bfloat16 arithmetic was found available (`check_bfloat16`)
        self._scratch = MlpScratch()  # buffers of the blocked network (`field.decoder_kernel` auto / numba)

    def _trunk(self, trunk: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
        """trunk(x); in bfloat16 mode its first layer runs in float32 (it reads the Fourier features, whose phases
        carry the position) and the rest under the caller's autocast."""
        if self.precision is MlpPrecision.FLOAT32:
            return trunk(x)
        with torch.autocast(x.device.type, enabled=False):
            h = trunk[1](trunk[0](x))
        return trunk[2:](h)

    def _blocked(self, p: torch.Tensor) -> bool:
        """Whether `field.decoder_kernel` runs this query through the blocked network (`kernels.blocked_mlp`): float32
        layers (bfloat16 keeps its autocast modules), CPU tensors of the parameters' dtype, no second-order backward
        to follow."""
        if self.precision is not MlpPrecision.FLOAT32:
            return False
        return resolve_backend(self.decoder_backend, cpu_floats(p, self.freq.B)) == "numba"

    @staticmethod
    def _linear_params(*modules: nn.Sequential) -> list[torch.Tensor]:
        """(W1, b1, W2, b2, ...) of the Linear layers of these Sequentials, in order."""
        return [t for mod in modules for layer in mod if isinstance(layer, nn.Linear)
                for t in (layer.weight, layer.bias)]

    def _net(self, p: torch.Tensor, *modules: nn.Sequential) -> torch.Tensor:
        """sin(p̂ᵀB) through the given Sequentials one after the other, as one blocked network: (N, out)."""
        return blocked_mlp(p, self._linear_params(*modules), self._scratch, "numba", freq=self.freq.B)

    def _decode_blocked(self, p: torch.Tensor, need_rgb: bool) -> FieldOutput:
        """`_decode` through `kernels.blocked_mlp`: the SDF path (Fourier features, trunk, SDF head) as one network;
        with coupled_base colour both heads in it side by side (first layers stacked, second block-diagonal)."""
        if need_rgb and self.coupling is Coupling.COUPLED_BASE:
            s1, s2, r1, r2 = (cast(nn.Linear, m[k]) for m in (self.sdf_head, self.rgb_head) for k in (0, 2))
            heads = [torch.cat([s1.weight, r1.weight]), torch.cat([s1.bias, r1.bias]),  # first layers stacked
                     torch.block_diag(s2.weight, r2.weight), torch.cat([s2.bias, r2.bias])]  # second block-diagonal
            params = self._linear_params(self.trunk) + heads
            out = blocked_mlp(p, params, self._scratch, "numba", freq=self.freq.B)
            n_sdf = s2.weight.shape[0]
            return FieldOutput(out[:, 0], out[:, n_sdf:])
        h = self._net(p, self.trunk, self.sdf_head)
        if not need_rgb:
            rgb = None
        elif self.coupling is Coupling.COUPLED:
            rgb = self.rgb_head(torch.cat([h[:, 1:], self.freq(p)], dim=-1))
        else:  # decoupled
            rgb = self._net(p, cast(nn.Sequential, self.rgb_trunk), self.rgb_head)
        return FieldOutput(h[:, 0], rgb)

    def _decode(self, p: torch.Tensor, need_rgb: bool) -> FieldOutput:
        if self._blocked(p):
            return self._decode_blocked(p, need_rgb)
        x = self.freq(p)
        low = self.precision is MlpPrecision.BFLOAT16
        if low and x.device.type != self._bf16_checked:
            check_bfloat16(x.device.type)
            self._bf16_checked = x.device.type
        with torch.autocast(x.device.type, dtype=torch.bfloat16) if low else contextlib.nullcontext():
            t = self._trunk(self.trunk, x)
            h = self.sdf_head(t)
            if not need_rgb:
                rgb = None
            elif self.coupling is Coupling.COUPLED:
                rgb = self.rgb_head(torch.cat([h[:, 1:], x.to(h.dtype)], dim=-1))
            elif self.coupling is Coupling.DECOUPLED:
                rgb = self.rgb_head(self._trunk(cast(nn.Sequential, self.rgb_trunk), x))
            else:
                rgb = self.rgb_head(t)
        if low:  # outputs back in the caller's dtype (autocast leaves them bfloat16)
            return FieldOutput(h[:, 0].to(x.dtype), None if rgb is None else rgb.to(x.dtype))
        return FieldOutput(h[:, 0], rgb)


class _GridField(EncoderField):
    hashed = False

    def make_encoder(self, coarse: float, fine: float) -> TableEncoder:
        c = self.cfg
        return GridEncoder(self.extent, coarse, fine, c.levels, c.feature_dim, self.hashed, c.log2_hashmap_size,
                           c.faithful, c.grid_init, c.kernel)


@ENCODINGS.register("dense", help="multi-resolution dense feature grid (24 cm .. 2 cm), trilinear")
class DenseGridField(_GridField):
    """F = Dense grid (docs/spec.md §3.4) with the grid decoder."""


@ENCODINGS.register("hash", help="multi-resolution hash grid (2^log2_hashmap_size rows per level)")
class HashGridField(_GridField):
    """F = Sparse / hash grid (docs/spec.md §3.5) with the grid decoder."""

    hashed = True


class _PlaneField(EncoderField):
    plane_style = True
    encoder_type: type[TriPlaneEncoder] | type[TensoRFEncoder] = TriPlaneEncoder

    def make_encoder(self, coarse: float, fine: float) -> TableEncoder:
        c = self.cfg
        sizes = plane_sizes(self.extent, coarse, fine, c.levels, c.faithful)
        return self.encoder_type(sizes, c.feature_dim, c.faithful, c.plane_init_std, c.kernel)


@ENCODINGS.register("triplane", help="multi-resolution tri-plane (sum of xy, xz, yz planes), tanh SDF decoder")
class TriPlaneField(_PlaneField):
    """F = Tri-plane (docs/spec.md §3.6) with the plane decoder."""


@ENCODINGS.register("tensorf", help="TensoRF vector-matrix factorisation (planes x lines), tanh SDF decoder")
class TensoRFField(_PlaneField):
    """F = Fact. / TensoRF (docs/spec.md §3.7; true VM by default) with the plane decoder."""

    encoder_type = TensoRFEncoder


class _HybridField(Field):
    """Hybrid (docs/spec.md §3.9): grid + one coarse tri-plane level for geometry, grid only for colour; coupling
    ignored.

    s = D_s([f_grid, f_plane, γ]) (no tanh), c = D_c([γ, f_grid]); both grid decoders (no biases).
    """

    hashed = False

    def __init__(self, cfg: FieldConfig, bounds: np.ndarray):
        super().__init__(cfg, bounds)
        c = cfg
        self.gamma = make_gamma(c.gamma)
        self.grid = GridEncoder(self.extent, c.block_coarse, c.block_fine, c.levels, c.feature_dim, self.hashed,
                                c.log2_hashmap_size, c.faithful, c.grid_init, c.kernel)
        # one level at the coarse plane block (faithful: ⌊L_a / h⌋ vertices per axis)
        sizes = plane_sizes(self.extent, c.plane_block_coarse, c.plane_block_coarse, 1, c.faithful)
        self.planes = TriPlaneEncoder(sizes, c.feature_dim, c.faithful, c.plane_init_std, c.kernel)
        gd, h = self.gamma.out_dim, c.hidden_dim
        self.sdf_net = grid_decoder(self.grid.out_dim + self.planes.out_dim + gd, h, 1)
        self.rgb_net = grid_decoder(gd + self.grid.out_dim, h, 3)

    def _decode(self, p: torch.Tensor, need_rgb: bool) -> FieldOutput:
        gam = self.gamma(p)
        fg = self.grid(p)
        s = self.decode(self.sdf_net, torch.cat([fg, self.planes(p), gam], dim=-1))[:, 0]
        if not need_rgb:
            return FieldOutput(s, None)
        return FieldOutput(s, self.decode(self.rgb_net, torch.cat([gam, fg], dim=-1)))


@ENCODINGS.register("dense+tri", help="hybrid: dense grid + one coarse tri-plane level (geometry), grid (colour)")
class DenseTriField(_HybridField):
    """Hybrid (Dense+Tri)."""


@ENCODINGS.register("hash+tri", help="hybrid: hash grid + one coarse tri-plane level (geometry), grid (colour)")
class HashTriField(_HybridField):
    """Hybrid (Hash+Tri)."""

    hashed = True


def _validate(cfg: FieldConfig, bounds: np.ndarray) -> np.ndarray:
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (3, 2) or not np.all(np.isfinite(b)) or not np.all(b[:, 1] > b[:, 0]):
        raise ConfigError(f"field bounds: expected a finite (3,2) array [[xmin,xmax],[ymin,ymax],[zmin,zmax]] "
                          f"with max > min, got {np.asarray(bounds).tolist()}")
    if cfg.encoding not in ENCODINGS:
        raise ConfigError(f"field.encoding: {ENCODINGS.unknown_message(cfg.encoding)}")
    for key, value in (("levels", cfg.levels), ("feature_dim", cfg.feature_dim), ("hidden_dim", cfg.hidden_dim),
                       ("geo_feat_dim", cfg.geo_feat_dim), ("mlp.width", cfg.mlp.width), ("mlp.depth", cfg.mlp.depth)):
        if int(value) < 1:
            raise ConfigError(f"field.{key}: expected a positive integer, got {value!r}")
    for key in ("block_coarse", "block_fine", "app_block_coarse", "app_block_fine", "plane_block_coarse",
                "truncation"):
        if not float(getattr(cfg, key)) > 0:
            raise ConfigError(f"field.{key}: expected a positive length in metres, got {getattr(cfg, key)!r}")
    for key in ("grid_init", "plane_init_std"):
        scale = float(getattr(cfg, key))
        if not (math.isfinite(scale) and scale >= 0):
            raise ConfigError(f"field.{key}: expected a finite number >= 0, got {getattr(cfg, key)!r}")
    if not 1 <= cfg.log2_hashmap_size <= 30:
        raise ConfigError(f"field.log2_hashmap_size: expected 1..30, got {cfg.log2_hashmap_size}")
    choices: tuple[tuple[str, type[enum.Enum], Any], ...] = (
        ("coupling", Coupling, cfg.coupling), ("kernel", KernelChoice, cfg.kernel),
        ("decoder_kernel", KernelChoice, cfg.decoder_kernel), ("mlp.precision", MlpPrecision, cfg.mlp.precision))
    for key, enum_t, choice in choices:
        try:
            enum_t(choice)
        except ValueError:
            raise ConfigError(f"field.{key}: {choice!r} is not one of {', '.join(e.value for e in enum_t)}") from None
    return b


def build_field(cfg: FieldConfig, bounds: np.ndarray) -> Field:
    """Build the representation ``cfg.encoding`` over the box ``bounds`` ((3,2) metres)."""
    b = _validate(cfg, bounds)
    return ENCODINGS.get(cfg.encoding)(cfg, b)
