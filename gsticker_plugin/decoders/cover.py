"""A covered rectangle: the axis-aligned part of an image where the mark a fit predicts is missing.

A cropout that pastes an unmarked render of the same camera into a rectangle leaves pixels that look like the base
render there: no occlusion (:func:`gsticker_plugin.decoders.image.occlusion_keep` sees nothing far from the base),
only the mark gone. The fit over the whole image then mixes the bits through the missing rows. After a first fit,
every pixel's gain from predicting no mark (``|change - mark|^2 - |change|^2``, positive where the image holds less
of the mark than predicted) is summed over the best rectangle (:func:`max_sum_rectangle`); the rectangle is left out
of a second fit when that sum stands far above what the residual's noise can make (:data:`COVER_Z`). The rule sees
the image, the base and the sticker only, never the message (docs/experiments/verify-notes.md).
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from torch import Tensor

COVER_Z = 8.0
"""A rectangle is left out when its gain is at least this many standard deviations of what the residual's noise
gives the same predicted mark (``2 sigma sqrt(sum mark^2)`` over it); lego100's paper attacks other than cropout stay
below 5, a 25 % cropout of a clean render reaches 24-36."""

COVER_MIN_SHARE = 0.01
"""... and when it covers at least this share of the image (a few pixels are noise or an edge)."""

COVER_GRID = 100
"""The gain map is summed in square blocks until its longer side is at most this many cells (the search is
``O(H^2 W)``)."""

Rectangle = Tuple[int, int, int, int]
"""``(top, bottom, left, right)``: rows ``top:bottom`` and columns ``left:right``."""


def max_sum_rectangle(g: Float[Tensor, "H W"]) -> Tuple[float, Optional[Rectangle]]:
    """The axis-aligned rectangle of ``g`` with the largest sum and that sum (Kadane's rule along the columns for every
    pair of rows); ``(0.0, None)`` when no entry is positive."""
    h, w = g.shape
    g = g.double()
    rows = torch.cat([torch.zeros(1, w, dtype=g.dtype), g.cumsum(0)])  # rows[b] - rows[t]: sum of rows t..b-1
    best: Tuple[float, Optional[Rectangle]] = (0.0, None)
    for top in range(h):
        band = rows[top + 1 :] - rows[top]  # [H - top, W]: one row per bottom
        c = torch.cat([torch.zeros(band.shape[0], 1, dtype=g.dtype), band.cumsum(1)], dim=1)  # [B, W + 1]
        lowest = torch.cummin(c, dim=1).values
        d = c[:, 1:] - lowest[:, :-1]  # best sum ending at each right edge
        k = int(d.reshape(-1).argmax())
        b, right = divmod(k, w)
        if float(d[b, right]) > best[0]:
            left = int(c[b, : right + 1].argmin())
            best = (float(d[b, right]), (top, top + b + 1, left, right + 1))
    return best


def _block_sum(x: Float[Tensor, "H W"], f: int) -> Float[Tensor, "h w"]:
    h, w = x.shape
    x = F.pad(x, (0, -w % f, 0, -h % f))
    return F.avg_pool2d(x[None, None], f, divisor_override=1)[0, 0]


def covered_pixels(
    change: Float[Tensor, "P C"],
    mark: Float[Tensor, "P C"],
    pixels: Int[Tensor, " P"],
    hw: Tuple[int, int],
) -> Optional[Bool[Tensor, " P"]]:
    """Which of ``pixels`` (flat indices into an ``hw`` image; ``change``: image minus base render there, ``mark``:
    the change the fitted message predicts, one or three rows per pixel) lie in the rectangle where the mark is missing,
    when that rectangle passes :data:`COVER_Z` and :data:`COVER_MIN_SHARE`; None otherwise."""
    if pixels.numel() == 0:
        return None
    change, mark = change.double().reshape(pixels.numel(), -1), mark.double().reshape(pixels.numel(), -1)
    h, w = hw
    gain = torch.zeros(h * w, dtype=torch.float64).index_copy(0, pixels, ((change - mark) ** 2 - change**2).sum(-1))
    energy = torch.zeros(h * w, dtype=torch.float64).index_copy(0, pixels, (mark**2).sum(-1))
    f = max(1, math.ceil(max(h, w) / COVER_GRID))
    gain, energy = _block_sum(gain.view(h, w), f), _block_sum(energy.view(h, w), f)
    score, rect = max_sum_rectangle(gain)
    if rect is None:
        return None
    top, bottom, left, right = (v * f for v in rect)
    sigma = float((change - mark).pow(2).mean().sqrt())
    spread = 2.0 * sigma * float(energy[rect[0] : rect[1], rect[2] : rect[3]].sum()) ** 0.5
    if (bottom - top) * (right - left) < COVER_MIN_SHARE * h * w or score < COVER_Z * spread:
        return None
    y, x = pixels // w, pixels % w
    return (y >= top) & (y < bottom) & (x >= left) & (x < right)
