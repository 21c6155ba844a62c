"""Informed decoding of the field mark from images: the owner's message read from pictures of the shared run.

An image shows colour only. The field mark changes the base's density *and* the geometry features its colour head
reads, both linearly in the table; at a camera the base's colour then changes by ``a * J s`` to first order, with
``J`` the derivative of the rendered colour in the signs (:func:`gsticker_plugin.fieldmark.image_view`: the stock
field and renderer, differentiated). Per image:

1. the camera, found against the owner's base (:func:`gsticker_plugin.decoders.pose.estimate_camera`, on V) unless
   given;
2. a colour map of the base's sample colours fitted to the image there (:func:`recolouring_at`): a recoloured copy
   (``ns-recolor`` palette, hue or fine-tune changes every sample's colour) is then searched again and read with the
   base rendered through that map (:func:`recoloured_camera`), the map's own error fitted beside the message;
3. ``s`` fitted to ``image - base render`` by least squares beside the base render's pose Jacobian, so what remains of
   the camera's error is fitted too (:func:`gsticker_plugin.decoders.image.without_columns`); the fitted pose step
   moves the camera and the fit runs again, for a few rounds, the best kept;
4. bit ``i`` = ``s_i > 0``.

No step reads the message: for an image that does not carry it the bits are independent of it, and with the
message uniformly random and secret the matches are ``Binomial(K, 1/2)`` (the informed decoders' null,
docs/experiments/verify-notes.md).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from gsticker_plugin import fieldmark as FM
from gsticker_plugin.cameras import same_aspect
from gsticker_plugin.decoders.colormap import (
    COLOR_MAP_MARGIN,
    MAP_SEARCH_SHARE,
    ColorMap,
    fit_to_change,
    map_columns,
    mapped_colors,
    scene_clusters,
)
from gsticker_plugin.decoders.fit import fit_and_decide, fit_summary, left_after, tie_generator
from gsticker_plugin.decoders.framed import (
    base_frame,
    content_box,
    estimate_framed_camera,
    footprint,
    framing_of,
    matched_resampler,
    refine_resampled,
    resampled,
    resampled_renderer,
    resized,
    warp_to_picture,
)
from gsticker_plugin.decoders.image import (
    DEGRADATION_GRID,
    Degradation,
    image_at_rays,
    match_blur_spectrum,
    match_degradation,
    observe,
    without_columns,
)
from gsticker_plugin.decoders.pose import (
    FRAMED,
    POSE,
    PRINCIPAL_STEP,
    PoseSearch,
    camera_distance,
    estimate_camera,
    flow_columns,
    moved_camera,
    refine_stage,
    render_at,
    render_cameras,
    scaled_camera,
    search_renders,
)
from gsticker_plugin.decoders.result import Decoded, decoded
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.sticker import render_weights
from gsticker_plugin.views import progress_bar


def decode_image_view(
    view: FM.ImageView,
    image_rgb: Float[Tensor, "R 3"],
    amplitude: float,
    generator: torch.Generator,
    columns: Optional[Float[Tensor, "M P"]] = None,
    luma: bool = False,
) -> Dict[str, Any]:
    """Fit the signs to one image's colour at the view's rays (minus the base render) and decide the bits.
    ``columns``: further free columns fitted beside the message (rows ``r * 3 + c``; the pose Jacobian); the result then
    holds their fitted coefficients (``column_step``). ``luma``: fit the luma of every row alone
    (:func:`gsticker_plugin.decoders.image.observe`). Returns the bits and the fit's summary."""
    k = view.jacobian.shape[-1]
    j = observe((view.jacobian * amplitude).reshape(-1, k), luma)
    target = observe((image_rgb.float() - view.base_rgb).reshape(-1), luma)
    cols = observe(columns, luma) if columns is not None and columns.numel() else None
    t, predict, jac = target, (lambda s: j @ s), (lambda s: j)
    if cols is not None:
        t, predict, jac = without_columns(cols, target, predict, jac)
    fit, bits, undetermined = fit_and_decide(predict, jac, t, k, view.rays.numel() > 0, generator)
    out = {
        "bits": bits,
        **fit_summary(fit, undetermined, int(view.rays.numel())),
        "signals": ["luma" if luma else "rgb"],
    }
    if cols is not None:
        rest = (target - j @ fit.signs).double()
        out["column_step"] = torch.linalg.lstsq(cols.double(), rest[:, None]).solution[:, 0].tolist()
    return out


