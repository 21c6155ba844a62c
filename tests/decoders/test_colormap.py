"""The colour map per material fitted on the base's samples (gsticker_plugin.decoders.colormap) and its use by the
decoder for images without cameras (gsticker_plugin.decoders.unposed.recolouring)."""

import torch
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.base_field import Field

from gsticker_plugin.background import Background
from gsticker_plugin.decoders.colormap import (
    ColorMap,
    composited_features,
    fit_color_map,
    identity_map,
    map_columns,
    mapped_colors,
    material_change,
    scene_clusters,
)
from gsticker_plugin.decoders.image import ImageReferenceView
from gsticker_plugin.decoders.reference import ReferenceView
from gsticker_plugin.decoders.unposed import mapped_reference, reading, recolouring
from gsticker_plugin.recolor.palette import recolor, rgb_to_lab
from gsticker_plugin.sticker import render_weights

MATERIALS = torch.tensor([[0.9, 0.8, 0.1], [0.2, 0.2, 0.2], [0.8, 0.2, 0.1], [0.3, 0.5, 0.8]])


def scene(rays: int = 400, samples: int = 6, seed: int = 0):
    """Rays through a few materials: per ray one material under a shading, samples of it with noise, an opaque
    surface behind some thin ones; returns the reference view and its render."""
    g = torch.Generator().manual_seed(seed)
    pick = torch.randint(0, MATERIALS.shape[0], (rays,), generator=g)
    shade = 0.5 + 0.5 * torch.rand(rays, 1, 1, generator=g)
    rgb = (MATERIALS[pick][:, None, :] * shade + 0.02 * torch.randn(rays, samples, 3, generator=g)).clamp(0, 1)
    density = torch.rand(rays, samples, 1, generator=g) * 2.0
    density[:, -1] = 50.0
    deltas = torch.full((rays, samples, 1), 0.1)
    w = render_weights(density, deltas)
    image = ((w * rgb).sum(1) + (1 - w.sum(1))).clamp(0, 1)  # white background
    side = int(rays**0.5)
    view = ReferenceView(
        name="t",
        hw=(side, rays // side),
        rays=torch.arange(rays),
        density=density,
        deltas=deltas,
        steps=torch.cumsum(deltas, dim=1),
        open_index=torch.arange(0, rays * samples, samples),
        psi_scale=torch.ones(rays, 1),
        features=torch.zeros(rays, 4),
        base_signal=torch.zeros(1, rays),
        depth_scale=1.0,
        signals=("accumulation",),
        image=image.T.reshape(3, side, rays // side),
        rgb=rgb,
    )
    return view, image


def test_the_identity_map_changes_nothing():
    rgb = torch.rand(50, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert torch.equal(identity_map(rgb_to_lab(MATERIALS)).__call__(rgb), rgb)


def test_fit_recovers_a_palette_edit_of_the_samples_from_the_composited_render():
    """The samples' colours recoloured (entry 0 to blue), composited: the fitted map explains the render's change."""
    view, image = scene()
    src = rgb_to_lab(MATERIALS)
    tgt = src.clone()
    tgt[0] = rgb_to_lab(torch.tensor([[0.1, 0.2, 0.9]]))[0]
    w = render_weights(view.density, view.deltas)
    recoloured = ((w * recolor(view.rgb, src, tgt, 5.0)).sum(1) + (1 - w.sum(1))).clamp(0, 1)
    change = recoloured - image
    cmap = fit_color_map(view.rgb, w, change, scene_clusters(image, k=4))
    fitted = (w.double() * (cmap(view.rgb.double()) - view.rgb.double())).sum(1)
    left = float(((change - fitted) ** 2).mean() / (change**2).mean())
    assert float((change**2).mean()) > 1e-3  # the edit moved the render
    assert left < 0.05


def test_map_columns_are_the_renders_derivative_in_the_map():
    view, _ = scene(rays=30)
    w = render_weights(view.density, view.deltas)
    cmap = ColorMap(rgb_to_lab(MATERIALS), 5.0, 0.01 * torch.randn(4, 4, 3, generator=torch.Generator().manual_seed(1)))
    theta = cmap.theta.double()
    render_change = (w.double() * material_change(cmap, view.rgb.double())).sum(1)  # before the colour clamp
    cols = map_columns(view.rgb, w, cmap)
    assert cols.shape == (30 * 3, 4 * 4 * 3)
    # the columns are laid out [feature, channel]: theta flattened the same way gives the change
    assert torch.allclose(cols @ theta.reshape(-1), render_change.reshape(-1), atol=1e-6)
    x = composited_features(view.rgb, w, cmap.centres_lab, cmap.softness)
    assert torch.allclose(x @ theta.reshape(-1, 3), render_change, atol=1e-6)


def test_recoloured_images_are_read_through_a_map_and_marked_ones_are_not():
    view, image = scene(rays=400)
    ref = ImageReferenceView(view=view, background=Background.of(torch.ones(3)), base_rgb=image.float())
    h, w_ = view.hw
    as_image = lambda x: x.reshape(h, w_, 3)  # noqa: E731
    faint = image + 0.005 * torch.randn(image.shape, generator=torch.Generator().manual_seed(2))  # a mark-sized change
    assert recolouring(as_image(faint), ref) is None
    src = rgb_to_lab(MATERIALS)
    tgt = src.clone()
    tgt[2] = rgb_to_lab(torch.tensor([[0.2, 0.8, 0.2]]))[0]
    wts = render_weights(view.density, view.deltas)
    recoloured = ((wts * recolor(view.rgb, src, tgt, 5.0)).sum(1) + (1 - wts.sum(1))).clamp(0, 1)
    cmap = recolouring(as_image(recoloured), ref)
    assert cmap is not None
    mapped = mapped_reference(ref, cmap)
    before = float(((recoloured - image) ** 2).mean())
    after = float(((recoloured - mapped.base_rgb) ** 2).mean())
    assert after < 0.1 * before  # the mapped reference renders the recoloured image


def test_a_palette_edit_that_keeps_v_is_read_through_the_map_and_a_hue_turn_by_v():
    """Yellow to blue keeps each sample's V, so the image's V barely moves, yet V's Jacobian (the dominant channel)
    is wrong for it: the map wins; an image-level hue turn leaves V exactly: V wins."""
    import kornia

    view, image = scene(rays=400)
    ref = ImageReferenceView(view=view, background=Background.of(torch.ones(3)), base_rgb=image.float())
    h, w_ = view.hw
    as_image = lambda x: x.reshape(h, w_, 3)  # noqa: E731
    src = rgb_to_lab(MATERIALS)
    tgt = src.clone()
    tgt[0] = rgb_to_lab(torch.tensor([[0.1, 0.2, 0.9]]))[0]
    wts = render_weights(view.density, view.deltas)
    palette = ((wts * recolor(view.rgb, src, tgt, 5.0)).sum(1) + (1 - wts.sum(1))).clamp(0, 1)
    value, cmap = reading(as_image(palette), ref, True, True)
    assert not value and cmap is not None
    turned = kornia.enhance.adjust_hue(as_image(image).permute(2, 0, 1), 1.5).permute(1, 2, 0)
    value, cmap = reading(turned, ref, True, True)
    assert value and cmap is None
    assert reading(as_image(palette), ref, True, False) == (True, None)  # no map asked for: as told


class ColourField(Field):
    """A field whose per-sample RGB is its input (a stand-in for a model's colour field)."""

    def get_density(self, ray_samples):
        return torch.ones_like(ray_samples[..., :1]), None

    def get_outputs(self, ray_samples, density_embedding=None):
        return {FieldHeadNames.RGB: ray_samples}


def test_mapped_colors_takes_every_sample_through_the_map_inside_the_block_only():
    """The camera search renders the base through a fitted map of its sample colours; the model is itself again
    after the block."""
    model = torch.nn.Module()
    model.field = ColourField()
    g = torch.Generator().manual_seed(3)
    centres = rgb_to_lab(MATERIALS)
    cmap = ColorMap(centres, 5.0, 0.2 * torch.randn(4, 4, 3, generator=g, dtype=torch.float64))
    rgb = torch.rand(7, 5, 3, generator=g)
    with mapped_colors(model, cmap):
        inside = model.field.get_outputs(rgb)[FieldHeadNames.RGB]
    after = model.field.get_outputs(rgb)[FieldHeadNames.RGB]
    assert torch.allclose(inside, cmap(rgb.double()).float(), atol=1e-6)
    assert (inside - rgb).abs().max() > 0.05
    assert torch.equal(after, rgb) and "get_outputs" not in model.field.__dict__
