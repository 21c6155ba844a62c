"""The camera search of the image decoder (decoders/pose.py) and the fit with pose columns, on an analytic scene."""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch
from nerfstudio.cameras.cameras import Cameras, CameraType

from gsticker_plugin.decoders import pose as P
from gsticker_plugin.decoders.fit import fit_message
from gsticker_plugin.decoders.image import without_columns


def look_at(eye: torch.Tensor) -> torch.Tensor:
    """A [3 4] OpenGL camera-to-world at ``eye`` looking at the origin, z up."""
    back = eye / eye.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), back)
    right = right / right.norm()
    up = torch.linalg.cross(back, right)
    return torch.cat([torch.stack([right, up, back], dim=1), eye[:, None]], dim=1)


def orbit(n: int, size: int = 48) -> Cameras:
    c2w = []
    for i in range(n):
        az = 2 * math.pi * i / n
        el = math.radians(35 + 20 * (i % 3) / 2)
        c2w.append(
            look_at(4.0 * torch.tensor([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]))
        )
    f = 0.5 * size / math.tan(0.5 * 0.7)
    return Cameras(
        camera_to_worlds=torch.stack(c2w),
        fx=f,
        fy=f,
        cx=size / 2,
        cy=size / 2,
        width=size,
        height=size,
        camera_type=CameraType.PERSPECTIVE,
    )


class TexturedSquare:
    """A textured square on z = 0 (soft edges, white background), rendered in closed form like a NeRF's outputs."""

    device = torch.device("cpu")

    def get_outputs_for_camera_ray_bundle(self, bundle):
        o = bundle.origins.reshape(-1, 3).double()
        d = bundle.directions.reshape(-1, 3).double()
        t = -o[:, 2] / d[:, 2].where(d[:, 2].abs() > 1e-9, torch.full_like(d[:, 2], -1e-9))
        p = o + t[:, None] * d
        x, y = p[:, 0], p[:, 1]
        acc = (torch.sigmoid((1 - x.abs()) / 0.03) * torch.sigmoid((1 - y.abs()) / 0.03)) * (t > 0)
        tex = torch.stack(
            [
                0.5 + 0.4 * torch.sin(4 * x) * torch.cos(3 * y),
                0.5 + 0.4 * torch.cos(5 * x + 1) * torch.sin(2 * y),
                0.5 + 0.3 * torch.sin(3 * (x + y)),
            ],
            dim=-1,
        )
        rgb = acc[:, None] * tex + (1 - acc[:, None])
        shape = bundle.origins.shape[:-1]
        return {
            "rgb": rgb.float().reshape(*shape, 3),
            "expected_depth": t.float().reshape(*shape, 1),
            "accumulation": acc.float().reshape(*shape, 1),
        }


def reference(train: Cameras):
    return SimpleNamespace(
        model=TexturedSquare(),
        pipeline=SimpleNamespace(datamanager=SimpleNamespace(train_dataset=SimpleNamespace(cameras=train))),
    )


def test_projection_follows_moved_camera():
    """The pixel motion the Gauss-Newton step uses equals projecting into the camera :func:`moved_camera` builds."""
    cam = orbit(8)[2:3]
    pts = torch.randn(20, 3) * 0.5
    delta = torch.tensor([0.01, -0.02, 0.015, 0.01, 0.005, -0.01], dtype=torch.float64)
    moved = P.moved_camera(cam, delta.float(), P.camera_distance(cam))
    ours = P.projection(cam, pts)(delta)
    direct = P.projection(moved, pts)(torch.zeros(6, dtype=torch.float64))
    assert torch.allclose(ours, direct, atol=2e-3), (ours - direct).abs().max()
    # and at delta 0 the pixel of a point on a pixel's ray is that pixel's centre
    out = P.render_cameras(TexturedSquare(), cam, ("expected_depth", "accumulation"))
    surf = P.surface_points(cam, out["expected_depth"][0], out["accumulation"][0])
    px = P.projection(cam, surf)(torch.zeros(6, dtype=torch.float64))
    assert torch.allclose(px, P.pixel_grid(48, 48).double(), atol=1e-3)


