"""A base's background as its renderer composites it (Nerfstudio's ``background_color``), for re-compositing cached
samples: a fixed colour, or each ray's last sample colour (``last_sample``, stock nerfacto's default)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import torch
from jaxtyping import Float
from torch import Tensor

from gsticker_plugin.errors import GStickerError

BACKGROUND_NAMES = ("white", "black", "random", "last_sample")


@dataclass(frozen=True)
class Background:
    """``color``: the fixed RGB colour, or None for ``last_sample``. ``name``: the renderer's setting.

    ``random`` is black here: outside training Nerfstudio's RGBRenderer adds no background for it, and the sticker,
    its pool and the decoders all work on those (evaluation) renders."""

    color: Optional[Float[Tensor, " 3"]]
    name: str

    @classmethod
    def of(cls, spec: Union[str, Tensor, "Background"]) -> "Background":
        """From a renderer's ``background_color`` (a name or an RGB tensor) or a colour."""
        if isinstance(spec, Background):
            return spec
        if isinstance(spec, Tensor):
            return cls(spec.detach().float().reshape(3), "color")
        if spec == "white":
            return cls(torch.ones(3), "white")
        if spec in ("black", "random"):
            return cls(torch.zeros(3), str(spec))
        if spec == "last_sample":
            return cls(None, "last_sample")
        raise GStickerError(f"unknown background {spec!r}: one of {', '.join(BACKGROUND_NAMES)} or an RGB colour")

    def fill(self, rgb: Float[Tensor, "*R S 3"]) -> Float[Tensor, "*R 3"]:
        """The background behind each ray whose sample colours are ``rgb`` (broadcastable to ``rgb[..., 0, :]``)."""
        if self.color is None:
            return rgb[..., -1, :]
        return self.color.to(rgb)

    def to(self, device) -> "Background":
        return self if self.color is None else Background(self.color.to(device), self.name)

    def image_color(self) -> Float[Tensor, " 3"]:
        """The colour to composite RGBA images on (ground truth, recolor targets); ``last_sample``: white, as the
        Blender-format scenes' backgrounds are."""
        return torch.ones(3) if self.color is None else self.color.cpu()


def background_of(model) -> Background:
    """The background of ``model``'s RGB renderer, through GeometrySticker (``base``) and recolor (``inner``) wrappers."""
    m = model
    while m is not None:
        renderer = getattr(m, "renderer_rgb", None)
        if renderer is not None and hasattr(renderer, "background_color"):
            return Background.of(renderer.background_color)
        nxt = m.__dict__.get("_modules", {})
        m = nxt.get("inner", nxt.get("base"))
    raise GStickerError(f"{type(model).__name__} has no renderer_rgb.background_color: not a Nerfstudio model")
