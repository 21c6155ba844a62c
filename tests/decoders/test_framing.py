"""How a picture is framed against a render (gsticker_plugin/decoders/framing.py), on synthetic renders: zooms,
crops and letterboxes of other aspect ratios, stretched and re-exposed copies, and a picture of something else."""

import math

import pytest
import torch
import torch.nn.functional as F

from gsticker_plugin.decoders.framing import Framing, coarse_framing, find_framing, warp_render


def _render(seed: int = 0, size: int = 80) -> torch.Tensor:
    """A smooth random texture (what a render of a scene looks like to a correlation), [size size 3] in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 3, size // 8, size // 8, generator=g)
    x = F.interpolate(x, size=(size, size), mode="bicubic", align_corners=False)
    x = x + 0.15 * F.interpolate(
        torch.rand(1, 3, size // 3, size // 3, generator=g), size=(size, size), mode="bilinear"
    )
    return x[0].permute(1, 2, 0).clamp(0, 1)


@pytest.mark.parametrize(
    "truth, size",
    [
        (Framing(1.0, 1.0, 0.0, 0.0), (80, 80)),  # the render itself
        (Framing(1.6, 1.6, -20.3, -35.7), (72, 128)),  # a 16:9 crop of a zoomed render
        (Framing(0.7, 0.7, 12.4, 3.2), (62, 90)),  # a smaller copy letterboxed into a wider frame
        (Framing(2.4, 2.4, -40.0, -60.5), (150, 110)),  # an upscaled portrait crop
        (Framing(1.25, 1.1, -4.6, 2.2), (90, 100)),  # a stretched copy
    ],
)
def test_the_framing_of_a_zoomed_cropped_or_stretched_picture_is_found_to_a_fraction_of_a_pixel(truth, size):
    render = _render()
    picture, seen = warp_render(render, truth, *size)
    picture = torch.where(seen[..., None] > 0, picture, torch.ones_like(picture))  # padding: white bars
    found = find_framing(picture, render)
    h, w = size
    # where the render's corners land in the picture, found against true
    for u, v in ((0, 0), (80, 0), (0, 80), (80, 80)):
        ut, vt = truth.sx * u + truth.tx, truth.sy * v + truth.ty
        uf, vf = found.sx * u + found.tx, found.sy * v + found.ty
        assert math.hypot(uf - ut, vf - vt) < 0.3 * max(truth.sx, truth.sy), (found, truth)
    assert found.score > 0.99


def test_a_recoloured_and_re_exposed_copy_frames_the_same_way():
    render = _render(1)
    truth = Framing(1.3, 1.3, -9.0, -14.0)
    picture, _ = warp_render(render, truth, 80, 96)
    picture = (0.6 * picture.flip(-1) + 0.2).clamp(0, 1)  # channels swapped, darker, lifted blacks
    found = find_framing(picture, render)
    assert abs(found.sx - truth.sx) < 0.01 and abs(found.tx - truth.tx) < 0.5 and abs(found.ty - truth.ty) < 0.5


def test_a_picture_of_something_else_correlates_far_less_than_a_framed_render():
    render, other = _render(2), _render(3)
    framed, _ = warp_render(render, Framing(1.2, 1.2, -5.0, -5.0), 80, 80)
    assert coarse_framing(framed, render).score > 0.95
    assert coarse_framing(other, render).score < 0.8
