"""Image distortions ("attacks") for robustness training and evaluation of the message extractor.

All functions take float RGB images ``Float[Tensor, "B 3 H W"]`` in [0, 1] and return a new image of the same
shape, dtype and device, clamped to [0, 1] (``gaussian_blur``, ``resize`` and ``rotate`` take ``clamp=False``
for their unclamped, linear-in-the-image form, which the image decoder applies to small changes). They are differentiable wherever the operation allows (they sit
between the renderer and the extractor during training), and every random one takes an optional
``generator: torch.Generator | None`` (random numbers are drawn on the generator's device and moved to the
image's device, so a CPU generator gives the same draws for CPU and CUDA images).

Pure functions come first; thin ``nn.Module`` wrappers (kornia style) and the training-time
:class:`RandomDistortion` follow. :data:`ATTACKS`, :func:`parse_attack_spec` and :func:`apply_attacks` give
the evaluation CLI a uniform ``name=strength`` interface.

Strengths may be a Python number (one for the batch) or, for every attack, a per-image tensor ``[B]``.
Python numbers are range-checked (``ValueError``); tensors are trusted, since checking them would force a
device sync in the training loop.

float16/bfloat16 images are processed in float32 and rounded back once at the end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Dict, Iterable, List, Sequence, Tuple, Union

import kornia
import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

Strength = Union[float, Tensor]

ATTACK_NAMES: Tuple[str, ...] = ("noise", "rotate", "crop", "blur", "hue", "jpeg", "resize")


# ----------------------------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------------------------
def _check_image(img: Tensor, fn: str) -> None:
    if not isinstance(img, Tensor) or img.ndim != 4 or img.shape[1] != 3 or not img.is_floating_point():
        shape = tuple(img.shape) if isinstance(img, Tensor) else type(img).__name__
        raise ValueError(f"{fn}: expected a float image tensor of shape (B, 3, H, W) in [0, 1], got {shape}")


def _work(img: Tensor) -> Tensor:
    """The image in the dtype the computation runs in (float32 for half precision inputs)."""
    return img.float() if img.dtype in (torch.float16, torch.bfloat16) else img


def _finish(out: Tensor, like: Tensor, clamp: bool = True) -> Tensor:
    return (out.clamp(0.0, 1.0) if clamp else out).to(like.dtype)


def _per_image(value: Strength, img: Tensor) -> Tensor:
    """A strength as a ``[B]`` tensor in the image's working dtype and device."""
    b = img.shape[0]
    t = torch.as_tensor(value, dtype=img.dtype, device=img.device)
    if t.ndim == 0:
        return t.expand(b)
    t = t.reshape(-1)
    if t.numel() == 1:
        return t.expand(b)
    if t.numel() != b:
        raise ValueError(f"per-image strength has {t.numel()} values for a batch of {b}; give one or {b}")
    return t


def _rand(shape: Sequence[int], generator: torch.Generator | None, device: torch.device) -> Tensor:
    """Uniform [0, 1) float32 numbers drawn on the generator's device (or ``device``), moved to ``device``."""
    dev = generator.device if generator is not None else device
    return torch.rand(tuple(shape), generator=generator, device=dev, dtype=torch.float32).to(device)


def _randn(shape: Sequence[int], generator: torch.Generator | None, device: torch.device) -> Tensor:
    dev = generator.device if generator is not None else device
    return torch.randn(tuple(shape), generator=generator, device=dev, dtype=torch.float32).to(device)