def test_camera_search_finds_a_held_out_camera():
    """An image at an orbit camera none of the candidates has: the search and Gauss-Newton find it to 0.01 degree."""
    train = orbit(24)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(5))
    image = P.render_cameras(TexturedSquare(), held)["rgb"][0]
    search = P.PoseSearch(candidates=60, keep=2)
    fit = P.estimate_camera(reference(train), image, False, search)
    a, b = held.camera_to_worlds[0].double(), fit.camera.camera_to_worlds[0].double()
    rel = a[:, :3].T @ b[:, :3]
    angle = math.degrees(
        math.atan2(
            float(torch.stack([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]]).norm() / 2),
            float((torch.trace(rel) - 1) / 2),
        )
    )
    start = min(
        math.degrees(math.acos(max(-1.0, min(1.0, float((torch.trace(a[:, :3].T @ c[:, :3].double()) - 1) / 2)))))
        for c in P.candidate_cameras(reference(train), search.candidates, search.seed).camera_to_worlds
    )
    assert start > 1.0  # no candidate is already the answer
    assert angle < 0.01 and float((a[:, 3] - b[:, 3]).norm()) < 1e-3 and fit.rms < 1e-3, (angle, fit.history)


def test_camera_search_reads_value_of_hue_shifted_images():
    """With ``value`` the search compares V = max(R, G, B): a channel-swapped image (a hue turn) still finds its camera."""
    train = orbit(24)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(6))
    image = P.render_cameras(TexturedSquare(), held)["rgb"][0][..., [2, 0, 1]]  # a third of a hue turn: V unchanged
    fit = P.estimate_camera(reference(train), image, True, P.PoseSearch(candidates=60, keep=2))
    err = (held.camera_to_worlds[0, :, 3] - fit.camera.camera_to_worlds[0, :, 3]).norm()
    assert float(err) < 2e-3 and fit.rms < 1e-3


def test_fit_without_pose_columns_is_the_joint_fit():
    """Projecting the pose columns out of a fit gives the message a joint fit of message and pose would give: a
    target made of the message's change plus a pose change reads the message exactly; without it, it does not."""
    g = torch.Generator().manual_seed(0)
    a = torch.randn(300, 8, generator=g, dtype=torch.float64)
    cols = torch.randn(300, 6, generator=g, dtype=torch.float64)
    s = torch.tensor([1.0, -1, 1, 1, -1, -1, 1, -1], dtype=torch.float64)
    target = a @ s + cols @ (torch.randn(6, generator=g, dtype=torch.float64) * 3)
    t2, pred, jac = without_columns(cols, target, lambda x: a @ x, lambda x: a)
    fit = fit_message(pred, t2, 8, jac=jac)
    assert torch.equal(torch.sign(fit.signs), s) and fit.explained > 0.999
    plain = fit_message(lambda x: a @ x, target, 8, jac=lambda x: a)
    assert plain.explained < 0.9


def test_windows_and_blur():
    acc = torch.zeros(10, 12, 1)
    acc[3:5, 4:9] = 1
    assert P.content_window(acc, 2) == (1, 7, 2, 11) and P.content_window(torch.zeros(4, 4, 1), 1) == (0, 4, 0, 4)
    flat = torch.full((9, 9, 3), 0.3, dtype=torch.float64)
    assert torch.allclose(P.smoothed(flat, 2.0), flat)
    x = torch.randn(5, 16)
    assert torch.allclose(P.ncc(x, x[2]), P.ncc(x, 3 * x[2] + 1)) and abs(float(P.ncc(x, x[2])[2]) - 1) < 1e-6


def test_camera_search_turns_a_rotated_image_back():
    """An image turned a quarter after rendering (white fill): with that roll in the search, the camera found is the
    held-out one rolled by 90 degrees about its own axis, and the base render there explains the image."""
    from gsticker_plugin.attacks.geometric import rotate

    train = orbit(24)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(7))
    image = rotate(P.render_cameras(TexturedSquare(), held)["rgb"][0].permute(2, 0, 1)[None], 90.0)[0].permute(1, 2, 0)
    fit = P.estimate_camera(reference(train), image, False, P.PoseSearch(candidates=60, keep=2, rolls=(0.0, 90.0)))
    a, b = held.camera_to_worlds[0].double(), fit.camera.camera_to_worlds[0].double()
    rel = a[:, :3].T @ b[:, :3]  # in the held-out camera's frame: a turn about z by a quarter
    quarter = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
    assert float((a[:, 3] - b[:, 3]).norm()) < 5e-3 and fit.rms < 0.02
    assert min(float((rel - quarter).abs().max()), float((rel - quarter.T).abs().max())) < 2e-3, rel


