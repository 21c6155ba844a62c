"""The informed image decoder for images without cameras: each image's camera found against the owner's base first.

:func:`gsticker_plugin.decoders.pose.estimate_camera` finds the camera (V channel, unchanged by a hue shift), then
the image decoder fits the message with the base render's pose Jacobian beside it, so what remains of the camera's
error is fitted too (:func:`gsticker_plugin.decoders.image.without_columns`). Neither step sees the owner's message:
the null is the informed decoders' (docs/verify.md).
"""

from __future__ import annotations

import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
from jaxtyping import Float
from torch import Tensor

from gsticker_plugin.decoders.fit import tie_generator
from gsticker_plugin.decoders.image import decode_image_view, image_at_rays, image_reference, reads_value
from gsticker_plugin.decoders.pose import (
    PoseSearch,
    camera_distance,
    estimate_camera,
    moved_camera,
    pose_columns,
    search_renders,
)
from gsticker_plugin.decoders.reference import any_reference_view, cpu_sticker
from gsticker_plugin.decoders.result import decoded
from gsticker_plugin.views import progress_bar


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
    rounds: int = 3,
    renders: Optional[Dict[Tuple[int, int], Any]] = None,
) -> Dict[str, Any]:
    """Decode ``images`` (``[H W 3]`` each, cameras unknown) of the owner's scene against the owner's base
    ``reference`` (:func:`gsticker_plugin.decoders.reference.load_base_reference`): camera search, then the image fit
    with the pose Jacobian. ``value_mode``: read an image whose V matches the base render far better than its RGB
    by V alone (:func:`gsticker_plugin.decoders.image.reads_value`). ``rounds``: fits at most, each from the camera the
    previous one's pose step moved. ``renders``: the search's candidate renders per image size, kept by a caller that
    decodes images one call at a time (filled here). Returns the decoders' shared result, with
    per image the found camera (``c2w``), the pose fit's RMS and seconds in ``image``."""
    search = search or PoseSearch()
    st = cpu_sticker(reference.model)
    background = reference.model.background_color()
    gen = tie_generator(seed)
    renders = renders if renders is not None else {}
    bits: List[Tensor] = []
    details: List[Dict[str, Any]] = []
    names = list(names) if names is not None else [f"image/{i:04d}" for i in range(len(images))]
    for name, image in progress_bar(list(zip(names, images)), "camera search + image decoding", progress):
        t0 = time.time()
        hw = (int(image.shape[0]), int(image.shape[1]))
        if hw not in renders:
            renders[hw] = search_renders(reference, search, hw, value=True)
        pose = estimate_camera(reference, image, True, search, renders[hw])
        camera = pose.camera
        best: Optional[Tuple[float, Dict[str, Any], Any, int]] = None
        for k in range(rounds):  # Gauss-Newton on camera and message together: the fit's pose step moves the camera
            ref_view = any_reference_view(reference, f"unposed/{name}/{k}", camera, None)
            ref = image_reference(ref_view, background)
            value = value_mode and reads_value(image, ref_view.image)
            cols = pose_columns(reference.model, camera, ref_view.rays, value)
            y = image_at_rays(image, ref_view.rays, ref_view.hw)
            d = decode_image_view(ref, st, y, gen, iterations, value=value, pose_columns=cols)
            step = torch.tensor(d.pop("pose_step"))
            left = d["residual_rms"] * max(0.0, 1.0 - d["explained"]) ** 0.5  # what the joint fit leaves
            if best is None or left < best[0]:
                best = (left, d, camera, k + 1)
            if float(step.abs().max()) <= 1e-6:
                break
            camera = moved_camera(camera, step, camera_distance(camera))
        assert best is not None
        _, d, camera, used = best
        d.update(
            {
                "camera": "estimated",
                "c2w": camera.camera_to_worlds[0].tolist(),
                "round": used,
                "pose_rms": pose.rms,
                "pose_score": pose.score,
                "pose_iterations": pose.iterations,
                "seconds": time.time() - t0,
            }
        )
        bits.append(d.pop("bits"))
        details.append(d)
    return decoded(key, bits, "image", details)
