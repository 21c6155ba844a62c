"""Geometric attacks (rotation, cropout, resize): a function and its thin ``nn.Module`` each."""

from __future__ import annotations

import math
from typing import Tuple

import kornia
import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from gsticker_plugin.attacks.common import (
    Strength,
    check_image,
    finish,
    is_number,
    per_image,
    rand_on,
    working,
)


def rotate(
    img: Float[Tensor, "B 3 H W"], degrees: Strength, fill: float = 1.0, clamp: bool = True
) -> Float[Tensor, "B 3 H W"]:
    """Rotate about the image centre by ``degrees`` (counter-clockwise, like ``torch.rot90``), keeping the size.

    The area that leaves the frame is lost; the area that enters it is ``fill`` (white by default: Blender
    scenes have white backgrounds, and black corners would be a give-away artefact the extractor could
    latch onto). kornia's ``rotate`` pads zeros, so a ones-mask is rotated the same way and the output is
    ``rot(img) + (1 - rot(mask)) * fill``, which also blends the bilinear border correctly.
    """
    check_image(img, "rotate")
    if is_number(degrees) and not math.isfinite(degrees):
        raise ValueError(f"rotate: degrees must be finite, got {degrees}")
    x = working(img)
    angle = per_image(degrees, x).contiguous()
    ones = torch.ones_like(x[:, :1])
    both = torch.cat([x, ones], dim=1)
    rot = kornia.geometry.transform.rotate(both, angle, mode="bilinear", padding_mode="zeros", align_corners=True)
    out = rot[:, :3] + (1.0 - rot[:, 3:]) * fill
    return finish(out, img, clamp)


def _rect_size(share: float, h: int, w: int, u: float) -> Tuple[int, int]:
    """Height and width of a rectangle covering about ``share`` of an h x w image; aspect from ``u`` in [0,1)."""
    area = share * h * w
    if area <= 0:
        return 0, 0
    ratio = 2.0 ** (2.0 * u - 1.0)  # aspect (height/width relative to the image's) in [1/2, 2]
    rh = int(round(math.sqrt(area * ratio * h / w)))
    rh = min(max(rh, 1), h)
    rw = int(round(area / rh))
    if rw > w:  # too wide: widen to the image and recompute the height
        rw = w
        rh = min(max(int(round(area / rw)), 1), h)
    return rh, max(rw, 0)


def cropout(
    img: Float[Tensor, "B 3 H W"],
    share: Strength,
    cover: Float[Tensor, "B 3 H W"] | None = None,
    fill: float = 1.0,
    generator: torch.Generator | None = None,
) -> Float[Tensor, "B 3 H W"]:
    """Replace a random axis-aligned rectangle covering ``share`` of each image's area by ``cover`` (or ``fill``).

    One rectangle per image, with a random aspect ratio in [1/2, 2] (relative to the image's) and a random
    position; its area is ``share * H * W`` up to rounding to whole pixels. ``share`` 0 changes nothing and
    1 replaces the whole image. Gradients flow to ``img`` outside the rectangle and to ``cover`` inside it.
    """
    check_image(img, "cropout")
    if is_number(share) and not (0.0 <= share <= 1.0):
        raise ValueError(f"cropout: share must be in [0, 1], got {share}")
    if cover is not None and cover.shape != img.shape:
        raise ValueError(f"cropout: cover must have the image's shape {tuple(img.shape)}, got {tuple(cover.shape)}")
    x = working(img)
    b, _, h, w = x.shape
    shares = per_image(share, x).detach().float().clamp(0.0, 1.0).cpu().tolist()
    u = rand_on((b, 3), generator, x.device).cpu().tolist()
    mask = torch.zeros((b, 1, h, w), dtype=x.dtype, device=x.device)
    for i in range(b):
        rh, rw = _rect_size(shares[i], h, w, u[i][0])
        if rh == 0 or rw == 0:
            continue
        top = min(int(u[i][1] * (h - rh + 1)), h - rh)
        left = min(int(u[i][2] * (w - rw + 1)), w - rw)
        mask[i, :, top : top + rh, left : left + rw] = 1.0
    repl = working(cover).to(x.dtype) if cover is not None else torch.full_like(x, fill)
    return finish(x * (1.0 - mask) + repl * mask, img)


def resize(img: Float[Tensor, "B 3 H W"], scale: Strength, clamp: bool = True) -> Float[Tensor, "B 3 H W"]:
    """Downscale by ``scale`` in (0, 1] (bilinear, antialiased) and upscale back to the original size.

    The reduced size is ``max(1, round(H * scale)) x max(1, round(W * scale))``; a scale that rounds to the
    original size (e.g. 1.0) is the identity.
    """
    check_image(img, "resize")
    if is_number(scale) and not (0.0 < scale <= 1.0):
        raise ValueError(f"resize: scale must be in (0, 1], got {scale}")
    x = working(img)
    b, _, h, w = x.shape
    if isinstance(scale, Tensor) and per_image(scale, x).unique().numel() > 1:
        scales = per_image(scale, x).detach().tolist()
        return torch.cat([resize(img[i : i + 1], float(scales[i]), clamp) for i in range(b)], dim=0)
    sc = float(per_image(scale, x)[0]) if isinstance(scale, Tensor) else float(scale)
    sh, sw = max(1, int(round(h * sc))), max(1, int(round(w * sc)))
    if (sh, sw) == (h, w):
        return img.clone()
    small = F.interpolate(x, size=(sh, sw), mode="bilinear", align_corners=False, antialias=True)
    out = F.interpolate(small, size=(h, w), mode="bilinear", align_corners=False)
    return finish(out, img, clamp)


class Rotate(nn.Module):
    """Module form of :func:`rotate`."""

    def __init__(self, degrees: float, fill: float = 1.0) -> None:
        super().__init__()
        self.degrees, self.fill = degrees, fill

    def forward(self, img: Tensor) -> Tensor:
        return rotate(img, self.degrees, fill=self.fill)


class Cropout(nn.Module):
    """Module form of :func:`cropout`."""

    def __init__(self, share: float, fill: float = 1.0) -> None:
        super().__init__()
        self.share, self.fill = share, fill

    def forward(self, img: Tensor, cover: Tensor | None = None, generator: torch.Generator | None = None) -> Tensor:
        return cropout(img, self.share, cover=cover, fill=self.fill, generator=generator)


class Resize(nn.Module):
    """Module form of :func:`resize`."""

    def __init__(self, scale: float) -> None:
        super().__init__()
        self.scale = scale

    def forward(self, img: Tensor) -> Tensor:
        return resize(img, self.scale)
