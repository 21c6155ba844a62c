"""The informed image decoder for images without cameras: each image's camera found against the owner's base first.

:func:`gsticker_plugin.decoders.pose.estimate_camera` finds the camera (V channel, unchanged by a hue shift; a
recoloured image's again with the base rendered through a colour map of its samples, :func:`recoloured_camera`),
then the image decoder fits the message with the base render's pose Jacobian beside it, so what remains of the camera's
error is fitted too (:func:`gsticker_plugin.decoders.image.without_columns`). Neither step sees the owner's message:
the null is the informed decoders' (docs/experiments/verify-notes.md).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
from jaxtyping import Float
from torch import Tensor

from gsticker_plugin.decoders.colormap import (
    COLOR_MAP_MARGIN,
    MAP_SEARCH_SHARE,
    ColorMap,
    fit_to_change,
    map_columns,
    mapped_colors,
    scene_clusters,
)
from gsticker_plugin.decoders.fit import left_after, tie_generator
from gsticker_plugin.decoders.image import (
    DEGRADATION_GRID,
    Degradation,
    ImageReferenceView,
    decode_degraded_view,
    decode_image_view,
    decode_selected,
    image_at_rays,
    image_reference,
    match_blur_spectrum,
    match_degradation,
    reads_value,
    residual_cost,
    rgb_of_sticker,
)
from gsticker_plugin.decoders.pose import (
    PoseSearch,
    camera_distance,
    channel_of,
    estimate_camera,
    line_search,
    moved_camera,
    pose_columns,
    refine_stage,
    search_renders,
)
from gsticker_plugin.decoders.reference import ReferenceView, any_reference_view, cpu_sticker
from gsticker_plugin.decoders.result import Decoded, decoded
from gsticker_plugin.sticker import render_weights
from gsticker_plugin.views import progress_bar


def map_fit(image: Float[Tensor, "H W 3"], ref: ImageReferenceView) -> Tuple[Optional[ColorMap], float, float]:
    """The colour map of the base's samples (:func:`gsticker_plugin.decoders.colormap.fit_color_map`) fitted to the
    difference between ``image`` and the base render at ``ref``'s rays, with the mean squared difference before and
    after it (per channel)."""
    v = ref.view
    if v.rays.numel() == 0:
        return None, 0.0, 0.0
    change = image_at_rays(image, v.rays, v.hw).double() - ref.base_rgb.double()
    if float((change**2).mean()) <= 0:
        return None, 0.0, 0.0
    centres = scene_clusters(v.image.permute(1, 2, 0).reshape(-1, 3))
    return fit_to_change(v.rgb, render_weights(v.density, v.deltas), change, centres)


def recolouring(image: Float[Tensor, "H W 3"], ref: ImageReferenceView) -> Optional[ColorMap]:
    """The colour map of :func:`map_fit` when it explains all but :data:`COLOR_MAP_MARGIN` of the difference between
    ``image`` and the base render at ``ref``'s rays; None otherwise."""
    return reading(image, ref, False, True)[1]


def reading(
    image: Float[Tensor, "H W 3"], ref: ImageReferenceView, value: bool, color_map: bool
) -> Tuple[bool, Optional[ColorMap]]:
    """How ``image`` is read at ``ref``: (by V alone, through a colour map). When both V (``value``: a hue-shifted
    look, :func:`gsticker_plugin.decoders.image.reads_value`) and a colour map (:func:`recolouring`) qualify, the one
    that leaves less of the image's difference from the base render at the rays is kept (a palette edit can keep V
    in the image and still move the samples' dominant channel)."""
    if not color_map:
        return value, None
    cmap, before, after = map_fit(image, ref)
    if cmap is None or after >= COLOR_MAP_MARGIN * before:
        return value, None
    if not value:
        return False, cmap
    y = image_at_rays(image, ref.view.rays, ref.view.hw).double()
    value_left = float(((y.amax(dim=-1) - ref.base_rgb.double().amax(dim=-1)) ** 2).mean())
    return (True, None) if value_left <= after else (False, cmap)


