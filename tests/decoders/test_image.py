"""The informed image decoder (gsticker_plugin/decoders/image.py) on small tensors: the predicted colour change,
its closed-form Jacobian, the fit on 8-bit images, and the null (an image that is the base render decodes to coin
flips). The same decoder on real tiny runs is tested in tests/test_geometry.py."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import synthetic_reference_view

from gsticker_plugin.decoders import cover as C
from gsticker_plugin.decoders import fit as FIT
from gsticker_plugin.decoders import image as I
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.evaluation.leaked_key import leaked_key_attack
from gsticker_plugin.key import parse_message
from gsticker_plugin.sticker import Sticker, composite, message_to_signs

MESSAGE = "101100111000111100001111100000111111000000111111"


def _view(st: Sticker, r: int = 600, s: int = 24, seed: int = 0) -> I.ImageReferenceView:
    base = synthetic_reference_view(st, r, s, seed, with_rgb=True)
    bg = torch.ones(3)
    image = composite(base.density, base.rgb, base.deltas, bg)[0].clamp(0, 1)  # [R 3]: the base render at the rays
    view = dataclasses.replace(
        base, base_signal=torch.zeros(1, r), signals=("accumulation",), image=image.T.reshape(3, 1, r)
    )
    return I.image_reference(view, bg)


def _marked_8_bit():
    """A sticker, a synthetic reference view, the message and the 8-bit marked image at its rays."""
    torch.manual_seed(0)
    st = Sticker(48, 5, 64, 2, 0.5, "bilinear").requires_grad_(False)
    ref = _view(st)
    msg = parse_message(MESSAGE)
    with torch.no_grad():
        marked = torch.round(I.predict_image_change(ref, st, message_to_signs(msg)) * 255) / 255
    return st, ref, msg, marked


def test_prediction_at_zero_is_the_base_render_and_the_jacobian_is_ad():
    torch.manual_seed(0)
    st = Sticker(48, 5, 64, 2, 0.5, "bilinear").requires_grad_(False)
    ref = _view(st, r=80, s=12)
    with torch.no_grad():
        assert torch.allclose(I.predict_image_change(ref, st, torch.zeros(48)), ref.base_rgb, atol=1e-6)
        # a message changes the colour (through the density only)
        assert (
            float(
                (I.predict_image_change(ref, st, message_to_signs(parse_message(MESSAGE))) - ref.base_rgb).abs().max()
            )
            > 1e-3
        )
    s0 = torch.rand(48) * 1.6 - 0.8
    ad = FIT.jacobian(lambda s: I.predict_image_change(ref, st, s).reshape(-1), s0)
    closed = I.image_change_jacobian(ref, st, s0)
    assert closed.shape == ad.shape == (80 * 3, 48)
    assert torch.allclose(closed, ad, atol=1e-6, rtol=1e-4) and float(closed.abs().max()) > 1e-3
    assert I.image_change_jacobian(ref, Sticker(48, 5, 16, 2, 0.5, "concat"), s0) is None


def test_fit_reads_the_message_from_an_8_bit_image_and_the_base_render_reads_no_match():
    st, ref, msg, marked = _marked_8_bit()
    d = I.decode_image_view(ref, st, marked, torch.Generator().manual_seed(1))
    assert torch.equal(d["bits"], msg) and d["undetermined"] == 0 and d["explained"] > 0.9
    # the base render itself: nothing to fit, every bit undetermined and a mismatch whatever the message
    d0 = I.decode_image_view(ref, st, ref.base_rgb.clone(), torch.Generator().manual_seed(2))
    assert d0["undetermined"] == 48 and d0["iterations"] == 0
    assert int((d0["bits"] == msg).sum()) == 0 and int((d0["bits"] == 1 - msg).sum()) == 0


def test_leaked_key_attack_keeps_its_psnr_budget_and_flips_the_bits_once_the_budget_allows():
    """PGD with the owner key: within its L2 (PSNR) budget; a budget far below the mark's own change leaves the
    message readable, one well above it drives most of the decoder's bits to their complement."""
    torch.manual_seed(0)
    st = Sticker(48, 5, 64, 2, 0.5, "bilinear").requires_grad_(False)
    ref = _view(st, r=400)
    msg = parse_message(MESSAGE)
    with torch.no_grad():
        marked = I.predict_image_change(ref, st, message_to_signs(msg))
    image = marked.reshape(1, 400, 3)  # the view is one row of 400 rays (hw = (1, 400))
    mark_psnr = float(-10 * torch.log10(((marked - ref.base_rgb) ** 2).mean()))
    bits = {}
    for budget in (mark_psnr + 30.0, mark_psnr - 12.0):
        x = leaked_key_attack(ref, st, image, budget)
        assert x.shape == image.shape and float(x.min()) >= 0 and float(x.max()) <= 1
        psnr = float(-10 * torch.log10(((x - image) ** 2).mean()))
        assert psnr >= budget - 1e-3
        bits[budget] = I.decode_image_view(ref, st, x.reshape(-1, 3), torch.Generator().manual_seed(1))["bits"]
    weak, strong = bits[mark_psnr + 30.0], bits[mark_psnr - 12.0]
    assert int((weak == msg).sum()) >= 47 and int((strong == msg).sum()) <= 8
    with pytest.raises(GStickerError, match="PSNR budget"):
        leaked_key_attack(ref, st, image, 0.0)


