"""Vanilla NeRF with a configurable MLP size: the stock ``NeRFModel`` and ``NeRFField``, only smaller.

Stock ``vanilla-nerf`` fixes its two fields at 8 x 256 (plus a 128-wide head) with 64 + 128 samples per ray:
about 1.2 M parameters evaluated 256 times per ray, far more than a 100 px object scene needs on a CPU. The
stock config exposes the sample counts but not the MLP size; this subclass adds those fields and builds the
stock ``NeRFField`` with them. Everything else (encodings, samplers, renderers, losses, outputs) is the stock
model's, so every gsticker path for vanilla-nerf (the sticker's wrap of the fine field, the decoders) applies.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Tuple, Type

from nerfstudio.field_components.encodings import NeRFEncoding
from nerfstudio.fields.vanilla_nerf_field import NeRFField
from nerfstudio.models.vanilla_nerf import NeRFModel, VanillaModelConfig


@dataclass
class SmallNeRFModelConfig(VanillaModelConfig):
    """vanilla-nerf with its MLP sizes and positional-encoding frequencies as config fields."""

    _target: Type = field(default_factory=lambda: SmallNeRFModel)
    base_mlp_num_layers: int = 4
    """Layers of each field's density MLP (stock 8)."""
    base_mlp_layer_width: int = 64
    """Width of the density MLP (stock 256)."""
    head_mlp_layer_width: int = 32
    """Width of the color head MLP (stock 128)."""
    skip_connections: Tuple[int, ...] = (2,)
    """Density-MLP layers that see the encoded position again (stock (4,))."""
    position_frequencies: int = 10
    """Positional-encoding frequencies of the position (stock 10, max frequency exponent 8)."""
    direction_frequencies: int = 4
    """Positional-encoding frequencies of the view direction (stock 4)."""


class SmallNeRFModel(NeRFModel):
    """``NeRFModel`` whose coarse and fine fields are stock ``NeRFField`` modules of the configured size."""

    config: SmallNeRFModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()  # samplers, renderers, losses, metrics; its 8 x 256 fields are replaced here
        c = self.config
        position_encoding = NeRFEncoding(
            in_dim=3,
            num_frequencies=c.position_frequencies,
            min_freq_exp=0.0,
            max_freq_exp=float(c.position_frequencies - 2),
            include_input=True,
        )
        direction_encoding = NeRFEncoding(
            in_dim=3,
            num_frequencies=c.direction_frequencies,
            min_freq_exp=0.0,
            max_freq_exp=float(c.direction_frequencies),
            include_input=True,
        )
        kw = dict(
            position_encoding=position_encoding,
            direction_encoding=direction_encoding,
            base_mlp_num_layers=c.base_mlp_num_layers,
            base_mlp_layer_width=c.base_mlp_layer_width,
            head_mlp_layer_width=c.head_mlp_layer_width,
            skip_connections=tuple(c.skip_connections),
        )
        self.field_coarse = NeRFField(**kw)
        self.field_fine = NeRFField(**kw)