def recoloured_camera(
    reference,
    image: Float[Tensor, "H W 3"],
    camera,
    search: PoseSearch,
    name: str,
    view: Optional[ReferenceView] = None,
) -> Tuple[Any, Optional[float], Optional[ReferenceView]]:
    """``camera`` (found on V) refined again through the colour map of the base's samples (:func:`map_fit`, refitted
    before every stage after the first of ``search``) when the map explains at least :data:`MAP_SEARCH_SHARE` of the
    image's difference from the base render there: the stages then compare RGB with the base rendered through the
    map. Returns the camera, the share the map explained at the start (None: no map could be fitted) and, when the
    camera was left as it came, the reference view built there (the decoder's first round reads it; ``view``: one
    built at ``camera`` already)."""
    background = reference.model.background_color()
    share: Optional[float] = None
    for k, (blur, its) in enumerate(zip(search.blurs[1:], search.iterations[1:])):
        if k > 0 or view is None:
            view = any_reference_view(reference, f"map/{name}/{k}", camera, None)
        cmap, before, after = map_fit(image, image_reference(view, background))
        if cmap is None or before <= 0:
            return camera, share, view if k == 0 else None
        if k == 0:
            share = 1.0 - after / before
            if share < MAP_SEARCH_SHARE:
                return camera, share, view
        with mapped_colors(reference.model, cmap):
            camera, _, _ = refine_stage(reference.model, image, camera, False, search, blur, its)
    return camera, share, None


def blurred_camera(
    reference, image: Float[Tensor, "H W 3"], camera, search: PoseSearch, name: str, view: Optional[ReferenceView]
) -> Tuple[Any, Degradation, Optional[ReferenceView]]:
    """The Gaussian blur whose blur of the base render at ``camera`` has the amplitude spectrum nearest ``image``'s
    (:func:`gsticker_plugin.decoders.image.match_blur_spectrum`: the identity unless clearly nearer; a spectrum
    does not need the camera exact, as a comparison of pixels would); when one is found, the search's stages after
    the first run again with the render blurred by it too, and the blur is matched again at the camera they reach.
    A turned image is a rolled camera, found by the search itself (and read by :func:`turned_reading`). Returns the
    camera, the blur (or the identity) and the reference view at the camera (``view``, built at ``camera`` already,
    when given and the camera stays)."""
    view = view if view is not None else any_reference_view(reference, f"blur/{name}/0", camera, None)
    deg = match_blur_spectrum(image, view.image)
    if deg.name == "none":
        return camera, deg, view
    for blur, its in zip(search.blurs[1:], search.iterations[1:]):
        camera, _, _ = refine_stage(reference.model, image, camera, True, search, blur, its, render_blur=deg.strength)
    view = any_reference_view(reference, f"blur/{name}/1", camera, None)
    again = match_blur_spectrum(image, view.image)
    return camera, again if again.name != "none" else deg, view


TURN_READ_DEG = 0.05
"""An image whose camera is turned at least this far (degrees) about its axis from level is also read as a level
render turned after rendering (:func:`turned_reading`)."""


TURN_ROUNDS = 2
"""Fits of a turned reading, each at the levelled camera moved by the previous fit's pose step."""


def level_roll(camera) -> float:
    """Degrees ``camera`` is turned about its viewing axis away from level (its x axis in the plane normal to the
    world's z, the up of Blender and nerfstudio-data scenes)."""
    r = camera.camera_to_worlds[0, :3, :3].double()
    return math.degrees(math.atan2(float(r[2, 0]), float(r[2, 1])))


def levelled(camera):
    """``camera`` turned about its viewing axis until level (:func:`level_roll` 0)."""
    return moved_camera(camera, torch.tensor([0.0, 0.0, -math.radians(level_roll(camera)), 0.0, 0.0, 0.0]))


def turn_of(image: Float[Tensor, "H W 3"], level: Float[Tensor, "3 H W"], degrees: float) -> Degradation:
    """The rotation about the image centre by ``degrees`` or ``-degrees`` whose turn of the level render ``level``
    is nearer ``image`` (pixels)."""
    x = image.permute(2, 0, 1)[None].float()
    turns = [Degradation("rotate", float(a)) for a in (degrees, -degrees)]
    errs = [float(((x - t.apply(level[None].float())) ** 2).mean()) for t in turns]
    return turns[0] if errs[0] <= errs[1] else turns[1]


