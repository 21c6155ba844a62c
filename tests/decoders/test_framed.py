"""The camera of a picture framed in any way (gsticker_plugin/decoders/framed.py), on the analytic scene of
test_pose.py: bars cut, framings turned into cameras and back, and the camera of crops, zooms and letterboxes of
other aspect ratios found against the base."""

from __future__ import annotations

import math

import torch
from test_pose import TexturedSquare, orbit, reference

from gsticker_plugin.decoders import framed as FR
from gsticker_plugin.decoders import pose as P
from gsticker_plugin.decoders.framing import Framing


def test_projection_follows_a_zoomed_camera_with_a_moved_principal_point():
    """The pixel motion of the framing's parameters equals projecting into the camera :func:`moved_camera` builds."""
    cam = orbit(8)[2:3]
    pts = torch.randn(20, 3) * 0.5
    delta = torch.tensor([0.01, -0.02, 0.015, 0.01, 0.005, -0.01, 0.05, 1.5, -0.75], dtype=torch.float64)
    moved = P.moved_camera(cam, delta.float(), P.camera_distance(cam))
    assert math.isclose(float(moved.fx), float(cam.fx) * math.exp(0.05), rel_tol=1e-5)
    assert math.isclose(float(moved.cx), float(cam.cx) + 1.5, rel_tol=1e-5)
    ours = P.projection(cam, pts)(delta)
    direct = P.projection(moved, pts)(torch.zeros(P.POSE, dtype=torch.float64))
    assert torch.allclose(ours, direct, atol=2e-3), (ours - direct).abs().max()


def test_a_framing_turned_into_a_camera_and_back_is_the_same_framing():
    cam = orbit(4)[1:2]
    truth = Framing(1.37, 1.37, -12.25, 3.5)
    back = FR.framing_of(FR.framed_camera(cam, truth, 40, 72), cam)
    got, want = (back.sx, back.sy, back.tx, back.ty), (truth.sx, truth.sy, truth.tx, truth.ty)
    assert all(math.isclose(a, b, abs_tol=1e-4) for a, b in zip(got, want)), (got, want)


def test_uniform_bars_of_any_colour_are_cut_and_the_content_kept():
    g = torch.Generator().manual_seed(0)
    content = torch.rand(30, 40, 3, generator=g)
    framed = torch.zeros(30, 70, 3)
    framed[:, 10:50] = content  # black bars left and right
    framed[:, 50:] = 1.0
    assert FR.content_box(framed) == (0, 30, 10, 50)
    padded = torch.full((50, 40, 3), 0.3)
    padded[12:42] = content  # grey bars above and below
    assert FR.content_box(padded) == (12, 42, 0, 40)
    assert FR.content_box(content) == (0, 30, 0, 40)  # nothing to cut
    flat = torch.full((20, 20, 3), 0.5)
    r0, r1, c0, c1 = FR.content_box(flat)
    assert r1 - r0 >= 8 and c1 - c0 >= 8  # all bar: the picture is kept


def test_warping_a_render_by_a_whole_pixel_crop_gives_the_crop():
    g = torch.Generator().manual_seed(1)
    render = torch.rand(3, 32, 32, generator=g)
    out, inside = FR.warp_to_picture(render, Framing(1.0, 1.0, -5.0, -7.0), 18, 20)
    assert torch.allclose(out, render[:, 7:25, 5:25], atol=1e-5) and bool(inside.all())


def test_a_pillow_resize_is_reproduced_by_its_own_resampling_filter_and_told_from_the_others():
    """Pillow's bilinear and bicubic resizes (up and down, then an integer crop) are what :func:`resampling_matrix`
    gives with the matching filter, to 8-bit rounding; every other filter is further off."""
    import numpy as np
    from PIL import Image

    g = torch.Generator().manual_seed(2)
    small = torch.nn.functional.interpolate(torch.rand(1, 3, 10, 10, generator=g), size=(40, 40), mode="bicubic")
    render = small[0].clamp(0, 1)
    im = Image.fromarray((render.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8))
    x = torch.from_numpy(np.asarray(im, dtype=np.float32) / 255).permute(2, 0, 1)
    for size in (52, 26):
        for name, how in (("bilinear", Image.BILINEAR), ("bicubic", Image.BICUBIC)):
            pic = np.asarray(im.resize((size, size), how).crop((0, 3, size, size - 3)), dtype=np.float32) / 255
            target = torch.from_numpy(pic).permute(2, 0, 1)
            s = size / 40
            err = {}
            for k in FR.RESAMPLERS:
                out, inside = FR.warp_to_picture(x, Framing(s, s, 0.0, -3.0), size - 6, size, k)
                err[k] = float(((out - target)[:, inside] ** 2).mean().sqrt())
            assert err[name] < 0.004, (size, name, err)
            assert min(v for k, v in err.items() if k != name) > 1.2 * err[name], (size, name, err)


def _angle(a: torch.Tensor, b: torch.Tensor) -> float:
    rel = a[:, :3].double().T @ b[:, :3].double()
    return math.degrees(math.acos(max(-1.0, min(1.0, float((torch.trace(rel) - 1) / 2)))))


