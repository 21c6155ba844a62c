"""A colour map per material (an affine change of RGB for each of a few colour clusters, softly assigned), fitted
from the owner's base to an image of a recoloured copy, on the base's own samples.

A palette edit, a hue turn or a colour fine-tune changes the colour every *sample* of the model renders; a pixel is a
composite of many samples, so a map of pixel colours cannot undo it near surfaces, where the mark is. This map acts on
the sample colours: ``g(c) = c + sum_k a_k(c) (A_k c + b_k)``, ``a`` the soft assignment of ``c`` to the clusters of
the base render's colours (CIELab, as ``ns-recolor palette``'s), and the image minus the base render is linear in the
``A_k, b_k``: a ridge least-squares fit. The fit sees the image and the base only, never the owner's message.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Iterator, Tuple

import torch
from jaxtyping import Float
from torch import Tensor

from gsticker_plugin.recolor.model import ColorWrap, color_fields
from gsticker_plugin.recolor.palette import extract_palette, palette_weights, rgb_to_lab

COLOR_MAP_MARGIN = 0.25
"""An image is read through a colour map when the map leaves at most this share of the squared difference between
the image and the base render at the rays (a recolouring moves whole materials; the mark and a small pose error it
cannot map)."""

MAP_SEARCH_SHARE = 0.15
"""The camera search goes on through a colour map of the base's samples when that map explains at least this share
of the image's difference from the base render at the camera found on V (a recolouring moves V too: the search on
V stops a few tenths of a degree off, where a pose error leaves the map little to explain)."""


@dataclass
class ColorMap:
    """Per-cluster affine changes of sample colours (``centres_lab [K 3]``, ``theta [K 4 3]``: ``A_k^T`` over
    ``b_k``)."""

    centres_lab: Float[Tensor, "K 3"]
    softness: float
    theta: Float[Tensor, "K 4 3"]

    def __call__(self, rgb: Float[Tensor, "... 3"]) -> Float[Tensor, "... 3"]:
        """``rgb`` (any leading shape) through the map, clamped to [0, 1]."""
        return (rgb + material_change(self, rgb)).clamp(0.0, 1.0)


def material_features(
    centres_lab: Float[Tensor, "K 3"], softness: float, rgb: Float[Tensor, "... 3"]
) -> Float[Tensor, "... K 4"]:
    """Each colour's soft assignment to the clusters times ``[r, g, b, 1]``: what the map's change is linear in."""
    a = palette_weights(rgb_to_lab(rgb.float().clamp(0.0, 1.0)), centres_lab, softness).to(rgb.dtype)
    ones = torch.ones_like(rgb[..., :1])
    return a[..., :, None] * torch.cat([rgb, ones], dim=-1)[..., None, :]


def material_change(cmap: ColorMap, rgb: Float[Tensor, "... 3"]) -> Float[Tensor, "... 3"]:
    """``g(c) - c`` before clamping."""
    f = material_features(cmap.centres_lab, cmap.softness, rgb)
    return torch.einsum("...kj,kjc->...c", f, cmap.theta.to(rgb.dtype))


def identity_map(centres_lab: Float[Tensor, "K 3"], softness: float = 5.0) -> ColorMap:
    """The map that changes nothing."""
    return ColorMap(centres_lab, softness, torch.zeros(centres_lab.shape[0], 4, 3, dtype=torch.float64))


def scene_clusters(pixels_rgb: Float[Tensor, "N 3"], k: int = 8, seed: int = 0) -> Float[Tensor, "K 3"]:
    """Cluster centres (CIELab) of a render's colours, as ``ns-recolor palette`` extracts its palette."""
    return extract_palette(pixels_rgb.float(), k=k, seed=seed).lab


def composited_features(
    sample_rgb: Float[Tensor, "R S 3"],
    sample_weights: Float[Tensor, "R S 1"],
    centres_lab: Float[Tensor, "K 3"],
    softness: float,
) -> Float[Tensor, "R F"]:
    """The map's features of every sample composited along each ray with the render weights (``F = 4K``): the
    change of the render at a ray is these times ``theta``, per output channel."""
    f = material_features(centres_lab, softness, sample_rgb.double())  # [R S K 4]
    return (sample_weights.double()[..., None] * f).sum(dim=1).reshape(sample_rgb.shape[0], -1)


def map_columns(
    sample_rgb: Float[Tensor, "R S 3"], sample_weights: Float[Tensor, "R S 1"], cmap: ColorMap
) -> Float[Tensor, "M P"]:
    """d (render at the rays) / d ``theta``, rows ``r * 3 + c`` (``M = 3R``, ``P = 12K``): a change of the map the
    image decoder fits beside the message."""
    x = composited_features(sample_rgb, sample_weights, cmap.centres_lab, cmap.softness)  # [R F]
    r, f = x.shape
    cols = torch.zeros(r, 3, f, 3, dtype=x.dtype)
    for c in range(3):
        cols[:, c, :, c] = x
    return cols.reshape(r * 3, f * 3)


def fit_color_map(
    sample_rgb: Float[Tensor, "R S 3"],
    sample_weights: Float[Tensor, "R S 1"],
    change: Float[Tensor, "R 3"],
    centres_lab: Float[Tensor, "K 3"],
    softness: float = 5.0,
    ridge: float = 1e-3,
) -> ColorMap:
    """The map whose change of the samples' colours, composited with their render weights, is nearest ``change``
    (image minus base render at the rays): ridge least squares (``ridge`` relative to the mean feature energy)."""
    x = composited_features(sample_rgb, sample_weights, centres_lab, softness)  # [R 4K]
    a = x.T @ x
    lam = ridge * float(torch.diagonal(a).mean()) + 1e-12
    theta = torch.linalg.solve(a + lam * torch.eye(a.shape[0], dtype=a.dtype), x.T @ change.double())
    return ColorMap(centres_lab, softness, theta.reshape(centres_lab.shape[0], 4, 3))


def fit_to_change(
    sample_rgb: Float[Tensor, "R S 3"],
    sample_weights: Float[Tensor, "R S 1"],
    change: Float[Tensor, "R 3"],
    centres_lab: Float[Tensor, "K 3"],
) -> Tuple[ColorMap, float, float]:
    """:func:`fit_color_map`, with the mean squared ``change`` (per channel) before the map and what the map leaves of
    it."""
    before = float((change.double() ** 2).mean())
    cmap = fit_color_map(sample_rgb, sample_weights, change, centres_lab)
    fitted = (sample_weights.double() * (cmap(sample_rgb.double()) - sample_rgb.double())).sum(dim=1)
    return cmap, before, float(((change.double() - fitted) ** 2).mean())


@contextlib.contextmanager
def mapped_colors(model, cmap: ColorMap) -> Iterator[None]:
    """Within the block ``model`` renders every sample's colour through ``cmap`` (before compositing, as ``ns-recolor``
    edits a run); the model is unchanged after it."""
    wraps = [ColorWrap(f, cmap) for _, f in color_fields(model)]
    try:
        yield
    finally:
        for w in reversed(wraps):
            w.remove()