def _is_number(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


# ----------------------------------------------------------------------------------------------------------------
# pure functions
# ----------------------------------------------------------------------------------------------------------------
def gaussian_noise(
    img: Float[Tensor, "B 3 H W"], sigma: Strength, generator: torch.Generator | None = None
) -> Float[Tensor, "B 3 H W"]:
    """Additive Gaussian noise N(0, sigma^2), then clamped to [0, 1].

    ``sigma`` is the *standard deviation* in [0, 1] intensity units. Beware when comparing with other
    watermarking benchmarks: several pass their "noise sigma" as the variance argument (e.g. a std of
    ``sigma**2``), so their "sigma 0.1" is a far weaker std 0.01 attack than ours.
    """
    _check_image(img, "gaussian_noise")
    if _is_number(sigma) and not (sigma >= 0 and math.isfinite(sigma)):
        raise ValueError(f"gaussian_noise: sigma must be a finite std >= 0, got {sigma}")
    x = _work(img)
    s = _per_image(sigma, x).view(-1, 1, 1, 1)
    noise = _randn(x.shape, generator, x.device).to(x.dtype)
    return _finish(x + s * noise, img)


def rotate(img: Float[Tensor, "B 3 H W"], degrees: Strength, fill: float = 1.0,
           clamp: bool = True) -> Float[Tensor, "B 3 H W"]:
    """Rotate about the image centre by ``degrees`` (counter-clockwise, like ``torch.rot90``), keeping the size.

    The area that leaves the frame is lost; the area that enters it is ``fill`` (white by default: Blender
    scenes have white backgrounds, and black corners would be a give-away artefact the extractor could
    latch onto). kornia's ``rotate`` pads zeros, so a ones-mask is rotated the same way and the output is
    ``rot(img) + (1 - rot(mask)) * fill``, which also blends the bilinear border correctly.
    """
    _check_image(img, "rotate")
    if _is_number(degrees) and not math.isfinite(degrees):
        raise ValueError(f"rotate: degrees must be finite, got {degrees}")
    x = _work(img)
    angle = _per_image(degrees, x).contiguous()
    ones = torch.ones_like(x[:, :1])
    both = torch.cat([x, ones], dim=1)
    rot = kornia.geometry.transform.rotate(both, angle, mode="bilinear", padding_mode="zeros", align_corners=True)
    out = rot[:, :3] + (1.0 - rot[:, 3:]) * fill
    return _finish(out, img, clamp)


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
    _check_image(img, "cropout")
    if _is_number(share) and not (0.0 <= share <= 1.0):
        raise ValueError(f"cropout: share must be in [0, 1], got {share}")
    if cover is not None and cover.shape != img.shape:
        raise ValueError(f"cropout: cover must have the image's shape {tuple(img.shape)}, got {tuple(cover.shape)}")
    x = _work(img)
    b, _, h, w = x.shape
    shares = _per_image(share, x).detach().float().clamp(0.0, 1.0).cpu().tolist()
    u = _rand((b, 3), generator, x.device).cpu().tolist()
    mask = torch.zeros((b, 1, h, w), dtype=x.dtype, device=x.device)
    for i in range(b):
        rh, rw = _rect_size(shares[i], h, w, u[i][0])
        if rh == 0 or rw == 0:
            continue
        top = min(int(u[i][1] * (h - rh + 1)), h - rh)
        left = min(int(u[i][2] * (w - rw + 1)), w - rw)
        mask[i, :, top : top + rh, left : left + rw] = 1.0
    repl = _work(cover).to(x.dtype) if cover is not None else torch.full_like(x, fill)
    return _finish(x * (1.0 - mask) + repl * mask, img)


def blur_kernel_size(sigma: float) -> int:
    """Odd Gaussian kernel size ``2 * ceil(3 * sigma) + 1``, at least 3."""
    return max(3, 2 * math.ceil(3.0 * sigma) + 1)


def gaussian_blur(img: Float[Tensor, "B 3 H W"], sigma: Strength, clamp: bool = True) -> Float[Tensor, "B 3 H W"]:
    """Gaussian blur with std ``sigma`` pixels, kernel size ``2*ceil(3*sigma)+1`` (at least 3), reflect borders.

    ``sigma <= 0`` is the identity. Note that a "blur sigma 0.1" setting, as some benchmarks use with a 3x3
    kernel, is practically an identity: the off-centre weight is ``exp(-1/(2*0.01)) ~ 2e-22``.
    """
    _check_image(img, "gaussian_blur")
    if _is_number(sigma):
        if not math.isfinite(sigma):
            raise ValueError(f"gaussian_blur: sigma must be finite, got {sigma}")
        if sigma <= 0:
            return img.clone()
    x = _work(img)
    _, _, h, w = x.shape
    s = _per_image(sigma, x)
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
    return _finish(out, img, clamp)


def hue_shift(img: Float[Tensor, "B 3 H W"], shift: Strength) -> Float[Tensor, "B 3 H W"]:
    """Rotate the HSV hue by ``shift`` full turns (``shift`` in [-0.5, 0.5]; 0.5 = 180 degrees).

    Uses ``kornia.color.rgb_to_hsv``/``hsv_to_rgb`` (kornia's hue is in radians, [0, 2*pi)). Saturation and
    value are kept, so gray pixels (saturation 0) are unchanged.
    """
    _check_image(img, "hue_shift")
    if _is_number(shift) and not (-0.5 <= shift <= 0.5):
        raise ValueError(f"hue_shift: shift must be in [-0.5, 0.5] turns (0.5 = 180 degrees), got {shift}")
    x = _work(img)
    hsv = kornia.color.rgb_to_hsv(x)
    d = _per_image(shift, x).view(-1, 1, 1) * (2.0 * math.pi)
    hue = torch.remainder(hsv[:, 0] + d, 2.0 * math.pi)
    out = kornia.color.hsv_to_rgb(torch.stack([hue, hsv[:, 1], hsv[:, 2]], dim=1))
    return _finish(out, img)


def jpeg(img: Float[Tensor, "B 3 H W"], quality: Strength) -> Float[Tensor, "B 3 H W"]:
    """Differentiable JPEG encode/decode (``kornia.enhance.jpeg_codec_differentiable``) at ``quality`` 1..100.

    kornia 0.9 wants the quality as a 1-D tensor (``(1,)`` or ``(B,)``; a 0-D scalar is rejected) and pads
    H, W to multiples of 16 internally (cropping back), so any size works. Gradients flow to the image
    through kornia's differentiable rounding.
    """
    _check_image(img, "jpeg")
    if _is_number(quality) and not (1.0 <= quality <= 100.0):
        raise ValueError(f"jpeg: quality must be in 1..100, got {quality}")
    x = _work(img)
    q = _per_image(quality, x).contiguous()
    out = kornia.enhance.jpeg_codec_differentiable(x, q)
    return _finish(out, img)


def resize(img: Float[Tensor, "B 3 H W"], scale: Strength, clamp: bool = True) -> Float[Tensor, "B 3 H W"]:
    """Downscale by ``scale`` in (0, 1] (bilinear, antialiased) and upscale back to the original size.

    The reduced size is ``max(1, round(H * scale)) x max(1, round(W * scale))``; a scale that rounds to the
    original size (e.g. 1.0) is the identity.
    """
    _check_image(img, "resize")
    if _is_number(scale) and not (0.0 < scale <= 1.0):
        raise ValueError(f"resize: scale must be in (0, 1], got {scale}")
    x = _work(img)
    b, _, h, w = x.shape
    if isinstance(scale, Tensor) and _per_image(scale, x).unique().numel() > 1:
        scales = _per_image(scale, x).detach().tolist()
        return torch.cat([resize(img[i : i + 1], float(scales[i]), clamp) for i in range(b)], dim=0)
    sc = float(_per_image(scale, x)[0]) if isinstance(scale, Tensor) else float(scale)
    sh, sw = max(1, int(round(h * sc))), max(1, int(round(w * sc)))
    if (sh, sw) == (h, w):
        return img.clone()
    small = F.interpolate(x, size=(sh, sw), mode="bilinear", align_corners=False, antialias=True)
    out = F.interpolate(small, size=(h, w), mode="bilinear", align_corners=False)
    return _finish(out, img, clamp)


# ----------------------------------------------------------------------------------------------------------------
# registry and spec parsing
# ----------------------------------------------------------------------------------------------------------------
AttackFn = Callable[..., Tensor]
"""``fn(img, strength, generator=None, cover=None) -> img``."""

ATTACKS: Dict[str, AttackFn] = {
    "noise": lambda img, s, generator=None, cover=None: gaussian_noise(img, s, generator=generator),
    "rotate": lambda img, s, generator=None, cover=None: rotate(img, s),
    "crop": lambda img, s, generator=None, cover=None: cropout(img, s, cover=cover, generator=generator),
    "blur": lambda img, s, generator=None, cover=None: gaussian_blur(img, s),
    "hue": lambda img, s, generator=None, cover=None: hue_shift(img, s),
    "jpeg": lambda img, s, generator=None, cover=None: jpeg(img, s),
    "resize": lambda img, s, generator=None, cover=None: resize(img, s),
}
"""Uniform ``name -> fn(img, strength, generator=None, cover=None)`` registry, names as in :data:`ATTACK_NAMES`."""

# name -> (check, what the value must be, an example)
_RANGES: Dict[str, Tuple[Callable[[float], bool], str, str]] = {
    "noise": (lambda v: v >= 0, "a noise std >= 0", "noise=0.1"),
    "rotate": (lambda v: True, "an angle in degrees", "rotate=30"),
    "crop": (lambda v: 0 <= v <= 1, "an area share in [0,1]", "crop=0.25"),
    "blur": (lambda v: v >= 0, "a blur sigma >= 0 (pixels)", "blur=1"),
    "hue": (lambda v: -0.5 <= v <= 0.5, "a hue shift in [-0.5,0.5] turns", "hue=0.3"),
    "jpeg": (lambda v: 1 <= v <= 100, "a jpeg quality in 1..100", "jpeg=50"),
    "resize": (lambda v: 0 < v <= 1, "a resize scale in (0,1]", "resize=0.5"),
}


def check_strength(name: str, value: float) -> float:
    """Validate one attack's strength; return it as a float or raise a one-line ``ValueError`` naming the fix."""
    if name not in _RANGES:
        raise ValueError(f"unknown attack {name!r}: use one of {', '.join(ATTACK_NAMES)}")
    ok, what, example = _RANGES[name]
    v = float(value)
    if not math.isfinite(v) or not ok(v):
        raise ValueError(f"attack {name!r}: strength must be {what}, got {value!r}; e.g. {example}")
    return v


def parse_attack_spec(spec: str) -> List[Tuple[str, float]]:
    """Parse ``"noise=0.1,rotate=30,crop=0.25,blur=1,jpeg=50,hue=0.3,resize=0.5"`` into ``[(name, value), ...]``.

    Order is kept (attacks are applied in order), names are case-insensitive, spaces and empty items are
    ignored, and an empty spec means no attack. Raises a one-line ``ValueError`` naming the fix for an
    unknown name, a missing ``=``, a value that is not a number, or a value out of range.
    """
    if not isinstance(spec, str):
        raise ValueError(f"attack spec must be a string like 'noise=0.1,jpeg=50', got {type(spec).__name__}")
    out: List[Tuple[str, float]] = []
    for item in spec.split(","):
        item = item.strip()
        if not item:
            continue
        if "=" not in item:
            raise ValueError(f"attack spec item {item!r} has no '=': write NAME=STRENGTH, e.g. 'noise=0.1'")
        name, _, raw = item.partition("=")
        name, raw = name.strip().lower(), raw.strip()
        if name not in ATTACKS:
            raise ValueError(f"unknown attack {name!r} in {spec!r}: use one of {', '.join(ATTACK_NAMES)}")
        try:
            value = float(raw)
        except ValueError:
            raise ValueError(
                f"attack {name!r}: {raw!r} is not a number; write e.g. '{_RANGES[name][2]}'"
            ) from None
        out.append((name, check_strength(name, value)))
    return out


def apply_attacks(
    img: Float[Tensor, "B 3 H W"],
    spec: str | Iterable[Tuple[str, float]],
    generator: torch.Generator | None = None,
    cover: Float[Tensor, "B 3 H W"] | None = None,
) -> Float[Tensor, "B 3 H W"]:
    """Apply the attacks of ``spec`` (a spec string or ``[(name, strength), ...]``) in order."""
    steps = parse_attack_spec(spec) if isinstance(spec, str) else [(n, check_strength(n, v)) for n, v in spec]
    out = img
    for name, value in steps:
        out = ATTACKS[name](out, value, generator=generator, cover=cover)
    return out


# ----------------------------------------------------------------------------------------------------------------
# nn.Module wrappers
# ----------------------------------------------------------------------------------------------------------------
class GaussianNoise(nn.Module):
    """Module form of :func:`gaussian_noise`."""

    def __init__(self, sigma: float) -> None:
        super().__init__()
        self.sigma = sigma

    def forward(self, img: Tensor, generator: torch.Generator | None = None) -> Tensor:
        return gaussian_noise(img, self.sigma, generator=generator)


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


class Resize(nn.Module):
    """Module form of :func:`resize`."""

    def __init__(self, scale: float) -> None:
        super().__init__()
        self.scale = scale

    def forward(self, img: Tensor) -> Tensor:
        return resize(img, self.scale)


# ----------------------------------------------------------------------------------------------------------------
# training-time random distortion
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class RandomDistortionConfig:
    """Maximum strengths of the training-time distortions (each drawn uniformly up to its maximum)."""

    noise_sigma: float = 0.1
    """Max noise std: sigma ~ U(0, noise_sigma)."""
    rotate_degrees: float = 30.0
    """Max rotation: angle ~ U(-rotate_degrees, rotate_degrees)."""
    crop_share: float = 0.25
    """Max cropout area share: share ~ U(0, crop_share)."""
    blur_sigma: float = 1.0
    """Max blur std in pixels: sigma ~ U(0, blur_sigma)."""
    hue_shift: float = 0.5
    """Max hue shift in turns: shift ~ U(-hue_shift, hue_shift)."""
    jpeg_quality_min: float = 50
    """Lowest JPEG quality: quality ~ U(jpeg_quality_min, 100)."""
    resize_min: float = 0.5
    """Smallest resize scale: scale ~ U(resize_min, 1)."""
    p_identity: float = 0.2
    """Probability that an image is left unchanged."""
    enabled: Tuple[str, ...] = ATTACK_NAMES
    """Names of the distortions to draw from (subset of noise, rotate, crop, blur, hue, jpeg, resize)."""

    def __post_init__(self) -> None:
        self.enabled = tuple(self.enabled)
        bad = [n for n in self.enabled if n not in ATTACKS]
        if bad:
            raise ValueError(f"RandomDistortionConfig.enabled: unknown {bad}; use names from {', '.join(ATTACK_NAMES)}")
        checks = [
            ("noise_sigma", self.noise_sigma >= 0),
            ("rotate_degrees", self.rotate_degrees >= 0),
            ("crop_share", 0 <= self.crop_share <= 1),
            ("blur_sigma", self.blur_sigma >= 0),
            ("hue_shift", 0 <= self.hue_shift <= 0.5),
            ("jpeg_quality_min", 1 <= self.jpeg_quality_min <= 100),
            ("resize_min", 0 < self.resize_min <= 1),
            ("p_identity", 0 <= self.p_identity <= 1),
        ]
        for name, ok in checks:
            if not ok:
                raise ValueError(f"RandomDistortionConfig.{name}={getattr(self, name)!r} is out of range; see its doc")

    def setup(self) -> "RandomDistortion":
        return RandomDistortion(self)


class RandomDistortion(nn.Module):
    """Per image, one randomly chosen enabled distortion at a random strength (or identity w.p. ``p_identity``).

    The training-time augmentation of GeometrySticker (noise, rotation, cropout, blur) plus hue jitter, JPEG
    and resize. It distorts whenever called (train or eval mode); callers decide when to use it. Images that
    draw the same distortion are processed together with per-image strengths. All randomness comes from
    ``generator`` (choices and strengths first, then each distortion's own draws in a fixed order), so a
    seeded generator gives a deterministic result.
    """

    def __init__(self, config: RandomDistortionConfig | None = None) -> None:
        super().__init__()
        self.config = config if config is not None else RandomDistortionConfig()

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tuple[List[str], List[float]]:
        """Draw the per-image distortion names (``"identity"`` for none) and strengths."""
        c = self.config
        u = _rand((batch, 3), generator, torch.device("cpu")).double().tolist()
        names: List[str] = []
        strengths: List[float] = []
        for ui, uc, us in u:
            if not c.enabled or ui < c.p_identity:
                names.append("identity")
                strengths.append(0.0)
                continue
            name = c.enabled[min(int(uc * len(c.enabled)), len(c.enabled) - 1)]
            names.append(name)
            strengths.append(
                {
                    "noise": us * c.noise_sigma,
                    "rotate": (2.0 * us - 1.0) * c.rotate_degrees,
                    "crop": us * c.crop_share,
                    "blur": us * c.blur_sigma,
                    "hue": (2.0 * us - 1.0) * c.hue_shift,
                    "jpeg": c.jpeg_quality_min + us * (100.0 - c.jpeg_quality_min),
                    "resize": c.resize_min + us * (1.0 - c.resize_min),
                }[name]
            )
        return names, strengths

    def forward(
        self,
        img: Float[Tensor, "B 3 H W"],
        cover: Float[Tensor, "B 3 H W"] | None = None,
        generator: torch.Generator | None = None,
    ) -> Float[Tensor, "B 3 H W"]:
        _check_image(img, "RandomDistortion")
        names, strengths = self.sample(img.shape[0], generator)
        out = img.clone()
        for name in ATTACK_NAMES:
            idx = [i for i, n in enumerate(names) if n == name]
            if not idx:
                continue
            sel = torch.tensor(idx, device=img.device, dtype=torch.long)
            s = torch.tensor([strengths[i] for i in idx], device=img.device, dtype=_work(img).dtype)
            cov = cover[sel] if cover is not None else None
            out[sel] = ATTACKS[name](img[sel], s, generator=generator, cover=cov)
        return out