def test_line_search_takes_the_multiple_of_a_short_step_that_lands_on_the_image():
    """A step a quarter of the way to the image's camera is taken four times; a step away from it not at all."""
    cam = orbit(8)[1:2]
    image = P.render_cameras(TexturedSquare(), cam)["rgb"][0]
    delta = torch.tensor([0.004, -0.003, 0.002, 0.004, 0.003, -0.002])
    start = P.moved_camera(cam, -delta, P.camera_distance(cam))
    found, scale = P.line_search(TexturedSquare(), start, delta / 4, image, False, 0.5)
    assert scale == 4
    off = float((start.camera_to_worlds - cam.camera_to_worlds).abs().max())
    assert float((found.camera_to_worlds - cam.camera_to_worlds).abs().max()) < 0.02 * off
    same, none = P.line_search(TexturedSquare(), start, -delta / 4, image, False, 0.5)
    assert none == 0 and torch.equal(same.camera_to_worlds, start.camera_to_worlds)


def test_a_blurred_image_finds_its_camera_when_the_render_is_blurred_alike():
    """An image blurred after rendering: the refinement with the render blurred by the same amount lands on its
    camera; comparing it with a sharp render leaves the camera further off."""
    train = orbit(24)
    held = train[3:4]
    image = P.smoothed(P.render_cameras(TexturedSquare(), held)["rgb"][0].double(), 1.5).float()
    start = P.moved_camera(held, torch.tensor([0.0, 0.0, 0.02, 0.03, -0.02, 0.0]), P.camera_distance(held))
    search = P.PoseSearch(iterations=(0, 8, 8, 8))

    def error(render_blur: float) -> float:
        cam = start
        for blur, its in zip(search.blurs[1:], search.iterations[1:]):
            cam, _, _ = P.refine_stage(TexturedSquare(), image, cam, False, search, blur, its, render_blur)
        return float((held.camera_to_worlds[0, :, 3] - cam.camera_to_worlds[0, :, 3]).norm())

    matched, sharp = error(1.5), error(0.0)
    assert matched < 2e-3 and matched < sharp / 2, (matched, sharp)


def test_a_rolled_camera_is_levelled_and_the_turn_that_maps_the_level_render_onto_the_image_is_found():
    """An image turned 7 degrees after rendering is a picture of the held-out camera rolled about its axis; that
    rolled camera is 7 degrees from level, levelling it gives back the held-out camera, and the 7 degree turn (not
    its opposite) of the level render is the one nearer the image."""
    from gsticker_plugin.attacks.geometric import rotate
    from gsticker_plugin.decoders.unposed import level_roll, levelled, turn_of

    held = orbit(24)[5:6]
    level = P.render_cameras(TexturedSquare(), held)["rgb"][0].permute(2, 0, 1)
    image = rotate(level[None], 7.0)[0].permute(1, 2, 0)
    rolled = P.moved_camera(held, torch.tensor([0.0, 0.0, -math.radians(7.0), 0.0, 0.0, 0.0]))
    assert abs(level_roll(held)) < 1e-4 and abs(abs(level_roll(rolled)) - 7.0) < 1e-3
    back = levelled(rolled).camera_to_worlds[0]
    assert float((back - held.camera_to_worlds[0]).abs().max()) < 1e-5
    turn = turn_of(image, level, level_roll(rolled))
    assert (turn.name, round(turn.strength, 3)) == ("rotate", 7.0)
    assert turn_of(image, level, -level_roll(rolled)).strength == turn.strength


def test_the_trimmed_rms_leaves_the_largest_residuals_out_so_a_painted_rectangle_cannot_pick_the_candidate():
    near = torch.full((10, 10), 0.01)
    near[:4, :5] = 0.8  # the right camera, but a fifth of the image painted over
    far = torch.full((10, 10), 0.2)  # a wrong camera: every pixel off a little
    assert P.trimmed_rms(near) > P.trimmed_rms(far)  # the plain RMS prefers the wrong camera
    assert P.trimmed_rms(near, 0.75) < P.trimmed_rms(far, 0.75)
    assert math.isclose(P.trimmed_rms(near, 0.75), 0.01, rel_tol=1e-5)
    assert math.isclose(P.trimmed_rms(far), 0.2, rel_tol=1e-6)


class ChunkedSquare(TexturedSquare):
    """:class:`TexturedSquare` rendered in chunks of rays, as nerfstudio's ``Model.get_outputs_for_camera_ray_bundle``
    does: no rays, no chunks, no outputs."""

    def get_outputs_for_camera_ray_bundle(self, bundle):
        flat = bundle.flatten()
        chunks = [
            super(ChunkedSquare, self).get_outputs_for_camera_ray_bundle(flat[i : i + 64])
            for i in range(0, len(flat), 64)
        ]
        return {k: torch.cat([c[k] for c in chunks]) for k in (chunks[0] if chunks else {})}


