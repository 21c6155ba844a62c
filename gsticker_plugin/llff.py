"""An LLFF capture (``poses_bounds.npy`` beside its images) as a nerfstudio-data ``transforms.json``.

``python -m gsticker_plugin.llff --input fern --images images_16 [--resolution 100] [--every-test 8]``

``poses_bounds.npy`` holds one row of 17 numbers per image: a 3 x 5 matrix ``[R | t | (h, w, f)]`` (row-major) and
the near and far bounds. The rotation's columns are the camera's *down*, *right* and *backwards* axes in world
coordinates, and ``(h, w, f)`` the full-resolution size and focal length. Nerfstudio wants OpenGL camera-to-world
matrices (*right*, *up*, *backwards*) ::

    c2w = [ R[:, 1] | -R[:, 0] | R[:, 2] | t ]

and intrinsics at the images' own size: ``f`` scaled by ``image width / w``, the principal point at the centre.
Images pair with rows in sorted file-name order (how LLFF wrote them). With ``--resolution N`` the images are
written again with their longer side ``N`` (area average) into ``images_N/``. Every ``--every-test``-th image is
a test view (LLFF's hold-out), the others train; the split goes into ``transforms.json`` so ``ns-train`` and
``ns-verify-owner --cameras`` use the same cameras.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import tyro
from jaxtyping import Float

from gsticker_plugin.errors import GStickerError, run_command

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def llff_to_opengl(poses_bounds: Float[np.ndarray, "N 17"]) -> Float[np.ndarray, "N 4 4"]:
    """OpenGL camera-to-world matrices from LLFF rows (see the module's docstring)."""
    m = np.asarray(poses_bounds, dtype=np.float64)[:, :15].reshape(-1, 3, 5)
    r, t = m[:, :, :3], m[:, :, 3]
    c2w = np.tile(np.eye(4), (len(m), 1, 1))
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = r[:, :, 1], -r[:, :, 0], r[:, :, 2], t
    return c2w


def transforms(
    poses_bounds: Float[np.ndarray, "N 17"], names: List[str], width: int, height: int, every_test: int
) -> Dict[str, Any]:
    """The ``transforms.json`` of ``names`` (image paths relative to the capture folder, one per row) at
    ``width x height`` px."""
    if len(names) != len(poses_bounds):
        raise GStickerError(
            f"{len(names)} images for {len(poses_bounds)} poses in poses_bounds.npy; pass --images with the folder "
            "that holds exactly one image per pose"
        )
    h0, w0, f0 = (float(x) for x in np.asarray(poses_bounds)[0, :15].reshape(3, 5)[:, 4])
    if abs(w0 / h0 - width / height) > 0.02 * (w0 / h0):
        raise GStickerError(f"images of {width}x{height} px for poses of {w0:.0f}x{h0:.0f} px: not the same frame")
    f = f0 * width / w0
    c2w = llff_to_opengl(poses_bounds)
    test = [n for i, n in enumerate(names) if every_test > 0 and i % every_test == 0]
    return {
        "camera_model": "OPENCV",
        "fl_x": f,
        "fl_y": f,
        "cx": width / 2.0,
        "cy": height / 2.0,
        "w": width,
        "h": height,
        "frames": [{"file_path": n, "transform_matrix": m.tolist()} for n, m in zip(names, c2w)],
        "train_filenames": [n for n in names if n not in test],
        "val_filenames": test,
        "test_filenames": test,
    }


@dataclass
class LLFFConfig:
    """Write a nerfstudio-data transforms.json for an LLFF capture (poses_bounds.npy beside its images)."""

    input: Path
    """The capture folder: poses_bounds.npy and an images folder."""
    images: str = "images_8"
    """The images folder inside it (LLFF's images, images_4, images_8, ...)."""
    resolution: Optional[int] = None
    """Write the images again with this longer side (px) into images_N/ and point the transforms there."""
    every_test: int = 8
    """Every this-many-th image is a test (and val) view; 0: none."""


def main(cfg: LLFFConfig) -> int:
    from PIL import Image

    folder = Path(cfg.input)
    pb_path = folder / "poses_bounds.npy"
    if not pb_path.is_file():
        raise GStickerError(f"no poses_bounds.npy in {folder}; pass --input with an LLFF capture folder")
    poses_bounds = np.load(pb_path, allow_pickle=False)
    if poses_bounds.ndim != 2 or poses_bounds.shape[1] != 17:
        raise GStickerError(f"{pb_path} holds an array of shape {poses_bounds.shape}, not N x 17")
    src = folder / cfg.images
    files = sorted(p for p in src.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if src.is_dir() else []
    if not files:
        raise GStickerError(f"no images in {src}; pass --images with the folder of the capture's images")
    with Image.open(files[0]) as im:
        width, height = im.size
    names = [str(p.relative_to(folder)) for p in files]
    if cfg.resolution is not None:
        k = cfg.resolution / max(width, height)
        width, height = max(1, round(width * k)), max(1, round(height * k))
        out_dir = folder / f"images_{cfg.resolution}"
        out_dir.mkdir(exist_ok=True)
        names = []
        for p in files:
            with Image.open(p) as im:
                im.convert("RGB").resize((width, height), Image.Resampling.BOX).save(out_dir / (p.stem + ".png"))
            names.append(f"{out_dir.name}/{p.stem}.png")
    meta = transforms(poses_bounds, names, width, height, cfg.every_test)
    (folder / "transforms.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(
        f"wrote {folder / 'transforms.json'}: {len(names)} images of {width}x{height} px, {len(meta['test_filenames'])} test"
    )
    return 0


def entrypoint() -> None:
    cfg = tyro.cli(LLFFConfig)
    raise SystemExit(run_command(lambda: main(cfg)))


if __name__ == "__main__":
    entrypoint()
