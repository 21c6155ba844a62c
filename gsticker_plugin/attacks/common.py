"""What every attack shares: the image check, the working dtype, per-image strengths and seeded random draws."""

from __future__ import annotations

from typing import Sequence, Union

import torch
from torch import Tensor

Strength = Union[float, Tensor]


def check_image(img: Tensor, fn: str) -> None:
    if not isinstance(img, Tensor) or img.ndim != 4 or img.shape[1] != 3 or not img.is_floating_point():
        shape = tuple(img.shape) if isinstance(img, Tensor) else type(img).__name__
        raise ValueError(f"{fn}: expected a float image tensor of shape (B, 3, H, W) in [0, 1], got {shape}")


def working(img: Tensor) -> Tensor:
    """The image in the dtype the computation runs in (float32 for half precision inputs)."""
    return img.float() if img.dtype in (torch.float16, torch.bfloat16) else img


def finish(out: Tensor, like: Tensor, clamp: bool = True) -> Tensor:
    return (out.clamp(0.0, 1.0) if clamp else out).to(like.dtype)


def per_image(value: Strength, img: Tensor) -> Tensor:
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


def rand_on(shape: Sequence[int], generator: torch.Generator | None, device: torch.device) -> Tensor:
    """Uniform [0, 1) float32 numbers drawn on the generator's device (or ``device``), moved to ``device``."""
    dev = generator.device if generator is not None else device
    return torch.rand(tuple(shape), generator=generator, device=dev, dtype=torch.float32).to(device)


def randn_on(shape: Sequence[int], generator: torch.Generator | None, device: torch.device) -> Tensor:
    dev = generator.device if generator is not None else device
    return torch.randn(tuple(shape), generator=generator, device=dev, dtype=torch.float32).to(device)


def is_number(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)
