"""The owner's secret heads: the *extractor* (one logit per bit) and the *classifier* (watermarked or not).

Both read rendered RGB images. ``small`` is a right-sized strided CNN (tens of thousands of parameters: a
100-200 px render does not need more); ``vgg16`` is the paper's backbone shape (torchvision's VGG16 layout,
randomly initialised: no ImageNet weights exist offline) followed by average pooling and a linear layer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Tuple

from jaxtyping import Float
from torch import Tensor, nn


@dataclass
class HeadConfig:
    """Shape of the extractor and classifier networks."""

    backbone: Literal["small", "vgg16"] = "small"
    """small: strided CNN sized for <= 400 px renders; vgg16: the paper's (untrained) VGG16 feature stack."""
    width: int = 32
    """Channels of the first small-CNN stage (doubles every other stage)."""
    depth: int = 4
    """Number of stride-2 stages of the small CNN."""
    pooling: Literal["grid", "avg"] = "avg"
    """avg: global average pooling (the paper's); grid: average-pool to grid x grid cells and read them out with a
    linear layer (keeps where a pattern is)."""
    grid: int = 4
    """Cells per side of the grid pooling."""


def small_backbone(width: int, depth: int) -> Tuple[nn.Module, int]:
    layers = [nn.Conv2d(3, width, 3, padding=1), nn.GroupNorm(4, width), nn.GELU()]
    ch = width
    for i in range(depth):
        out = min(width * 2 ** ((i + 1) // 2), 8 * width)
        layers += [nn.Conv2d(ch, out, 3, stride=2, padding=1), nn.GroupNorm(4, out), nn.GELU()]
        ch = out
    return nn.Sequential(*layers), ch


def vgg16_backbone() -> Tuple[nn.Module, int]:
    # deferred: only the VGG16 backbone needs it
    from torchvision.models import vgg16

    return vgg16(weights=None).features, 512


class ConvHead(nn.Module):
    """Backbone -> global average pooling -> linear layer with ``num_outputs`` logits."""

    def __init__(self, config: HeadConfig, num_outputs: int) -> None:
        super().__init__()
        self.config = config
        if config.backbone == "vgg16":
            self.backbone, ch = vgg16_backbone()
        else:
            self.backbone, ch = small_backbone(config.width, config.depth)
        cells = config.grid * config.grid if config.pooling == "grid" else 1
        self.head = nn.Linear(ch * cells, num_outputs)

    def forward(self, images: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B O"]:
        x = self.backbone((images - 0.5) * 2.0)
        if self.config.pooling == "grid":
            x = nn.functional.adaptive_avg_pool2d(x, self.config.grid).flatten(1)
        else:
            x = x.mean(dim=(-2, -1))
        return self.head(x)


class Heads(nn.Module):
    """Extractor D (num_bits logits) and classifier C (1 logit), kept together in the owner key."""

    def __init__(self, config: HeadConfig, num_bits: int) -> None:
        super().__init__()
        self.config = config
        self.num_bits = num_bits
        self.extractor = ConvHead(config, num_bits)
        self.classifier = ConvHead(config, 1)

    def decode(self, images: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B K"]:
        return self.extractor(images)

    def classify(self, images: Float[Tensor, "B 3 H W"]) -> Float[Tensor, " B"]:
        return self.classifier(images).squeeze(-1)


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