def test_a_view_with_no_ray_to_read_has_no_pose_columns_instead_of_a_failed_render():
    """A camera the pose step moved off every ray the gate reads (seen on a random image) gets ``[0 6]`` pose
    columns, so the image fit reads nothing there; a view with rays gets one row per ray and channel."""
    cam = orbit(8)[2:3]
    none = torch.zeros(0, dtype=torch.long)
    for value in (False, True):
        assert P.pose_columns(ChunkedSquare(), cam, none, value).shape == (0, 6)
    some = torch.arange(0, 48 * 48, 37)
    cols = P.pose_columns(ChunkedSquare(), cam, some, False)
    assert cols.shape == (some.numel() * 3, 6) and float(cols.abs().sum()) > 0


def test_forward_pose_columns_from_the_render_already_made_agree_with_central_ones_at_half_the_renders():
    """``pose_columns(..., base=render)``: one render a column instead of two, the same derivatives (to 2 % of their
    size) on the analytic scene."""
    cam = orbit(8)[2:3]
    rays = torch.arange(0, 48 * 48, 5)
    central_model, forward_model = CountingSquare(), CountingSquare()
    central = P.pose_columns(central_model, cam, rays, False)
    base = P.render_at(TexturedSquare(), cam, rays)
    forward = P.pose_columns(forward_model, cam, rays, False, base=base)
    assert forward_model.renders * 2 == central_model.renders == 12
    assert float((forward - central).norm()) < 0.02 * float(central.norm()), (forward - central).abs().max()


class CountingSquare(TexturedSquare):
    """:class:`TexturedSquare` counting the renders asked of it."""

    def __init__(self):
        self.renders = 0

    def get_outputs_for_camera_ray_bundle(self, bundle):
        self.renders += 1
        return super().get_outputs_for_camera_ray_bundle(bundle)


def rotation_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """The angle between two camera rotations (atan2 of the relative rotation's skew part and trace: exact for small
    angles of float32 matrices, where the trace alone is not)."""
    rel = a[:, :3].double().T @ b[:, :3].double()
    skew = torch.stack([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
    return math.degrees(math.atan2(float(skew.norm() / 2), float((torch.trace(rel) - 1) / 2)))


def test_the_warp_refinement_finds_a_held_out_camera_with_a_quarter_of_the_renders():
    """``refine="warp"`` steps on the image warped onto a held render: the same held-out camera as the render-per-step
    refinement, to 0.01 degree, with a quarter of the renders; ``mixed`` (the finest stage rendering per step) lies
    between."""
    train = orbit(24)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(5))
    image = P.render_cameras(TexturedSquare(), held)["rgb"][0]
    found, renders = {}, {}
    for refine in ("render", "warp", "mixed"):
        ref = reference(train)
        ref.model = CountingSquare()
        search = P.PoseSearch(candidates=60, keep=2, refine=refine)
        cands = P.search_renders(ref, search, (48, 48), False)
        ref.model.renders = 0
        found[refine] = P.estimate_camera(ref, image, False, search, cands)
        renders[refine] = ref.model.renders
    a = held.camera_to_worlds[0]
    for refine, fit in found.items():
        b = fit.camera.camera_to_worlds[0]
        assert rotation_deg(a, b) < 0.01 and float((a[:, 3] - b[:, 3]).norm()) < 1e-3, (refine, fit.history)
    assert renders["warp"] * 4 <= renders["render"] and renders["warp"] < renders["mixed"] < renders["render"], renders


def test_the_warp_refinement_follows_a_pose_change_that_moves_the_picture_by_pixels_with_two_renders():
    """One stage of :func:`warp_refine` from a camera 2 degrees off: back within 0.01 degree with its two renders."""
    cam = orbit(8)[2:3]
    image = P.render_cameras(TexturedSquare(), cam)["rgb"][0]
    start = P.moved_camera(cam, torch.tensor([0.02, -0.015, 0.01, 0.02, -0.01, 0.0]), P.camera_distance(cam))
    model = CountingSquare()
    fit, rms, its = P.warp_refine(model, start, image, False, iterations=10, sigma=1.0, renders=2)
    a, b = cam.camera_to_worlds[0], fit.camera_to_worlds[0]
    assert rotation_deg(a, start.camera_to_worlds[0]) > 1.0
    assert rotation_deg(a, b) < 0.01 and float((a[:, 3] - b[:, 3]).norm()) < 1e-3, (rms, its)
    assert model.renders == 2 and rms < 1e-3


def test_the_default_refinement_warps_large_pictures_and_renders_per_step_for_small_ones(monkeypatch):
    """``refine="auto"`` (the default): a picture over :attr:`PoseSearch.warp_pixels` is refined by
    :func:`warp_refine`, one of at most that many pixels by :func:`lk_refine`; both find the held-out camera."""
    calls = []
    for name in ("warp_refine", "lk_refine"):
        monkeypatch.setattr(P, name, lambda *a, _f=getattr(P, name), _n=name, **k: calls.append(_n) or _f(*a, **k))
    train = orbit(24)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(5))
    image = P.render_cameras(TexturedSquare(), held)["rgb"][0]  # 48 x 48
    for warp_pixels, used in ((48 * 48 - 1, "warp_refine"), (48 * 48, "lk_refine")):
        calls.clear()
        search = P.PoseSearch(candidates=60, keep=2, warp_pixels=warp_pixels)
        assert search.refine == "auto"
        ref = reference(train)
        fit = P.estimate_camera(ref, image, False, search)
        assert set(calls) == {used}, calls
        a, b = held.camera_to_worlds[0], fit.camera.camera_to_worlds[0]
        assert rotation_deg(a, b) < 0.01 and float((a[:, 3] - b[:, 3]).norm()) < 1e-3, (used, fit.history)


