"""Value attacks (noise, blur, hue, JPEG): a function and its thin ``nn.Module`` each."""

from __future__ import annotations

import math

import kornia
import torch
from jaxtyping import Float
from torch import Tensor, nn

from gsticker_plugin.attacks.common import (
    Strength,
    check_image,
    finish,
    is_number,
    per_image,
    randn_on,
    working,
)


def gaussian_noise(
    img: Float[Tensor, "B 3 H W"], sigma: Strength, generator: torch.Generator | None = None
) -> Float[Tensor, "B 3 H W"]:
    """Additive Gaussian noise N(0, sigma^2), then clamped to [0, 1].

    ``sigma`` is the *standard deviation* in [0, 1] intensity units. Beware when comparing with other
    watermarking benchmarks: several pass their "noise sigma" as the variance argument (e.g. a std of
    ``sigma**2``), so their "sigma 0.1" is a far weaker std 0.01 attack than ours.
    """
    check_image(img, "gaussian_noise")
    if is_number(sigma) and not (sigma >= 0 and math.isfinite(sigma)):
        raise ValueError(f"gaussian_noise: sigma must be a finite std >= 0, got {sigma}")
    x = working(img)
    s = per_image(sigma, x).view(-1, 1, 1, 1)
    noise = randn_on(x.shape, generator, x.device).to(x.dtype)
    return finish(x + s * noise, img)


def blur_kernel_size(sigma: float) -> int:
    """Odd Gaussian kernel size ``2 * ceil(3 * sigma) + 1``, at least 3."""
    return max(3, 2 * math.ceil(3.0 * sigma) + 1)


def gaussian_blur(img: Float[Tensor, "B 3 H W"], sigma: Strength, clamp: bool = True) -> Float[Tensor, "B 3 H W"]:
    """Gaussian blur with std ``sigma`` pixels, kernel size ``2*ceil(3*sigma)+1`` (at least 3), reflect borders.

    ``sigma <= 0`` is the identity. Note that a "blur sigma 0.1" setting, as some benchmarks use with a 3x3
    kernel, is practically an identity: the off-centre weight is ``exp(-1/(2*0.01)) ~ 2e-22``.
    """
    check_image(img, "gaussian_blur")
    if is_number(sigma):
        if not math.isfinite(sigma):
            raise ValueError(f"gaussian_blur: sigma must be finite, got {sigma}")
        if sigma <= 0:
            return img.clone()
    x = working(img)
    _, _, h, w = x.shape
    s = per_image(sigma, x)
    smax = float(s.detach().max()) if isinstance(sigma, Tensor) else float(sigma)
    if smax <= 0:
        return img.clone()
    k = blur_kernel_size(smax)
    kmax = 2 * min(h, w) - 1  # reflect padding needs pad < size
    if k > kmax:
        k = kmax if kmax % 2 == 1 else kmax - 1
    k = max(k, 1)
    s_safe = s.clamp_min(1e-3)
    out = kornia.filters.gaussian_blur2d(x, (k, k), torch.stack([s_safe, s_safe], dim=-1), border_type="reflect")
    out = torch.where((s > 0).view(-1, 1, 1, 1), out, x)
    return finish(out, img, clamp)


def hue_shift(img: Float[Tensor, "B 3 H W"], shift: Strength) -> Float[Tensor, "B 3 H W"]:
    """Rotate the HSV hue by ``shift`` full turns (``shift`` in [-0.5, 0.5]; 0.5 = 180 degrees).

    Uses ``kornia.color.rgb_to_hsv``/``hsv_to_rgb`` (kornia's hue is in radians, [0, 2*pi)). Saturation and
    value are kept, so gray pixels (saturation 0) are unchanged.
    """
    check_image(img, "hue_shift")
    if is_number(shift) and not (-0.5 <= shift <= 0.5):
        raise ValueError(f"hue_shift: shift must be in [-0.5, 0.5] turns (0.5 = 180 degrees), got {shift}")
    x = working(img)
    hsv = kornia.color.rgb_to_hsv(x)
    d = per_image(shift, x).view(-1, 1, 1) * (2.0 * math.pi)
    hue = torch.remainder(hsv[:, 0] + d, 2.0 * math.pi)
    out = kornia.color.hsv_to_rgb(torch.stack([hue, hsv[:, 1], hsv[:, 2]], dim=1))
    return finish(out, img)


def jpeg(img: Float[Tensor, "B 3 H W"], quality: Strength) -> Float[Tensor, "B 3 H W"]:
    """Differentiable JPEG encode/decode (``kornia.enhance.jpeg_codec_differentiable``) at ``quality`` 1..100.

    kornia 0.9 wants the quality as a 1-D tensor (``(1,)`` or ``(B,)``; a 0-D scalar is rejected) and pads
    H, W to multiples of 16 internally (cropping back), so any size works. Gradients flow to the image
    through kornia's differentiable rounding.
    """
    check_image(img, "jpeg")
    if is_number(quality) and not (1.0 <= quality <= 100.0):
        raise ValueError(f"jpeg: quality must be in 1..100, got {quality}")
    x = working(img)
    q = per_image(quality, x).contiguous()
    out = kornia.enhance.jpeg_codec_differentiable(x, q)
    return finish(out, img)


class GaussianNoise(nn.Module):
    """Module form of :func:`gaussian_noise`."""

    def __init__(self, sigma: float) -> None:
        super().__init__()
        self.sigma = sigma

    def forward(self, img: Tensor, generator: torch.Generator | None = None) -> Tensor:
        return gaussian_noise(img, self.sigma, generator=generator)


class GaussianBlur(nn.Module):
    """Module form of :func:`gaussian_blur`."""

    def __init__(self, sigma: float) -> None:
        super().__init__()
        self.sigma = sigma

    def forward(self, img: Tensor) -> Tensor:
        return gaussian_blur(img, self.sigma)


class HueShift(nn.Module):
    """Module form of :func:`hue_shift`."""

    def __init__(self, shift: float) -> None:
        super().__init__()
        self.shift = shift

    def forward(self, img: Tensor) -> Tensor:
        return hue_shift(img, self.shift)


class JPEG(nn.Module):
    """Module form of :func:`jpeg`."""

    def __init__(self, quality: float) -> None:
        super().__init__()
        self.quality = quality

    def forward(self, img: Tensor) -> Tensor:
        return jpeg(img, self.quality)