def test_an_image_of_another_size_is_one_line_naming_the_fix():
    with pytest.raises(GStickerError, match="resize them"):
        I.image_at_rays(torch.zeros(4, 5, 3), torch.arange(3), (4, 4))


def _edged_scene():
    """A 24x24 view whose base render is 4 px blocks of random colour (edges), and the marked image [1 3 H W]."""
    torch.manual_seed(0)
    st = Sticker(48, 5, 64, 2, 0.5, "bilinear").requires_grad_(False)
    g = torch.Generator().manual_seed(3)
    h = w = 24
    ref = _view(st, r=h * w, s=16, seed=1)
    base = (torch.rand(3, h // 4, w // 4, generator=g)).repeat_interleave(4, 1).repeat_interleave(4, 2)  # edges
    ref.view.image = base
    ref.view.hw = (h, w)
    ref.base_rgb = base.permute(1, 2, 0).reshape(-1, 3)
    msg = parse_message(MESSAGE)
    with torch.no_grad():
        change = I.predict_image_change(ref, st, message_to_signs(msg)) - I.predict_image_change(
            ref, st, torch.zeros(48)
        )
    marked = (base.permute(1, 2, 0).reshape(-1, 3) + change).reshape(h, w, 3).permute(2, 0, 1)[None]
    return st, ref, base, marked, msg, g


def test_a_blurred_rotated_or_resized_image_is_matched_from_the_base_alone_and_decoded():
    """The degradation is estimated from the base render (never the message); the fit through it reads the bits
    that comparing with the unblurred base loses; the linear part is the attack's own on small changes."""
    st, ref, base, marked, msg, g = _edged_scene()
    h = w = 24
    for deg in (I.Degradation("blur", 1.0), I.Degradation("rotate", 10.0), I.Degradation("resize", 0.5)):
        x = deg.apply(marked)[0].permute(1, 2, 0)
        found, _ = I.match_degradation(x, base)
        assert found == deg
        d = I.decode_degraded_view(ref, st, x, found, torch.Generator().manual_seed(0))
        assert int((d["bits"] == msg).sum()) >= 46 and d["degradation"] == deg.label(), (deg, d)
        small = 0.01 * torch.randn(1, 3, h, w, generator=g)
        lin = deg.apply(0.5 + small) - deg.apply(torch.full_like(small, 0.5))
        assert torch.allclose(lin, deg.linear(small), atol=1e-5), deg
    assert I.match_degradation(marked[0].permute(1, 2, 0), base)[0] == I.Degradation()  # the mark alone: identity
    # JPEG is matched too and read by its luma, which the codec keeps whole (chroma is halved): a small change's
    # luma passes through at high quality, its chroma does not
    jp = I.Degradation("jpeg", 50.0)
    assert I.match_degradation(jp.apply(marked)[0].permute(1, 2, 0), base)[0] == jp
    small = 0.01 * torch.randn(1, 3, h, w, generator=g)
    near = I.Degradation("jpeg", 100.0)
    assert near.luma and not I.Degradation("blur", 1.0).luma
    out = near.apply(0.5 + small) - near.apply(torch.full_like(small, 0.5))

    def y(t):
        return I.observe(t[0].permute(1, 2, 0).reshape(-1), True)

    assert float((y(out) - y(near.linear(small))).abs().mean()) < 0.3 * float(y(small).abs().mean())
    assert float((out - small).abs().mean()) > 0.3 * float(small.abs().mean())  # RGB: chroma resampled away
    x = I.Degradation("jpeg", 100.0).apply(marked)[0].permute(1, 2, 0)
    d = I.decode_selected(ref, st, x, I.match_degradation(x, base)[0], torch.Generator().manual_seed(0))
    assert d["signals"] == ["luma"] and int((d["bits"] == msg).sum()) >= 46, d


def test_images_alone_a_jpeg_is_read_through_the_coded_base_render_and_an_uncoded_image_is_left_alone():
    """The unposed decoder's JPEG reading at the camera it found: the quality whose coding of the base render is
    nearest the image, fitted by luma; an image that is no JPEG gets no such reading."""
    from gsticker_plugin.decoders.unposed import coded_reading

    st, ref, base, marked, msg, _ = _edged_scene()
    coded = I.Degradation("jpeg", 100.0).apply(marked)[0].permute(1, 2, 0)
    d = coded_reading(ref, ref.view, st, coded, torch.Generator().manual_seed(0), 10)
    assert d is not None and d["degradation"] == "jpeg=100" and d["signals"] == ["luma"], d
    assert int((d["bits"] == msg).sum()) >= 46 and d["color_map"] is False
    plain = I.decode_image_view(ref, st, coded.reshape(-1, 3), torch.Generator().manual_seed(0))
    assert int((plain["bits"] == msg).sum()) <= 40  # read in RGB against the uncoded render, the chroma misleads
    assert coded_reading(ref, ref.view, st, marked[0].permute(1, 2, 0), torch.Generator().manual_seed(0), 10) is None


def test_the_fit_with_the_smaller_residual_is_kept_when_a_degradation_was_matched():
    """A wrongly matched transform (a strong mark on a plain scene can make one look closer) loses to the identity
    once both are fitted; a right one wins. The coin flips advance as for one fit."""
    torch.manual_seed(0)
    st = Sticker(48, 5, 64, 2, 0.5, "bilinear").requires_grad_(False)
    g = torch.Generator().manual_seed(3)
    h = w = 24
    ref = _view(st, r=h * w, s=16, seed=1)
    base = (torch.rand(3, h // 4, w // 4, generator=g)).repeat_interleave(4, 1).repeat_interleave(4, 2)
    ref.view.image, ref.view.hw, ref.base_rgb = base, (h, w), base.permute(1, 2, 0).reshape(-1, 3)
    msg = parse_message(MESSAGE)
    with torch.no_grad():
        change = I.predict_image_change(ref, st, message_to_signs(msg)) - I.predict_image_change(
            ref, st, torch.zeros(48)
        )
    marked = (ref.base_rgb + change).reshape(h, w, 3)
    wrong = I.decode_selected(ref, st, marked, I.Degradation("jpeg", 10.0), torch.Generator().manual_seed(0))
    assert wrong["degradation"] == "none" and int((wrong["bits"] == msg).sum()) == 48
    assert wrong["residual_cost_none"] < wrong["residual_cost_matched"]
    blur = I.Degradation("blur", 1.0)
    blurred = blur.apply(marked.permute(2, 0, 1)[None])[0].permute(1, 2, 0)
    gen = torch.Generator().manual_seed(0)
    right = I.decode_selected(ref, st, blurred, blur, gen)
    assert right["degradation"] == "blur=1" and int((right["bits"] == msg).sum()) >= 46
    one = torch.Generator().manual_seed(0)
    I.decode_degraded_view(ref, st, blurred, blur, one)
    assert torch.equal(gen.get_state(), one.get_state())


def test_a_hue_shifted_image_is_read_by_its_value_channel():
    """V = max(R, G, B) is exactly invariant under the HSV hue shift: the V-channel fit reads a hue-shifted marked
    image as well as the unshifted one, where the RGB fit cannot; the V mode is chosen from image and base only."""
    from gsticker_plugin.attacks import hue_shift

    torch.manual_seed(0)
    st = Sticker(48, 5, 64, 2, 0.5, "bilinear").requires_grad_(False)
    h = w = 24
    ref = _view(st, r=h * w, s=16, seed=1)
    msg = parse_message(MESSAGE)
    with torch.no_grad():
        marked_rays = I.predict_image_change(ref, st, message_to_signs(msg))
    marked = marked_rays.reshape(h, w, 3)
    base = ref.base_rgb.reshape(h, w, 3).permute(2, 0, 1)
    shifted = hue_shift(marked.permute(2, 0, 1)[None], 0.3)[0].permute(1, 2, 0)
    assert I.reads_value(shifted, base) and not I.reads_value(marked, base)
    as_value = I.decode_image_view(ref, st, shifted.reshape(-1, 3), torch.Generator().manual_seed(0), value=True)
    as_rgb = I.decode_image_view(ref, st, shifted.reshape(-1, 3), torch.Generator().manual_seed(0))
    assert as_value["signals"] == ["value"] and int((as_value["bits"] == msg).sum()) >= 46, as_value
    assert int((as_rgb["bits"] == msg).sum()) < int((as_value["bits"] == msg).sum()) - 4
    # unmarked but hue-shifted: V is unchanged, so nothing is read (every bit undetermined, a mismatch)
    clean = hue_shift(base[None], 0.3)[0].permute(1, 2, 0)
    none = I.decode_image_view(ref, st, clean.reshape(-1, 3), torch.Generator().manual_seed(0), value=True)
    assert none["undetermined"] == 48 and int((none["bits"] == msg).sum()) == 0


def test_pixels_a_cropout_filled_are_left_out_of_the_fit_and_the_message_still_reads(monkeypatch):
    st, ref, msg, marked = _marked_8_bit()
    cropped = marked.clone()
    cropped[200:400] = 1.0  # a third of the image filled white
    far = (cropped - ref.base_rgb).abs().amax(dim=-1) > I.OCCLUSION_CHANGE
    assert float(far.double().mean()) > 0.05
    d = I.decode_image_view(ref, st, cropped, torch.Generator().manual_seed(1))
    assert torch.equal(d["bits"], msg)
    assert 0.5 * float(far.double().mean()) <= d["occluded_share"] <= float(far.double().mean()) + 1e-9
    # the same fit over every pixel (no occlusion rule) is pulled off by the fill
    monkeypatch.setattr(I, "OCCLUSION_SHARE", 2.0)
    monkeypatch.setattr(C, "COVER_Z", 1e9)
    d_all = I.decode_image_view(ref, st, cropped, torch.Generator().manual_seed(1))
    assert d_all["occluded_share"] == 0.0 and int((d_all["bits"] == msg).sum()) < 44
    # an unoccluded image keeps every row
    assert I.decode_image_view(ref, st, marked, torch.Generator().manual_seed(1))["occluded_share"] == 0.0


def test_noise_that_pushes_single_pixels_far_from_the_base_is_not_taken_for_an_occlusion():
    """Scattered pixels far from the base render (noise 0.1) stay in the fit: only patches count as occluded."""
    st = Sticker(48, 5, 64, 2, 0.5, "bilinear").requires_grad_(False)
    ref = _view(st)
    noisy = ref.base_rgb + 0.1 * torch.randn(ref.base_rgb.shape, generator=torch.Generator().manual_seed(4))
    far = (noisy - ref.base_rgb).abs().amax(dim=-1) > I.OCCLUSION_CHANGE
    assert float(far.double().mean()) > I.OCCLUSION_SHARE  # every far pixel counted, the old rule would fire
    d = I.decode_image_view(ref, st, noisy, torch.Generator().manual_seed(1))
    assert d["occluded_share"] == 0.0


def test_a_stretch_pasted_from_the_base_render_is_left_out_of_the_second_fit(monkeypatch):
    """A cropout that pastes the unmarked render (no occlusion to see) removes the mark from a stretch of the image:
    the covered-rectangle rule finds the stretch after the first fit and reads the message from the rest."""
    st, ref, msg, marked = _marked_8_bit()
    pasted = marked.clone()
    pasted[150:450] = torch.round(ref.base_rgb[150:450] * 255) / 255
    d = I.decode_image_view(ref, st, pasted, torch.Generator().manual_seed(1))
    assert abs(d["covered_share"] - 0.5) < 0.05 and d["occluded_share"] == 0.0
    assert int((d["bits"] == msg).sum()) >= 46
    monkeypatch.setattr(C, "COVER_Z", 1e9)  # the rule off: one fit over every pixel
    d_all = I.decode_image_view(ref, st, pasted, torch.Generator().manual_seed(1))
    assert d_all["covered_share"] == 0.0 and int((d_all["bits"] == msg).sum()) < int((d["bits"] == msg).sum())
    # the whole mark there: nothing is left out
    assert I.decode_image_view(ref, st, marked, torch.Generator().manual_seed(1))["covered_share"] == 0.0