def through_degradation(
    degradation: Degradation, rows: Float[Tensor, "P 3 C"], hw: Tuple[int, int]
) -> Float[Tensor, "P 3 C"]:
    """The linear part of ``degradation`` applied to per-pixel colour changes (``C`` of them, every pixel of an
    ``hw`` camera): what it does to a small change of the picture."""
    h, w = hw
    c = rows.shape[-1]
    x = degradation.linear(rows.reshape(h, w, 3, c).permute(3, 2, 0, 1).float())  # [C 3 H W]
    return x.permute(2, 3, 1, 0).reshape(h * w, 3, c)


def degraded_render(degradation: Degradation, rgb: Float[Tensor, "P 3"], hw: Tuple[int, int]) -> Float[Tensor, "P 3"]:
    """``degradation`` applied to a render of every pixel of an ``hw`` camera."""
    h, w = hw
    return degradation.apply(rgb.reshape(1, h, w, 3).permute(0, 3, 1, 2).float())[0].permute(1, 2, 0).reshape(-1, 3)


def degraded_view(
    view: FM.ImageView, degradation: Degradation, columns: Optional[Float[Tensor, "M P"]]
) -> Tuple[FM.ImageView, Optional[Float[Tensor, "M P"]]]:
    """``view`` (with its render of every pixel) and free ``columns`` of every pixel (rows ``p * 3 + c``) as a picture
    ``degradation`` was applied to shows them: the base render degraded, the mark's and the columns' changes through
    its linear part, at the pixels where the mark's change now lands."""
    assert view.image is not None
    h, w = view.hw
    k = view.jacobian.shape[-1]
    jac = torch.zeros(h * w, 3, k)
    jac[view.rays] = view.jacobian.float()
    jac = through_degradation(degradation, jac, view.hw)
    rays = (jac.abs().amax(dim=(1, 2)) > 1e-4).nonzero().reshape(-1)
    base = degraded_render(degradation, view.image, view.hw)
    out = FM.ImageView(rays, base[rays], jac[rays], view.hw, view.image)
    if columns is None:
        return out, None
    p = columns.shape[1]
    cols = through_degradation(degradation, columns.reshape(h * w, 3, p), view.hw)[rays].reshape(-1, p)
    return out, cols


@dataclass
class Recolouring:
    """A colour map of the base's sample colours fitted to a picture at one camera (:func:`recolouring_at`)."""

    cmap: ColorMap
    share: float
    """Of the picture's squared difference from the base render, the share the map explains."""
    sample_rgb: Float[Tensor, "P S 3"]
    """The base's sample colours at every pixel of the camera."""
    weights: Float[Tensor, "P S 1"]
    """Their render weights."""

    @property
    def reads(self) -> bool:
        """Whether the picture is read through the map: it leaves at most :data:`COLOR_MAP_MARGIN` of the difference
        (a recolouring moves whole materials; the mark and a small pose error it cannot map)."""
        return self.share >= 1.0 - COLOR_MAP_MARGIN

    def columns(self, rays: Tensor) -> Float[Tensor, "M P"]:
        """d (render through the map at the flat pixels ``rays``) / d map: rows ``r * 3 + c``."""
        return map_columns(self.sample_rgb[rays], self.weights[rays], self.cmap).float()


def recolouring_at(model, image: Float[Tensor, "H W 3"], camera) -> Optional[Recolouring]:
    """The colour map of the base's samples (:func:`gsticker_plugin.decoders.colormap.fit_color_map`, clusters of the
    base render's colours) that best turns the base render at ``camera`` (sized like ``image``) into ``image``; None
    when the image is the render. The fit sees the image and the base only."""
    outputs, smp = FM.capture_samples(model, camera)
    render = outputs["rgb"].reshape(-1, 3).float().cpu()
    change = image.reshape(-1, 3).double() - render.double()
    if float((change**2).mean()) <= 0:
        return None
    rgb = smp["rgb"].cpu()
    weights = render_weights(smp["density"], smp["deltas"]).cpu()
    cmap, before, after = fit_to_change(rgb, weights, change, scene_clusters(render))
    return Recolouring(cmap, 1.0 - after / before, rgb, weights)


