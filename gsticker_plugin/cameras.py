"""Cameras of suspect images: a transforms JSON (Blender format or a capture's nerfstudio-data) read into frames,
images matched to frames by name, and each frame as a Nerfstudio camera at the image's size in the owner's base's
coordinates."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import torch
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras, CameraType
from torch import Tensor

from gsticker_plugin.errors import GStickerError

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp", ".hdr", ".tga", ".ppm"}
INTRINSIC_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")


def frame_name(path: str) -> str:
    """A frame's or an image's name for matching: posix path without a leading ``./`` and without an image suffix."""
    p = str(path).replace("\\", "/")
    while p.startswith("./"):
        p = p[2:]
    for s in IMAGE_SUFFIXES:
        if p.lower().endswith(s):
            return p[: -len(s)]
    return p


@dataclass(frozen=True)
class Frame:
    """One camera of a transforms JSON: its 4x4 OpenGL camera-to-world ``c2w`` in the file's coordinates, its
    ``intrinsics`` (the file's ``camera_angle_x/y`` or ``fl_x, fl_y, cx, cy, w, h``, per frame over the file's top
    level) and the file's ``applied`` transform and scale (:func:`applied_transform_of`)."""

    c2w: Float[Tensor, "4 4"]
    intrinsics: Dict[str, Any]
    applied: Tuple[Tensor, float]


def read_cameras_file(path) -> Dict[str, Frame]:
    """The frames of a Blender-style transforms JSON (``transforms_test.json``: ``camera_angle_x`` and per frame
    ``file_path`` and a 4x4 OpenGL camera-to-world ``transform_matrix``; nerfstudio's intrinsics ``fl_x, fl_y, cx,
    cy, w, h`` are read too, at the top level or per frame). Returns each :class:`Frame` by :func:`frame_name` of
    its ``file_path``. One-line errors for what cannot be used."""
    path = Path(path)
    if not path.is_file():
        raise GStickerError(f"--cameras {path} does not exist; pass the transforms JSON of the suspect images' cameras")
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise GStickerError(
            f"--cameras {path} is not readable JSON ({type(e).__name__}: {str(e)[:80]}); pass a "
            "transforms JSON (Blender format)"
        ) from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise GStickerError(
            f"--cameras {path} has no 'frames' list; pass a transforms JSON (Blender format: "
            "camera_angle_x and frames with file_path and transform_matrix)"
        )
    top = {k: meta[k] for k in INTRINSIC_KEYS if k in meta}
    applied = applied_transform_of(meta, path)
    out: Dict[str, Frame] = {}
    for i, fr in enumerate(frames):
        try:
            name = frame_name(fr["file_path"])
            c2w = torch.tensor(fr["transform_matrix"], dtype=torch.float32)
        except (KeyError, TypeError, ValueError) as e:
            raise GStickerError(
                f"--cameras {path}: frame {i} lacks a usable file_path/transform_matrix ({type(e).__name__}: {e})"
            ) from None
        if tuple(c2w.shape) == (3, 4):
            c2w = torch.cat([c2w, torch.tensor([[0.0, 0.0, 0.0, 1.0]])])
        if tuple(c2w.shape) != (4, 4) or not bool(torch.isfinite(c2w).all()):
            raise GStickerError(
                f"--cameras {path}: frame {i} ({name}) has a transform_matrix of shape "
                f"{tuple(c2w.shape)} or non-finite values; it must be a 4x4 camera-to-world matrix"
            )
        intr = {**top, **{k: fr[k] for k in INTRINSIC_KEYS if k in fr}}
        if "camera_angle_x" not in intr and "fl_x" not in intr:
            raise GStickerError(f"--cameras {path}: frame {i} ({name}) has no intrinsics (camera_angle_x or fl_x)")
        if "fl_x" in intr and not ("w" in intr and "h" in intr):
            raise GStickerError(
                f"--cameras {path}: frame {i} ({name}) gives fl_x without the image size w, h it refers to"
            )
        out[name] = Frame(c2w=c2w, intrinsics=intr, applied=applied)
    return out