def test_the_camera_of_a_zoomed_16_9_crop_is_found_with_its_zoom():
    """A picture of a held-out camera zoomed 1.3x and cropped to 16:9 (the base's cameras are square): the search
    finds a camera whose render is the picture. (The scene is a plane, so pose and zoom trade off exactly; lego100's
    depth pins them, docs/experiments/bench-framed.md.)"""
    train = orbit(24)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(5))
    truth = Framing(1.3, 1.3, -7.0, -4.0)
    cam = FR.framed_camera(held, truth, 36, 64)
    picture = P.render_cameras(TexturedSquare(), cam)["rgb"][0]
    box = FR.content_box(picture)
    r0, r1, c0, c1 = box
    pic = picture[r0:r1, c0:c1]
    fit = FR.estimate_framed_camera(reference(train), pic, False, P.PoseSearch(candidates=60, keep=2))
    assert (int(fit.camera.height[0]), int(fit.camera.width[0])) == (r1 - r0, c1 - c0)  # sized like the cut picture
    again = P.render_cameras(TexturedSquare(), fit.camera)["rgb"][0]
    assert float((again - pic).abs().mean()) < 2e-3, fit.history
    start = min(_angle(c, held.camera_to_worlds[0]) for c in train.camera_to_worlds)
    assert start > 1.0  # no training camera is already the answer


def test_the_camera_of_a_letterboxed_smaller_copy_is_found():
    """A held-out view shrunk to 0.8x and letterboxed into a wide frame with black bars: the bars are cut and a
    camera whose render is what is left found."""
    train = orbit(24)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(7))
    inner = FR.framed_camera(held, Framing(0.8, 0.8, 0.0, 0.0), 38, 38)
    picture = torch.zeros(38, 68, 3)
    picture[:, 15:53] = P.render_cameras(TexturedSquare(), inner)["rgb"][0]
    box = FR.content_box(picture)
    r0, r1, c0, c1 = box
    pic = picture[r0:r1, c0:c1]
    fit = FR.estimate_framed_camera(reference(train), pic, False, P.PoseSearch(candidates=60, keep=2))
    assert c0 >= 15 and c1 <= 53 and c1 - c0 >= 30, box  # the bars (and any white edge of the render) cut
    again = P.render_cameras(TexturedSquare(), fit.camera)["rgb"][0]
    assert float((again - pic).abs().mean()) < 2e-3, fit.history


def test_a_resized_copys_camera_turned_along_its_framing_is_put_back_by_the_phase_fit():
    """A render resized 1.3x (Pillow's bicubic) read from a camera turned by 0.4 degrees with its framing moved to
    compensate (the picture barely changes): :func:`phase_fit` brings the camera back to within a third of that (its
    2x render, bilinearly sampled, is not the field itself) and the picture made from the camera it returns matches the
    copy better than the start."""
    train = orbit(24, size=40)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(3))
    truth = Framing(1.3, 1.3, -3.0, -2.0)
    render = P.render_cameras(TexturedSquare(), held)["rgb"][0]
    picture = FR.warp_to_picture(render.permute(2, 0, 1), truth, 44, 48, "bicubic")[0].permute(1, 2, 0)
    turn = math.radians(0.4)
    start_pose = P.moved_camera(held, torch.tensor([0.0, turn, 0.0, 0.0, 0.0, 0.0]))
    shift = float(held.fx) * math.tan(turn) * truth.sx  # the turn's image motion, framed back
    start = FR.framed_camera(held, Framing(1.3, 1.3, truth.tx - shift, truth.ty), 44, 48, start_pose.camera_to_worlds)
    moved = FR.framed_camera(held, Framing(1.3, 1.3, truth.tx + shift, truth.ty), 44, 48, start_pose.camera_to_worlds)
    if _left(start, picture, held) > _left(moved, picture, held):  # the compensating move's sign
        start = moved
    cam = FR.phase_fit(TexturedSquare(), held, start, picture, False, "bicubic")
    before = _angle(start.camera_to_worlds[0], held.camera_to_worlds[0])
    after = _angle(cam.camera_to_worlds[0], held.camera_to_worlds[0])
    assert after < before / 3, (before, after)
    assert _left(cam, picture, held) < 0.5 * _left(start, picture, held)


def _left(camera, picture, base) -> float:
    """RMS of ``picture`` less the base rendered at ``camera``'s pose and resized by its framing."""
    render = FR.resampled_renderer(base, "bicubic")(TexturedSquare(), camera, ("rgb",))["rgb"][0]
    return float((render - picture).pow(2).mean().sqrt())


def test_a_phase_fit_that_cannot_help_leaves_the_camera_as_it_was():
    """A picture the base does not explain (noise): whatever the fit runs into, the camera comes back unchanged."""
    train = orbit(24, size=40)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(3))
    start = FR.framed_camera(held, Framing(1.3, 1.3, -3.0, -2.0), 44, 48)
    noise = torch.rand(44, 48, 3, generator=torch.Generator().manual_seed(0))
    cam = FR.phase_fit(TexturedSquare(), held, start, noise, False, "bicubic")
    assert torch.equal(cam.camera_to_worlds, start.camera_to_worlds)
    assert all(float(getattr(cam, k)) == float(getattr(start, k)) for k in ("fx", "fy", "cx", "cy"))


def test_a_resized_copys_render_covers_only_its_footprint_and_matches_the_whole_frames():
    """The base rendered for a 16:9 crop of a 1.3x copy renders only the part of the base frame the crop shows (plus
    the resampling filter's reach): fewer rays, and the picture made from them is the one the whole frame gives."""
    train = orbit(24, size=60)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(3))
    truth = Framing(1.3, 1.3, -20.0, -25.0)
    cam = FR.framed_camera(held, truth, 30, 40)
    part = FR.footprint(cam, held)
    assert int(part.height[0]) * int(part.width[0]) < 0.6 * 60 * 60
    whole = P.render_cameras(TexturedSquare(), FR.base_frame(cam, held))["rgb"][0]
    from_whole = FR.warp_to_picture(whole.permute(2, 0, 1), FR.framing_of(cam, held), 30, 40, "bicubic")[0]
    from_part = FR.resampled_renderer(held, "bicubic")(TexturedSquare(), cam, ("rgb",))["rgb"][0].permute(2, 0, 1)
    assert torch.allclose(from_part, from_whole, atol=1e-5), float((from_part - from_whole).abs().max())
