"""Pictures found in the wild, as the registered protocol draws them (docs/experiments/images-wild-protocol.md).

A picture is a render of the suspect at a test camera (the base's intrinsics and size), framed as a re-poster would:

- zoom ``z``, log-uniform over [0.7, 1.5]; output aspect ratio one of 1:1, 4:3, 3:4, 16:9, 9:16; output long side
  ``s`` times the base's, ``s`` one of 0.5, 1, 2, 3 (each with equal chance);
- the render is resized (bicubic) so that its long side is ``z`` times the output's long side, and placed on a black
  canvas of the output's size at an offset drawn uniformly over the positions that keep at least
  :data:`MIN_COVER` of the canvas covered by the render (rejection: offsets are drawn until one qualifies; a draw of
  zoom, aspect and size that no offset can cover is drawn again, from the same generator);
- then the row's attack, at its fixed magnitude (:data:`ROWS`), and an 8-bit PNG (or the JPEG of the row).

Everything comes from one generator seeded with the registered seed; the draws of a view do not depend on the row,
the model or on any decode. The picture's true camera (the base camera's intrinsics scaled by the framing and moved
by its offset) is kept beside it for the camera error.
"""

from __future__ import annotations

import io
import math
from dataclasses import asdict, dataclass
from typing import Callable, Dict, List, Sequence, Tuple

import numpy as np
import torch
from PIL import Image

from gsticker_plugin.attacks import cropout, gaussian_blur, gaussian_noise, hue_shift, rotate

REGISTERED_SEED = 1621744754
"""The protocol's camera seed (drawn with ``secrets.randbits(31)`` before any of its pictures was rendered)."""
ZOOM = (0.7, 1.5)
ASPECTS = ((1, 1), (4, 3), (3, 4), (16, 9), (9, 16))
SIDES = (0.5, 1.0, 2.0, 3.0)
MIN_COVER = 0.6
"""The share of the canvas the placed render must cover."""
MAX_TRIES = 1000


@dataclass(frozen=True)
class Framing:
    """One drawn framing: the test view, the zoom, the output size and where the resized render sits on it."""

    view: int
    zoom: float
    aspect: Tuple[int, int]
    side: float
    width: int
    height: int
    render_width: int
    render_height: int
    left: int
    top: int

    @property
    def cover(self) -> float:
        """The share of the canvas the render covers."""
        return cover_of(self.width, self.height, self.render_width, self.render_height, self.left, self.top)

    def as_dict(self) -> Dict:
        return {**asdict(self), "cover": self.cover}


def cover_of(w: int, h: int, rw: int, rh: int, left: int, top: int) -> float:
    """The share of a ``w`` x ``h`` canvas covered by an ``rw`` x ``rh`` render placed at (``left``, ``top``)."""
    x = max(0, min(w, left + rw) - max(0, left))
    y = max(0, min(h, top + rh) - max(0, top))
    return x * y / float(w * h)


def output_size(base_long: int, aspect: Tuple[int, int], side: float) -> Tuple[int, int]:
    """(width, height) of an output of ``aspect`` whose long side is ``side`` times ``base_long`` px."""
    long = max(1, round(side * base_long))
    a, b = aspect
    if a >= b:
        return long, max(1, round(long * b / a))
    return max(1, round(long * a / b)), long


def draw_framings(
    views: Sequence[int], base_hw: Tuple[int, int], seed: int = REGISTERED_SEED, count: int = 24
) -> List[Framing]:
    """``count`` framings of the protocol: each a test view drawn (without replacement) from ``views``, then its
    zoom, aspect, size and offset, all from one generator seeded with ``seed``."""
    if count > len(views):
        raise ValueError(f"{count} framings need as many distinct test views, got {len(views)}")
    g = np.random.default_rng(seed)
    chosen = [int(v) for v in g.choice(np.asarray(list(views)), size=count, replace=False)]
    h0, w0 = base_hw
    out = []
    for view in chosen:
        for _ in range(MAX_TRIES):
            zoom = float(math.exp(g.uniform(math.log(ZOOM[0]), math.log(ZOOM[1]))))
            aspect = ASPECTS[int(g.integers(len(ASPECTS)))]
            side = SIDES[int(g.integers(len(SIDES)))]
            w, h = output_size(max(h0, w0), aspect, side)
            f = zoom * max(w, h) / max(h0, w0)
            rw, rh = max(1, round(w0 * f)), max(1, round(h0 * f))
            lefts = (min(0, w - rw), max(0, w - rw))
            tops = (min(0, h - rh), max(0, h - rh))
            if cover_of(w, h, rw, rh, *_centred(w, h, rw, rh)) < MIN_COVER:
                continue  # the most covering (centred) place falls short: no offset can qualify
            for _ in range(MAX_TRIES):
                left = int(g.integers(lefts[0], lefts[1] + 1))
                top = int(g.integers(tops[0], tops[1] + 1))
                if cover_of(w, h, rw, rh, left, top) >= MIN_COVER:
                    break
            else:
                continue
            out.append(Framing(view, zoom, aspect, side, w, h, rw, rh, left, top))
            break
        else:
            raise RuntimeError(f"no framing of view {view} covers {MIN_COVER:.0%} in {MAX_TRIES} draws")
    return out