def test_the_warp_refinement_blurs_its_held_render_like_a_picture_blurred_after_rendering():
    """A picture blurred by 1 px after rendering: :func:`warp_refine` told so (``render_blur``) returns to the true
    camera from 2 degrees off; its residual is smaller than when it is not told."""
    from gsticker_plugin.fastpath import smoothed

    cam = orbit(8)[2:3]
    image = smoothed(P.render_cameras(TexturedSquare(), cam)["rgb"][0].double(), 1.0).float()
    start = P.moved_camera(cam, torch.tensor([0.02, -0.015, 0.01, 0.02, -0.01, 0.0]), P.camera_distance(cam))
    told, rms_told, _ = P.warp_refine(TexturedSquare(), start, image, False, 10, sigma=1.0, render_blur=1.0)
    _, rms_untold, _ = P.warp_refine(TexturedSquare(), start, image, False, 10, sigma=1.0)
    a, b = cam.camera_to_worlds[0], told.camera_to_worlds[0]
    assert rotation_deg(a, b) < 0.02 and float((a[:, 3] - b[:, 3]).norm()) < 2e-3
    assert rms_told < rms_untold, (rms_told, rms_untold)


def test_an_unknown_refinement_is_refused_rather_than_run_as_the_default():
    import pytest

    with pytest.raises(ValueError, match="auto, render, warp or mixed"):
        P.PoseSearch(refine="wrap")  # type: ignore[arg-type]


def test_render_cameras_cut_into_ray_chunks_equals_one_pass():
    """A render of more rays than ``RAY_CHUNK`` goes to the model in passes of at most that many rays, and the
    image is the one a single pass gives (pixels in place, none lost at a chunk's edge)."""
    from gsticker_plugin.decoders.geometric import RAY_CHUNK

    square = TexturedSquare()
    sizes = []
    inner = square.get_outputs_for_camera_ray_bundle

    def counted(bundle):
        sizes.append(int(bundle.shape[0]))
        return inner(bundle)

    square.get_outputs_for_camera_ray_bundle = counted
    cam = orbit(8, size=72)[1:2]  # 5184 rays: two passes
    out = P.render_cameras(square, cam, ("rgb", "accumulation"))
    assert sizes == [RAY_CHUNK, 72 * 72 - RAY_CHUNK]
    bundle = cam.generate_rays(camera_indices=0, keep_shape=True)
    whole = inner(bundle)
    for k in ("rgb", "accumulation"):
        assert torch.allclose(out[k][0], whole[k], atol=1e-6), k


def test_flow_columns_match_a_render_per_column():
    """The camera's columns from one render (the render's gradient times each surface point's pixel motion) are the
    finite-difference columns of a render per parameter, pose and framing alike, where the surface is smooth."""
    cam = orbit(8, size=48)[3:4]
    out = P.render_cameras(TexturedSquare(), cam, ("rgb", "expected_depth", "accumulation"))
    rgb, depth, acc = out["rgb"][0], out["expected_depth"][0], out["accumulation"][0]
    inner = (acc[..., 0] > 0.99).reshape(-1)
    rays = torch.nonzero(inner).reshape(-1)
    flow = P.flow_columns(cam, rgb, depth, acc, rays, False, P.FRAMED)
    rendered = P.pose_columns(TexturedSquare(), cam, rays, False, free=P.FRAMED)
    for k in range(P.FRAMED):
        a, b = flow[:, k].double(), rendered[:, k].double()
        cos = float(a @ b / (a.norm() * b.norm()))
        assert cos > 0.97, (k, cos)
        assert 0.8 < float(a.norm() / b.norm()) < 1.25, (k, float(a.norm() / b.norm()))