def at_base_scale(image: Float[Tensor, "H W 3"], camera, base: Optional[Cameras]) -> Tuple[Tensor, Any]:
    """``image`` and its ``camera`` shrunk to ``base``'s scale when the picture is larger (a colour map needs no finer
    pixels); as they are for a smaller picture or no ``base``."""
    scale = framing_of(camera, base).sx if base is not None else 1.0
    if scale <= 1.0:
        return image, camera
    hh, ww = max(1, round(int(image.shape[0]) / scale)), max(1, round(int(image.shape[1]) / scale))
    return resized(image, hh, ww), scaled_camera(camera, hh, ww)


def recoloured_camera(
    model, image: Float[Tensor, "H W 3"], camera, search: PoseSearch, recolouring: Recolouring, free: int = POSE
) -> Tuple[Any, Optional[Recolouring]]:
    """``camera`` (found on V, which a recolouring moves too) refined again in RGB against the base rendered with its
    sample colours through ``recolouring``'s map (fitted at ``camera``), the map fitted again before every stage after
    the first of ``search``'s finer stages, each of :attr:`PoseSearch.map_iterations` (``free``: the camera's
    parameters moved). Returns the camera and the map fitted there."""
    search = search.for_size(int(image.shape[0]), int(image.shape[1]))
    rec: Optional[Recolouring] = recolouring
    for k, blur in enumerate(search.blurs[1:]):
        if k > 0:
            rec = recolouring_at(model, image, camera)
        if rec is None:
            break
        with mapped_colors(model, rec.cmap):
            camera, _, _ = refine_stage(model, image, camera, False, search, blur, search.map_iterations, free=free)
    return camera, recolouring_at(model, image, camera)


def camera_columns(camera, view: FM.ImageView, rays: Tensor, free: int) -> Float[Tensor, "M free"]:
    """d (base render at ``rays``) / d (the camera's ``free`` parameters), rows ``r * 3 + c``, from ``view``'s render
    of every pixel (:func:`gsticker_plugin.decoders.pose.flow_columns`; no render of its own)."""
    assert view.image is not None and view.depth is not None and view.accumulation is not None
    h, w = view.hw
    rgb, depth, acc = view.image.reshape(h, w, 3), view.depth.reshape(h, w, 1), view.accumulation.reshape(h, w, 1)
    return flow_columns(camera, rgb, depth, acc, rays, False, free)


def read_at_camera(
    reference,
    image: Float[Tensor, "H W 3"],
    camera,
    generator: torch.Generator,
    rounds: int,
    free: int = POSE,
    recolouring: Optional[Recolouring] = None,
    degradation: Optional[Degradation] = Degradation(),
) -> Tuple[Dict[str, Any], Any, int]:
    """Fit the message and the camera's error (``free``: its pose, or with :data:`gsticker_plugin.decoders.pose.FRAMED`
    its zoom and principal point too) together for up to ``rounds`` rounds, each from the camera the previous fit's
    step moved; returns the fit that left the least, its camera and its round (1-based). The mark's Jacobian and the
    camera's columns are those of the first camera (the steps are fractions of a pixel); each later round renders the
    base again at its camera. ``recolouring`` (fitted at ``camera``): the base is rendered with its sample colours
    through that map, and the map's own error is fitted beside the message too. ``degradation`` (a blur or JPEG the
    picture went through; None: :func:`matched_degradation` at the first camera's base render): everything is compared
    as that degradation shows it (:func:`degraded_view`; JPEG by luma)."""
    model = reference.model
    tint = mapped_colors(model, recolouring.cmap) if recolouring is not None else contextlib.nullcontext()
    best: Optional[Tuple[float, Dict[str, Any], Any, int]] = None
    with tint:
        view = FM.image_view(model, camera, reference.patterns)
        if degradation is None:
            assert view.image is not None
            degradation = matched_degradation(image, view.image)
        degraded = degradation.name != "none"
        h, w = view.hw
        rays = torch.arange(h * w) if degraded else view.rays
        cols = camera_columns(camera, view, rays, free) if rounds > 1 else None
        if recolouring is not None:
            mapped = recolouring.columns(rays)
            cols = mapped if cols is None else torch.cat([cols, mapped], dim=1)
        if degraded:
            view, cols = degraded_view(view, degradation, cols)
        for r in range(rounds):
            if r > 0:
                again = render_at(model, camera, rays)
                base = degraded_render(degradation, again, view.hw)[view.rays] if degraded else again
                view = replace(view, base_rgb=base)
            picture = image_at_rays(image, view.rays, view.hw)
            d = decode_image_view(view, picture, reference.amplitude, generator, cols, luma=degradation.luma)
            step = torch.tensor(d.pop("column_step", [0.0] * free))[:free]
            if best is None or left_after(d) < best[0]:
                best = (left_after(d), d, camera, r + 1)
            if r + 1 == rounds or float(step.abs().max()) <= 1e-7:
                break
            camera = moved_camera(camera, step, camera_distance(camera))
    assert best is not None
    best[1]["degradation"] = degradation.label()
    return best[1], best[2], best[3]