def turned_reading(
    reference,
    st,
    image: Float[Tensor, "H W 3"],
    camera,
    native: Tuple[Any, Dict[str, Any]],
    gen,
    iterations: int,
    name: str,
) -> Optional[Tuple[Any, Dict[str, Any]]]:
    """``image`` read as the base's render at the level camera turned after rendering (a rotation attack resamples
    the pixels, which a render at the rolled camera does not): the turn's bilinear resampling is applied to the
    level render and to the mark's Jacobian alike (:func:`gsticker_plugin.decoders.image.decode_degraded_view`).
    Kept, with the level camera, when it leaves a smaller squared residual over the whole image than the reading at
    ``camera`` (``native``: its reference and result); None otherwise. Uses the image and the base only."""
    roll = level_roll(camera)
    if abs(roll) < TURN_READ_DEG:
        return None
    level, best = levelled(camera), None
    native_cost = residual_cost(native[0], image, native[1])
    for k in range(TURN_ROUNDS):  # each round from the camera the previous one's pose step moved
        view = any_reference_view(reference, f"turn/{name}/{k}", level, None)
        ref = image_reference(view, reference.model.background_color())
        cols = pose_columns(reference.model, level, view.rays, False)  # the camera's small error, fitted too
        g = torch.Generator().set_state(gen.get_state())
        d = decode_degraded_view(ref, st, image, turn_of(image, view.image, roll), g, iterations, pose_columns=cols)
        step = torch.tensor(d.pop("pose_step"))
        cost = residual_cost(ref, image, d)
        if best is None or cost < best[0]:
            best = (cost, level, d, g)
        level = moved_camera(level, step, camera_distance(level))
    assert best is not None
    cost, level, d, g = best
    if cost >= native_cost:
        return None
    gen.set_state(g.get_state())
    d["residual_cost_none"], d["residual_cost_matched"] = native_cost, cost
    return level, d


def coded_reading(
    ref: ImageReferenceView, view: ReferenceView, st, image: Float[Tensor, "H W 3"], gen, iterations: int
) -> Optional[Dict[str, Any]]:
    """``image`` read through the JPEG quality whose coding of the base render at the camera found (``view``) is
    nearest it (:func:`gsticker_plugin.decoders.image.match_degradation` over the JPEG grid, the posed decoder's
    rule), by luma and against the coded render (:func:`gsticker_plugin.decoders.image.decode_selected`); None when
    no quality is clearly nearer than the render itself or the uncoded fit leaves the smaller residual."""
    deg, _ = match_degradation(image, view.image, {"jpeg": DEGRADATION_GRID["jpeg"]})
    if deg.name == "none":
        return None
    g = torch.Generator().set_state(gen.get_state())
    d = decode_selected(ref, st, image, deg, g, iterations)
    if d["degradation"] == "none":
        return None
    gen.set_state(g.get_state())
    d["color_map"] = False
    return d


def tinted(model, cmap: Optional[ColorMap]):
    """:func:`gsticker_plugin.decoders.colormap.mapped_colors` of ``cmap``, or a block that changes nothing."""
    return mapped_colors(model, cmap) if cmap is not None else contextlib.nullcontext()


def mapped_reference(ref: ImageReferenceView, cmap: ColorMap) -> ImageReferenceView:
    """``ref`` with every sample's colour taken through ``cmap`` (the base render at the rays recomposited from
    them)."""
    view = dataclasses.replace(ref.view, rgb=cmap(ref.view.rgb.double()).to(ref.view.rgb.dtype))
    mapped = ImageReferenceView(view=view, background=ref.background, base_rgb=ref.base_rgb)
    zero = torch.zeros(view.open_index.numel(), 1, dtype=view.density.dtype)
    mapped.base_rgb = rgb_of_sticker(mapped, zero).detach().float()
    return mapped