def _centred(w: int, h: int, rw: int, rh: int) -> Tuple[int, int]:
    return (w - rw) // 2, (h - rh) // 2


def frame(render: Image.Image, framing: Framing) -> Image.Image:
    """``render`` (the base camera's size) resized and placed on a black canvas as ``framing`` says."""
    resized = render.convert("RGB").resize((framing.render_width, framing.render_height), Image.BICUBIC)
    canvas = Image.new("RGB", (framing.width, framing.height), (0, 0, 0))
    canvas.paste(resized, (framing.left, framing.top))
    return canvas


def framed_intrinsics(fx: float, fy: float, cx: float, cy: float, base_hw: Tuple[int, int], framing: Framing) -> Dict:
    """The picture's true intrinsics: the base camera's scaled like the render and moved by its offset (pixel
    centres kept: a pixel edge at 0 maps to ``left``)."""
    h0, w0 = base_hw
    sx, sy = framing.render_width / w0, framing.render_height / h0
    return {
        "fx": fx * sx,
        "fy": fy * sy,
        "cx": cx * sx + framing.left,
        "cy": cy * sy + framing.top,
        "width": framing.width,
        "height": framing.height,
    }


# ---------------------------------------------------------------------------------------------- rows


def _tensor(im: Image.Image) -> torch.Tensor:
    return torch.from_numpy(np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0).permute(2, 0, 1)[None]


def _image(x: torch.Tensor) -> Image.Image:
    return Image.fromarray((x[0].permute(1, 2, 0).clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8))


def jpeg(im: Image.Image, quality: int) -> Image.Image:
    """``im`` saved as a Pillow JPEG of ``quality`` and read back (as a re-poster's encoder would)."""
    buf = io.BytesIO()
    im.convert("RGB").save(buf, "JPEG", quality=quality)
    buf.seek(0)
    return Image.open(buf).convert("RGB")


def _rotated(im: Image.Image, i: int) -> Image.Image:
    return _image(rotate(_tensor(im), 30.0 if i % 2 == 0 else -30.0, fill=1.0))


def _hue(turns: float) -> Callable[[Image.Image, int], Image.Image]:
    return lambda im, i: _image(hue_shift(_tensor(im), turns))


def _half_turn(im: Image.Image, i: int) -> Image.Image:
    return _hue(0.5 if i % 2 == 0 else -0.5)(im, i)


def _cropout(im: Image.Image, i: int) -> Image.Image:
    return _image(cropout(_tensor(im), 0.25, fill=1.0, generator=torch.Generator().manual_seed(REGISTERED_SEED + i)))


def _noise(im: Image.Image, i: int) -> Image.Image:
    return _image(gaussian_noise(_tensor(im), 0.1, generator=torch.Generator().manual_seed(REGISTERED_SEED + i)))


def _resized(im: Image.Image, i: int) -> Image.Image:
    w, h = im.size
    return im.resize((max(1, round(w / 2)), max(1, round(h / 2))), Image.BICUBIC)


def _crop_jpeg_hue(im: Image.Image, i: int) -> Image.Image:
    w, h = im.size
    cw, ch = max(1, round(w * 0.8)), max(1, round(h * 0.8))
    cropped = im.crop(((w - cw) // 2, (h - ch) // 2, (w - cw) // 2 + cw, (h - ch) // 2 + ch))
    return jpeg(_hue(0.25)(cropped, i), 70)


ROWS: Dict[str, Callable[[Image.Image, int], Image.Image]] = {
    "framed": lambda im, i: im,
    "rotation +-30": _rotated,
    "hue +-0.5": _half_turn,
    "cropout 25 %": _cropout,
    "noise 0.1": _noise,
    "JPEG 50": lambda im, i: jpeg(im, 50),
    "blur 1": lambda im, i: _image(gaussian_blur(_tensor(im), 1.0)),
    "resize 0.5": _resized,
    "crop + JPEG + hue": _crop_jpeg_hue,
}
"""The protocol's rows at their fixed magnitudes: what is done to the ``i``-th framed picture (``i`` seeds the
random ones: cropout's rectangle, the noise; even ``i`` turn by +30 degrees / +0.5 turn, odd ones by -30 / -0.5,
the protocol's "half the views each"). Rotation fills the corners white, cropout's rectangle is white."""