JPEG_GRID = {"jpeg": DEGRADATION_GRID["jpeg"]}


def matched_degradation(image: Float[Tensor, "H W 3"], render: Float[Tensor, "P 3"]) -> Degradation:
    """The blur (by amplitude spectrum, :func:`gsticker_plugin.decoders.image.match_blur_spectrum`) or else the JPEG
    quality (by pixels, :func:`gsticker_plugin.decoders.image.match_degradation`) whose transform of the base's
    ``render`` at the picture's camera is clearly closer to the picture than the render itself; the identity
    otherwise. Uses the picture and the base only."""
    h, w = int(image.shape[0]), int(image.shape[1])
    base = render.reshape(h, w, 3).permute(2, 0, 1).float()
    blur = match_blur_spectrum(image, base)
    if blur.name != "none":
        return blur
    return match_degradation(image, base, JPEG_GRID)[0]


def read_picture(
    reference,
    picture: Float[Tensor, "H W 3"],
    camera,
    generator: torch.Generator,
    rounds: int = 2,
    recolouring: Optional[Recolouring] = None,
    resampler: Optional[str] = None,
) -> Tuple[Dict[str, Any], Any, int]:
    """Read a framed picture at the ``camera`` :func:`gsticker_plugin.decoders.framed.estimate_framed_camera` found:
    a resized copy (``resampler``: the filter its camera was refined with) at the base's own intrinsics carried into
    the picture by its framing (:func:`read_framed`, through the blur or JPEG :func:`matched_degradation` finds against
    that resized render); any other picture with the base rendered at ``camera`` (:func:`read_at_camera`, zoom and
    principal point free, the degradation matched there). Both through ``recolouring``'s colour map when given
    (``read``: ``framing`` or ``render``). Neither looks at the message."""
    if resampler is not None:
        base = reference.pipeline.datamanager.train_dataset.cameras[:1]
        tint = mapped_colors(reference.model, recolouring.cmap) if recolouring is not None else contextlib.nullcontext()
        with tint:
            render = resampled_renderer(base, resampler)(reference.model, camera, ("rgb",))["rgb"][0]
        degradation = matched_degradation(picture, render.reshape(-1, 3))
        d, cam, used = read_framed(
            reference, picture, camera, generator, rounds, recolouring=recolouring, degradation=degradation
        )
        d["read"] = "framing"
        return d, cam, used
    d, cam, used = read_at_camera(reference, picture, camera, generator, rounds, FRAMED, recolouring, None)
    d["read"] = "render"
    return d, cam, used


