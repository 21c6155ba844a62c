"""The ``name=strength`` interface: the attack registry, strength ranges, the spec parser and ``apply_attacks``."""

from __future__ import annotations

import math
from typing import Callable, Dict, Iterable, List, Tuple

import torch
from jaxtyping import Float
from torch import Tensor

from gsticker_plugin.attacks.geometric import cropout, resize, rotate
from gsticker_plugin.attacks.valuemetric import gaussian_blur, gaussian_noise, hue_shift, jpeg

ATTACK_NAMES: Tuple[str, ...] = ("noise", "rotate", "crop", "blur", "hue", "jpeg", "resize")


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
            raise ValueError(f"attack {name!r}: {raw!r} is not a number; write e.g. '{_RANGES[name][2]}'") from None
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