def applied_transform_of(meta: Dict[str, Any], path) -> Tuple[Tensor, float]:
    """A nerfstudio transforms file's ``applied_transform`` (3x4 -> 4x4) and ``applied_scale``: what its poses already
    underwent from the original capture coordinates (identity and 1 when absent)."""
    a = torch.eye(4)
    if "applied_transform" in meta:
        try:
            a[:3] = torch.tensor(meta["applied_transform"], dtype=torch.float32).reshape(3, 4)
        except (TypeError, ValueError, RuntimeError) as e:
            raise GStickerError(
                f"--cameras {path}: applied_transform is not a 3x4 matrix ({type(e).__name__})"
            ) from None
    return a, float(meta.get("applied_scale", 1.0))


def match_frame(image_name: str, frames: Dict[str, Frame]) -> Optional[str]:
    """The frame of an image (its path relative to the images folder): the same name, else the same last
    component when exactly one frame has it (``r_0.png`` <-> ``./test/r_0``)."""
    name = frame_name(image_name)
    if name in frames:
        return name
    last = name.rsplit("/", 1)[-1]
    hits = [f for f in frames if f.rsplit("/", 1)[-1] == last]
    return hits[0] if len(hits) == 1 else None


@dataclass(frozen=True)
class PoseMap:
    """How a base run's dataparser maps the poses of its data files to run coordinates: ``c2w -> transform @ c2w``,
    then the translation times ``scale`` (nerfstudio's ``dataparser_transforms.json``)."""

    transform: Float[Tensor, "3 4"]
    scale: float

    def apply(self, c2w: Float[Tensor, "4 4"], applied: Optional[Tuple[Tensor, float]] = None) -> Float[Tensor, "3 4"]:
        """``c2w`` of a transforms file in run coordinates; ``applied``: the file's own applied transform and scale
        (:func:`applied_transform_of`), which the run's transform already includes."""
        t = torch.cat([self.transform.float(), torch.tensor([[0.0, 0.0, 0.0, 1.0]])])
        scale = self.scale
        if applied is not None:
            t = t @ torch.linalg.inv(applied[0])
            scale = scale / applied[1]
        out = (t @ c2w.float())[:3].clone()
        out[:, 3] *= scale
        return out


def same_aspect(width: float, height: float, w0: float, h0: float) -> bool:
    """Whether a ``width x height`` image has the aspect ratio of a ``w0 x h0`` camera (to 1 %): then the camera's
    intrinsics scale to it."""
    return abs(w0 / h0 - width / height) <= 0.01 * (w0 / h0)


def camera_for_image(frame: Frame, height: int, width: int, pose_map: Optional[PoseMap] = None):
    """A nerfstudio camera for an image of ``height x width`` px taken at ``frame`` (:func:`read_cameras_file`):
    the intrinsics scaled to the image's size, the pose put in the base run's coordinates by ``pose_map``
    (:func:`base_pose_map`; None: the file's own coordinates)."""

    intr = frame.intrinsics
    if "fl_x" in intr:
        w0, h0 = float(intr["w"]), float(intr["h"])
        if not same_aspect(width, height, w0, h0):
            raise GStickerError(
                f"a {width}x{height} image for a camera of {int(w0)}x{int(h0)} px (another aspect "
                "ratio): crop or pad it back to the camera's frame"
            )
        sx, sy = width / w0, height / h0
        fx = float(intr["fl_x"]) * sx
        fy = float(intr.get("fl_y", intr["fl_x"])) * sy
        cx, cy = float(intr.get("cx", w0 / 2)) * sx, float(intr.get("cy", h0 / 2)) * sy
    else:
        fx = 0.5 * width / math.tan(0.5 * float(intr["camera_angle_x"]))
        fy = 0.5 * height / math.tan(0.5 * float(intr["camera_angle_y"])) if "camera_angle_y" in intr else fx
        cx, cy = width / 2.0, height / 2.0
    c2w = (pose_map or PoseMap(torch.eye(4)[:3], 1.0)).apply(frame.c2w, frame.applied)
    return Cameras(
        camera_to_worlds=c2w[None],
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        width=int(width),
        height=int(height),
        camera_type=CameraType.PERSPECTIVE,
    )
