"""The colour map fitted from a base render to a recoloured image (gsticker_plugin.decoders.colormap)."""

import torch

from gsticker_plugin.decoders.colormap import apply_color_map, fit_color_map, identity_table
from gsticker_plugin.recolor.palette import hue_rotate, recolor, rgb_to_lab


def test_identity_table_maps_every_colour_to_itself():
    rgb = torch.rand(500, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert torch.allclose(apply_color_map(identity_table(5), rgb), rgb, atol=1e-12)


def test_fit_recovers_a_palette_edit_on_colours_it_never_saw():
    g = torch.Generator().manual_seed(1)
    src = torch.rand(4000, 3, generator=g)
    source_lab = rgb_to_lab(torch.tensor([[0.9, 0.8, 0.1], [0.2, 0.2, 0.2], [0.8, 0.2, 0.1]]))
    target_lab = rgb_to_lab(torch.tensor([[0.1, 0.3, 0.9], [0.2, 0.2, 0.2], [0.8, 0.2, 0.1]]))
    tgt = recolor(src, source_lab, target_lab, 20.0)
    table = fit_color_map(src, tgt, nodes=8, smooth=1e-4)
    held = torch.rand(1000, 3, generator=g)
    err = (apply_color_map(table, held) - recolor(held, source_lab, target_lab, 20.0)).abs()
    moved = (recolor(held, source_lab, target_lab, 20.0) - held).abs()
    assert float(moved.mean()) > 0.05  # the edit is not a no-op
    assert float(err.mean()) < 0.15 * float(moved.mean())


def test_fit_of_an_unchanged_image_is_the_identity_and_a_hue_turn_is_not():
    g = torch.Generator().manual_seed(2)
    src = torch.rand(2000, 3, generator=g)
    same = fit_color_map(src, src)
    assert float((same - identity_table(6)).abs().max()) < 1e-6
    turned = fit_color_map(src, hue_rotate(src, 0.25), nodes=8, smooth=1e-4)
    held = torch.rand(500, 3, generator=g)
    err = (apply_color_map(turned, held) - hue_rotate(held, 0.25)).abs().mean()
    assert float(err) < 0.2 * float((hue_rotate(held, 0.25) - held).abs().mean())


def test_colours_the_image_never_shows_stay_where_they_were():
    """A fit on dark colours only leaves bright ones (far from any data) at the identity."""
    g = torch.Generator().manual_seed(3)
    dark = torch.rand(1000, 3, generator=g) * 0.3
    table = fit_color_map(dark, (dark * 0.5).clamp(0, 1), nodes=6)
    bright = torch.tensor([[0.95, 0.95, 0.95], [1.0, 0.9, 0.95]])
    assert float((apply_color_map(table, bright) - bright).abs().max()) < 0.1
    assert float((apply_color_map(table, dark[:10]) - dark[:10] * 0.5).abs().max()) < 0.03