def decode_unposed_images(
    key,
    reference,
    images: Sequence[Float[Tensor, "H W 3"]],
    seed: int,
    search: Optional[PoseSearch] = None,
    progress: bool = False,
    value_mode: bool = True,
    iterations: int = 10,
    names: Optional[Sequence[str]] = None,
    rounds: int = 4,
    renders: Optional[Dict[Tuple[int, int], Any]] = None,
    line_scale: int = 8,
    color_map: bool = True,
    pattern: bool = True,
    blur: bool = True,
    turn: bool = True,
    jpeg: bool = True,
    bank: Optional[Path] = None,
) -> Decoded:
    """Decode ``images`` (``[H W 3]`` each, cameras unknown) of the owner's scene against the owner's base
    ``reference`` (:func:`gsticker_plugin.decoders.reference.load_base_reference`): camera search, then the image fit
    with the pose Jacobian. ``value_mode``: read an image whose V matches the base render far better than its RGB
    by V alone (:func:`gsticker_plugin.decoders.image.reads_value`). ``rounds``: fits at most, each from the camera the
    previous one's pose step moved. ``renders``: the search's candidate renders per image size, kept by a caller that
    decodes images one call at a time (filled here); ``bank``: the owner key's view bank folder for them
    (:mod:`gsticker_plugin.decoders.viewbank`). ``line_scale``: each pose step is taken at the multiple up to this
    whose base render is nearest the image (:func:`gsticker_plugin.decoders.pose.line_search`; 0: as fitted).
    ``color_map``: read an image whose colours a smooth map of the base render's explains far better than the render
    itself (a recoloured copy, :func:`recolouring`) with the base's sample colours taken through that map.
    ``blur``: an image that a blur of the base render at the camera found explains far better than the render
    (:func:`blurred_camera`) has its camera refined through that blur and is read through it
    (:func:`gsticker_plugin.decoders.image.decode_selected`). ``turn``: an image whose camera is turned about its axis
    is also read as a level render turned after rendering, and kept so when that explains it better
    (:func:`turned_reading`). ``jpeg``: an image that a JPEG of the base render at the camera found explains far
    better than the render is read through that JPEG, by its luma (:func:`coded_reading`). Returns the decoders' shared result, with per image the
    found camera (``c2w``), the pose fit's RMS, the degradation read through and seconds in ``image``."""
    search = search or PoseSearch()
    if search.refine == "auto":  # the sticker keys' readings were built and measured rendering per step
        search = dataclasses.replace(search, refine="render")
    st = cpu_sticker(reference.model)
    background = reference.model.background_color()
    gen = tie_generator(seed)
    renders = renders if renders is not None else {}
    bits: List[Tensor] = []
    details: List[Dict[str, Any]] = []
    names = list(names) if names is not None else [f"image/{i:04d}" for i in range(len(images))]
    for name, image in progress_bar(list(zip(names, images)), "camera search + image decoding", progress):
        hw = (int(image.shape[0]), int(image.shape[1]))
        bank_seconds = None
        if hw not in renders:
            t0 = time.time()
            renders[hw] = search_renders(reference, search, hw, value=True, bank=bank)
            bank_seconds = time.time() - t0
        t0 = time.time()
        pose = estimate_camera(reference, image, True, search, renders[hw])
        timing = {
            "search_seconds": time.time() - t0,
            **({} if bank_seconds is None else {"view_bank_seconds": bank_seconds}),
        }
        camera, share, view = pose.camera, None, None
        degradation = Degradation()
        if blur:  # before the colour map: a map of the samples explains part of a blur too
            camera, degradation, view = blurred_camera(reference, image, camera, search, name, None)
        if color_map and degradation.name == "none":  # its view at the camera found is the first round's
            camera, share, view = recoloured_camera(reference, image, camera, search, name, view)
        if degradation.name != "none":  # read through the blur at that camera, as the posed decoder reads
            ref = image_reference(view, background)
            d = decode_selected(ref, st, image, degradation, gen, iterations)
            turned = turned_reading(reference, st, image, camera, (ref, d), gen, iterations, name) if turn else None
            if turned is not None:  # a turn's resampling looks like a blur: the turn may explain it better
                camera, d = turned
            d.update(finding(camera, 0, pose, share, t0), **timing)
            bits.append(d.pop("bits"))
            details.append(d)
            continue
        best: Optional[Tuple[float, Dict[str, Any], Any, int, ImageReferenceView, Any]] = None
        previous: Optional[Tensor] = None
        for k in range(rounds):  # Gauss-Newton on camera and message together: the fit's pose step moves the camera
            ref_view = (
                view
                if k == 0 and view is not None
                else any_reference_view(reference, f"unposed/{name}/{k}", camera, None)
            )
            # the pose step left every ray the gate reads: earlier rounds stand (a round with no ray has residual 0)
            if k > 0 and ref_view.rays.numel() == 0:
                break
            ref = image_reference(ref_view, background)
            value, cmap = reading(image, ref, value_mode and reads_value(image, ref_view.image), color_map)
            if cmap is not None:
                ref = mapped_reference(ref, cmap)
            with tinted(reference.model, cmap):  # the base rendered with its samples' colours through the map
                cols = pose_columns(reference.model, camera, ref_view.rays, value)
            if cmap is not None:  # what remains of the map's error is fitted beside the message too
                weights = render_weights(ref.view.density, ref.view.deltas)
                cols = torch.cat([cols, map_columns(ref_view.rgb, weights, cmap).to(cols.dtype)], dim=1)
            y = image_at_rays(image, ref_view.rays, ref_view.hw)
            d = decode_image_view(ref, st, y, gen, iterations, value=value, pose_columns=cols)
            step = torch.tensor(d.pop("pose_step"))[:6]
            mark = d.pop("mark_change")
            left = left_after(d)  # what the joint fit leaves
            d["color_map"] = cmap is not None
            if best is None or left < best[0]:
                best = (left, d, camera, k + 1, ref, ref_view)
            if float(step.abs().max()) <= 1e-6:
                break
            if line_scale > 0:  # the fit's step falls short on a sharp render: the base render decides how far
                sigma = search.blurs[-1] * max(hw) / 100.0
                target = channel_of(image.float(), value).clone()  # the image less the fitted mark
                flat = target.view(-1, target.shape[-1])
                flat[ref_view.rays] -= mark.reshape(-1, target.shape[-1]).to(flat.dtype)
                with tinted(reference.model, cmap):
                    camera, scale = line_search(reference.model, camera, step, target, value, sigma, line_scale)
                if scale == 0:  # no multiple of the step brings the base render nearer: the fit has settled
                    break
                moved = step * scale
                if pattern and previous is not None:  # along a narrow valley: the last two moves together, further
                    with tinted(reference.model, cmap):
                        camera, more = line_search(
                            reference.model, camera, previous + moved, target, value, sigma, line_scale
                        )
                    moved = moved + more * (previous + moved)
                previous = moved
            else:
                camera = moved_camera(camera, step, camera_distance(camera))
        assert best is not None
        _, d, camera, used, ref, ref_view = best
        d["degradation"] = "none"
        if jpeg and not d["color_map"] and d["signals"] == ["rgb"]:
            coded = coded_reading(ref, ref_view, st, image, gen, iterations)
            if coded is not None:  # JPEG's blocks and chroma, not the mark, are most of what the base leaves
                d, used = coded, 0
        if turn and not d["color_map"] and d["signals"] == ["rgb"]:
            turned = turned_reading(reference, st, image, camera, (ref, d), gen, iterations, name)
            if turned is not None:  # a level render turned after rendering explains the image better
                (camera, d), used = turned, 0
        d.update(finding(camera, used, pose, share, t0), **timing)
        bits.append(d.pop("bits"))
        details.append(d)
    return decoded(key, bits, "image", details)


def finding(camera, used: int, pose, share: Optional[float], t0: float) -> Dict[str, Any]:
    """What a decoded image's result records of its camera: the camera found (``c2w``), the fit round it came from
    (0: read through a blur or a turn at the camera), the search's fit and the seconds since ``t0``."""
    return {
        "camera": "estimated",
        "c2w": camera.camera_to_worlds[0].tolist(),
        "round": used,
        "pose_rms": pose.rms,
        "pose_score": pose.score,
        "pose_iterations": pose.iterations,
        "map_share_at_search": share,
        "seconds": time.time() - t0,
    }