def read_framed(
    reference,
    picture: Float[Tensor, "H W 3"],
    camera: Cameras,
    generator: torch.Generator,
    rounds: int = 2,
    eps: float = 3.5e-4,
    recolouring: Optional[Recolouring] = None,
    degradation: Degradation = Degradation(),
) -> Tuple[Dict[str, Any], Cameras, int]:
    """:func:`read_at_camera` for a framed picture whose ``camera`` (sized like it) was found by
    :func:`gsticker_plugin.decoders.framed.estimate_framed_camera`: the base render, the mark's per-bit colour change
    and the derivatives in the pose and in the framing's zoom and principal point, all at the base's own intrinsics (where a
    render is what a resized copy was made from), carried into the picture by its framing (:func:`warp_to_picture`);
    the signs fitted there to ``picture - framed base`` beside those columns. ``recolouring``: the base rendered
    through its colour map (a map of sample colours, whatever the camera), the map's own columns at the base's
    samples fitted too. ``degradation`` (a blur or JPEG the copy went through after it was resized): everything
    compared as it shows it (:func:`degraded_view`). Returns the fit that left the least, its camera (the picture's)
    and its round (1-based)."""
    model = reference.model
    base = reference.pipeline.datamanager.train_dataset.cameras[:1]
    degraded = degradation.name != "none"
    ph, pw = int(picture.shape[0]), int(picture.shape[1])
    dist = camera_distance(camera)
    at = footprint(camera, base)
    tint = mapped_colors(model, recolouring.cmap) if recolouring is not None else contextlib.nullcontext()
    map_cols: List[Tensor] = []
    if recolouring is not None:
        _, smp = FM.capture_samples(model, at)
        weights = render_weights(smp["density"], smp["deltas"]).cpu()
        map_cols = [map_columns(smp["rgb"].cpu(), weights, recolouring.cmap).float()]  # rows r * 3 + c
    best: Optional[Tuple[float, Dict[str, Any], Cameras, int]] = None
    with tint:
        view = FM.image_view(model, at, reference.patterns)
        h0, w0 = view.hw
        k = view.jacobian.shape[-1]
        jac = torch.zeros(h0 * w0, 3, k)
        jac[view.rays] = view.jacobian.float()
        assert view.image is not None
        render = view.image.reshape(h0, w0, 3)
        pose = camera_columns(at, view, torch.arange(h0 * w0), POSE)  # rows r * 3 + c
        extra = torch.cat([pose] + map_cols, dim=1)
        e = extra.shape[1]
        fixed = torch.cat([jac.reshape(h0, w0, 3 * k), extra.reshape(h0, w0, 3 * e)], dim=-1).permute(2, 0, 1)
        kernel = matched_resampler(render, picture, framing_of(camera, at))
        for r in range(rounds):
            if r > 0:  # the Jacobians of the first camera (the steps are fractions of a pixel), the base rendered again
                render = render_cameras(model, base_frame(camera, at))["rgb"][0]
            framing = framing_of(camera, at)
            warped, inside = warp_to_picture(torch.cat([render.permute(2, 0, 1), fixed]), framing, ph, pw, kernel)
            rows = torch.arange(ph * pw) if degraded else torch.nonzero(inside.reshape(-1)).reshape(-1)
            flat = warped.reshape(warped.shape[0], -1)[:, rows].T  # [R C]
            framed = FM.ImageView(rows, flat[:, :3], flat[:, 3 : 3 + 3 * k].reshape(-1, 3, k), (ph, pw), flat[:, :3])
            cols = [flat[:, 3 + 3 * k :].reshape(-1, 3, e).reshape(-1, e)]  # rows r * 3 + c, like the message's
            for i in range(POSE, FRAMED):  # the zoom and the principal point, moved in the picture
                step_i = torch.zeros(FRAMED)
                step_i[i] = PRINCIPAL_STEP if i > POSE else eps
                plus, minus = (
                    warp_to_picture(
                        render.permute(2, 0, 1), framing_of(moved_camera(camera, sign * step_i), at), ph, pw, kernel
                    )[0]
                    for sign in (1, -1)
                )
                cols.append(((plus - minus) / (2 * float(step_i[i]))).reshape(3, -1)[:, rows].T.reshape(-1, 1))
            columns = torch.cat(cols, 1)
            if degraded:  # every pixel of the picture, as the degradation shows them
                framed, columns = degraded_view(framed, degradation, columns)
                assert columns is not None
            picture_rows = picture.reshape(-1, 3)[framed.rays].float()
            d = decode_image_view(framed, picture_rows, reference.amplitude, generator, columns, degradation.luma)
            coeffs = torch.tensor(d.pop("column_step", [0.0] * (e + FRAMED - POSE)))
            step = torch.cat([coeffs[:POSE], coeffs[e : e + FRAMED - POSE]])  # the pose's, then the framing's
            d["resampler"] = kernel
            d["degradation"] = degradation.label()
            if best is None or left_after(d) < best[0]:
                best = (left_after(d), d, camera, r + 1)
            if r + 1 == rounds or float(step.abs().max()) <= 1e-7:
                break
            camera = moved_camera(camera, step, dist)
    assert best is not None
    return best[1], best[2], best[3]


