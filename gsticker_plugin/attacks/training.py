"""The training-time random distortion between the renderer and the extractor."""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Tuple

import torch
from jaxtyping import Float
from torch import Tensor, nn

from gsticker_plugin.attacks.common import check_image, rand_on, working
from gsticker_plugin.attacks.spec import ATTACK_NAMES, ATTACKS


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
        u = rand_on((batch, 3), generator, torch.device("cpu")).double().tolist()
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
        check_image(img, "RandomDistortion")
        names, strengths = self.sample(img.shape[0], generator)
        out = img.clone()
        for name in ATTACK_NAMES:
            idx = [i for i, n in enumerate(names) if n == name]
            if not idx:
                continue
            sel = torch.tensor(idx, device=img.device, dtype=torch.long)
            s = torch.tensor([strengths[i] for i in idx], device=img.device, dtype=working(img).dtype)
            cov = cover[sel] if cover is not None else None
            out[sel] = ATTACKS[name](img[sel], s, generator=generator, cover=cov)
        return out