def decode_images(
    key,
    reference,
    images: Sequence[Float[Tensor, "H W 3"]],
    seed: int,
    cameras: Optional[Sequence[Any]] = None,
    search: Optional[PoseSearch] = None,
    rounds: int = 2,
    names: Optional[Sequence[str]] = None,
    progress: bool = False,
    renders: Optional[Dict[Tuple[int, int], Any]] = None,
    bank: Optional[Path] = None,
) -> Decoded:
    """Decode ``images`` (``[H W 3]`` in [0, 1]) of the owner's scene against the field-mark ``reference``
    (:func:`gsticker_plugin.decoders.fieldmark.load_field_reference`): at the given ``cameras`` (one per image, a
    one-camera ``Cameras``; None: found by the camera search, with its framing for an image of another aspect ratio
    than the base's, :mod:`gsticker_plugin.decoders.framed`), then the fit with the pose Jacobian. ``renders``: the
    search's candidate renders per image size, kept by a caller that decodes images one call at a time (filled here);
    ``bank``: the owner key's view bank folder for them (:mod:`gsticker_plugin.decoders.viewbank`). Returns the
    decoders' shared result with, per image, its camera (``c2w``, and whether it was estimated), the fit and the
    seconds taken (``seconds`` in all, ``search_seconds`` of them finding the camera; ``view_bank_seconds``, apart,
    on the first image of a size: loading or rendering the search's candidates)."""
    if FM.host_of(reference.model.field) != "hash":
        raise GStickerError(
            "pictures of a TensoRF shared run are not read yet; verify the model itself with --load-config "
            "SUSPECT/config.yml"
        )
    search = search or PoseSearch()
    gen = tie_generator(seed)
    names = list(names) if names is not None else [f"image/{i:04d}" for i in range(len(images))]
    renders = renders if renders is not None else {}
    bits: List[Tensor] = []
    details: List[Dict[str, Any]] = []
    if cameras is None:
        base = reference.pipeline.datamanager.train_dataset.cameras
        h0, w0 = int(base.height[0]), int(base.width[0])
    for i, (name, image) in enumerate(progress_bar(list(zip(names, images)), "field-mark image decoding", progress)):
        extra: Dict[str, Any] = {"camera": "given"}
        framed = cameras is None and not same_aspect(image.shape[1], image.shape[0], w0, h0)
        if framed:  # bars cut; a letterboxed render is the render again
            r0, r1, c0, c1 = content_box(image)
            image = image[r0:r1, c0:c1]
            extra["content_box"] = [r0, r1, c0, c1]
            framed = not same_aspect(image.shape[1], image.shape[0], w0, h0)
        if cameras is None:
            hw = (h0, w0) if framed else (int(image.shape[0]), int(image.shape[1]))
            if hw not in renders:
                t0 = time.time()
                renders[hw] = search_renders(reference, search, hw, value=True, bank=bank)
                extra["view_bank_seconds"] = time.time() - t0
        t0 = time.time()
        free = FRAMED if framed else POSE
        resampler: Optional[str] = None
        if cameras is not None:
            camera = cameras[i]
        else:
            if framed:
                pose = estimate_framed_camera(reference, image, True, search, renders[hw])
                extra["camera"] = "estimated with its framing"
            else:
                pose = estimate_camera(reference, image, True, search, renders[hw])
                extra["camera"] = "estimated"
            camera, resampler = pose.camera, pose.resampler
            extra.update(pose_rms=pose.rms, pose_score=pose.score)
        rec = recolouring_at(reference.model, *at_base_scale(image, camera, base[:1] if resampler else None))
        if cameras is None and rec is not None and rec.share >= MAP_SEARCH_SHARE:
            if framed and resampled(framing_of(camera, base[:1]).sx):  # a resized copy: refined again as it was made
                with mapped_colors(reference.model, rec.cmap):
                    camera, resampler = refine_resampled(reference.model, base[:1], camera, image, False, last=True)
                rec = recolouring_at(reference.model, *at_base_scale(image, camera, base[:1]))
            else:
                camera, rec = recoloured_camera(reference.model, image, camera, search, rec, free)
        if cameras is None:
            extra["search_seconds"] = time.time() - t0
        mapped = rec if rec is not None and rec.reads else None
        extra.update(color_map=mapped is not None, map_share=rec.share if rec is not None else 0.0)
        if framed:
            d, camera, used = read_picture(reference, image, camera, gen, rounds, mapped, resampler)
        else:
            d, camera, used = read_at_camera(reference, image, camera, gen, rounds, POSE, mapped, None)
        d.update(extra, name=name, round=used, c2w=camera.camera_to_worlds[0].tolist(), seconds=time.time() - t0)
        bits.append(d.pop("bits"))
        details.append(d)
    return decoded(key, bits, "image", details)
