"""The informed *image* decoder: read the owner's message from images of the scene taken at known cameras.

Over 600 lines on purpose: the fit, its degradation matching and the suspect images' cameras are one decoder; split
further, each piece would import the others.

The geometric decoder (:mod:`gsticker_plugin.decoders.geometric`) reads a suspect *model's* accumulation and depth. An
image shows only colour, but the colour a NeRF renders is the composite of its sample colours with the density the
sticker changed: ``pixel = clamp(sum_i w_i(sigma~) c_i + (1 - acc(sigma~)) bg)``. Given the owner's base (the key
records it, as for the geometric decoder) and the camera of each image, the change the sticker of a continuous
message ``s`` makes to the base render at that camera is predicted exactly on the base's own samples, with the
base's own colours, and ``s`` is fitted to ``image - base render`` by the same Levenberg-Marquardt fit
(:func:`gsticker_plugin.decoders.fit.fit_message`, Jacobian in closed form); bit ``i`` = ``s_i > 0``, undetermined
bits count as mismatches.

What it reads: images at *known* cameras (renders of the scene at the base's cameras, e.g. the evaluation
protocol's test views), as they are or after image distortions (noise, blur, JPEG, resize, cropout, rotation,
hue shifts: :mod:`gsticker_plugin.attacks`). Blur, resize, rotation and JPEG are estimated from the base render
alone and fitted through (:func:`match_degradation`, :func:`decode_selected`); whatever else an attack does is
residual the fit has to live with, so its robustness curves measure the mark, not a trained invariance. A
recoloured *model* changes the sample colours, which this decoder takes from the base: recolouring is read by the
geometric decoder, which does not look at colour at all.

Why the binomial null holds: as for the geometric decoder, the fit uses the image, the base and the sticker, never
the owner's message, and the sticker was trained on uniformly random messages; for an image that does not carry
``M`` the decoded bits are independent of ``M``.

Limits: informed (needs the base run) and posed (needs each image's camera); a screenshot of unknown pose cannot
be read. :func:`gsticker_plugin.verify` keeps the blind extractor for those.
"""

from __future__ import annotations

import contextlib
import sys
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from torch import Tensor

from gsticker_plugin.attacks import ATTACKS, gaussian_blur, resize, rotate
from gsticker_plugin.background import Background
from gsticker_plugin.cameras import Frame, PoseMap, camera_for_image, match_frame
from gsticker_plugin.decoders.cover import covered_pixels
from gsticker_plugin.decoders.fit import (
    fit_and_decide,
    fit_summary,
    per_ray_jacobian,
    tie_generator,
)
from gsticker_plugin.decoders.geometric import marked_density
from gsticker_plugin.decoders.reference import any_reference_view, cpu_sticker
from gsticker_plugin.decoders.result import Decoded, decoded
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.sticker import Sticker, render_weights
from gsticker_plugin.views import View, Views, progress_bar


@dataclass
class ImageReferenceView:
    """One camera of the owner's base in the image decoder's terms."""

    view: (
        Any  # gsticker_plugin.decoders.reference.ReferenceView (rays, samples, gate, sticker features, sample colours)
    )
    background: Background
    base_rgb: Float[Tensor, "R 3"]  # the base render at the rays (what the suspect image is compared with)


def image_reference(ref_view, background: Union[Float[Tensor, " 3"], Background]) -> ImageReferenceView:
    if ref_view.rgb is None:
        raise GStickerError("the reference view holds no sample colours (made by an older gsticker); rebuild it")
    h, w = ref_view.hw
    base = ref_view.image.permute(1, 2, 0).reshape(h * w, 3)[ref_view.rays].float()
    return ImageReferenceView(view=ref_view, background=Background.of(background).to("cpu"), base_rgb=base)


def rgb_of_sticker(ref: ImageReferenceView, m: Float[Tensor, "N 1"]) -> Float[Tensor, "R 3"]:
    """The rendered colour at the rays with sticker values ``m`` at the gate-open samples: the same wrap
    (``relu(sigma + psi * scale * m)``), quadrature, background and clamp as the renderer."""

    v = ref.view
    w = render_weights(marked_density(v, m), v.deltas)
    rgb = (w * v.rgb).sum(dim=-2) + ref.background.fill(v.rgb) * (1.0 - w.sum(dim=-2))
    return rgb.clamp(0.0, 1.0)


def predict_image_change(ref: ImageReferenceView, sticker: Sticker, signs: Float[Tensor, " K"]) -> Float[Tensor, "R 3"]:
    """The base render's colour at the rays with the sticker of continuous message ``signs`` (the fit subtracts
    its value at ``s = 0``); differentiable in ``signs``."""
    return rgb_of_sticker(ref, sticker.mix(ref.view.features, signs))


def image_change_jacobian(
    ref: ImageReferenceView, sticker: Sticker, signs: Float[Tensor, " K"]
) -> Optional[Float[Tensor, "M K"]]:
    """d predict_image_change / d signs, rows ``r * 3 + c`` like ``predict_image_change(...).reshape(-1)``
    (None: no closed form for this sticker; the fit then uses forward-mode AD)."""

    v = ref.view
    r, s = v.density.shape[:2]
    j = per_ray_jacobian(lambda x: rgb_of_sticker(ref, x).T, sticker, v.features, signs, v.open_index // s, r)
    return None if j is None else j.permute(1, 0, 2).reshape(-1, j.shape[-1])


LUMA = (0.299, 0.587, 0.114)
"""The luma row of JPEG's RGB -> YCbCr conversion (ITU-R BT.601): the channel JPEG keeps at full resolution."""


def observe(rows: Tensor, luma: bool) -> Tensor:
    """What a fit reads of colour rows ``[..., 3, K]`` (rows ``p * 3 + c`` flattened as ``[P * 3, K]`` or ``[P * 3]``):
    all three channels, or their luma alone (``[P, K]`` / ``[P]``)."""
    if not luma:
        return rows
    k = rows.shape[1:] if rows.ndim > 1 else ()
    w = torch.tensor(LUMA, dtype=rows.dtype, device=rows.device)
    return torch.einsum("pc...,c->p...", rows.reshape(-1, 3, *k), w)


def decode_image_view(
    ref: ImageReferenceView,
    sticker: Sticker,
    image_rgb: Float[Tensor, "R 3"],
    generator: torch.Generator,
    iterations: int = 10,
    luma: bool = False,
    value: bool = False,
    pose_columns: Optional[Float[Tensor, "M 6"]] = None,
) -> Dict[str, Any]:
    """Fit the continuous message to one image's colour change (image minus base render) and decide the bits;
    ``luma``: read the change's luma only (what JPEG keeps at full resolution); ``value``: read the change of
    V = max(R, G, B) only, which an HSV hue shift leaves exactly as it is (its Jacobian: the rows of the channel
    that holds the maximum). ``pose_columns``: d base render / d pose at the rays (RGB rows ``r * 3 + c``, or V rows
    with ``value``): an estimated camera's small error is fitted alongside the message (:func:`without_columns`);
    the result then holds the fitted ``pose_step`` and the fitted message's change at the rays (``mark_change``, rows
    as the pose columns')."""
    if value:
        signal = "value"
        target = image_rgb.float().amax(dim=-1) - ref.base_rgb.amax(dim=-1)

        def predict(x: Tensor) -> Tensor:
            return predict_image_change(ref, sticker, x).amax(dim=-1)

        def jac(x: Tensor) -> Optional[Tensor]:
            j = image_change_jacobian(ref, sticker, x)
            if j is None:
                return None
            top = predict_image_change(ref, sticker, x).detach().argmax(dim=-1)  # [R]
            j = j.reshape(-1, 3, j.shape[-1])
            return j[torch.arange(j.shape[0]), top]

    else:
        signal = "luma" if luma else "rgb"
        target = observe((image_rgb.float() - ref.base_rgb).reshape(-1), luma)

        def predict(x: Tensor) -> Tensor:
            return observe(predict_image_change(ref, sticker, x).reshape(-1), luma)

        def jac(x: Tensor) -> Optional[Tensor]:
            j = image_change_jacobian(ref, sticker, x)
            return None if j is None else observe(j, luma)

    all_cols = None if pose_columns is None else (observe(pose_columns, luma) if not value else pose_columns)
    per_pixel = 1 if (luma or value) else 3
    keep = occluded = occlusion_keep(image_rgb.float() - ref.base_rgb, per_pixel, ref.view.rays, ref.view.hw)
    covered = None
    for _ in range(2):  # the second fit leaves out a covered rectangle the first one's mark is missing from
        t, p, j, cols = target, predict, jac, all_cols
        if keep is not None:  # rows of pixels that hold something the base does not (a cropout) are left out
            t, p, j = on_rows(keep, t, p, j)
            cols = None if cols is None else cols[keep]
        plain = (t, p)
        if cols is not None:  # the fit sees only what a small pose change of the base render cannot explain
            t, p, j = without_columns(cols, t, p, j)
        fit, bits, undetermined = fit_and_decide(
            p, j, t, sticker.num_bits, ref.view.rays.numel() > 0, generator, iterations
        )
        with torch.no_grad():  # the fitted message's change at the rows read
            mark = plain[1](fit.signs) - plain[1](torch.zeros_like(fit.signs))
        if covered is not None or ref.view.rays.numel() == 0:
            break
        kept = torch.ones(ref.view.rays.numel(), dtype=torch.bool) if keep is None else keep[::per_pixel]
        covered = covered_pixels(plain[0], mark, ref.view.rays[kept], ref.view.hw)
        if covered is None:
            break
        inside = torch.zeros_like(kept).masked_scatter(kept, covered)
        keep = (kept & ~inside).repeat_interleave(per_pixel)
    out = {"bits": bits, **fit_summary(fit, undetermined, int(ref.view.rays.numel())), "signals": [signal]}
    out["occluded_share"] = 0.0 if occluded is None else float(1.0 - occluded.double().mean())
    out["covered_share"] = 0.0 if covered is None else float(covered.double().sum()) / max(1, ref.view.rays.numel())
    if cols is not None:  # the pose change fitted beside the message (a step for the camera)
        with torch.no_grad():
            rest = plain[0] - mark
            if keep is not None:  # the change at every row: none at the rows left out
                mark = torch.zeros(keep.numel(), dtype=mark.dtype).masked_scatter(keep, mark)
        out["mark_change"] = mark.detach()
        step = torch.linalg.lstsq(cols.double(), rest.double()[:, None]).solution[:, 0] if cols.numel() else None
        out["pose_step"] = [0.0] * 6 if step is None else [float(v) for v in step]
    return out


OCCLUSION_CHANGE = 0.25
"""A pixel whose colour differs from the base render's by more than this in some channel holds something the base
does not (a cropout's fill, an overlay): the mark changes a pixel by at most ~0.11 (lego100, 45 dB)."""

OCCLUSION_SHARE = 0.01
"""Such pixels are left out of the fit when they are at least this share of the pixels read (fewer: edges)."""

OCCLUSION_NEIGHBOURS = 0.5
"""... and only those that at least this share of their read 3 x 3 neighbours join: a fill covers a patch, while
noise's far pixels stand alone (leaving them out would bias the fit: the ones kept lean against the mark)."""


def occlusion_keep(
    change: Float[Tensor, "R 3"], per_pixel: int, rays: Int[Tensor, " R"], hw: Tuple[int, int]
) -> Optional[Tensor]:
    """The fit's rows to keep (``per_pixel`` rows per pixel) when :data:`OCCLUSION_SHARE` or more of the pixels
    (``rays``: their flat indices into an ``hw`` image) change by more than :data:`OCCLUSION_CHANGE` in patches
    (:data:`OCCLUSION_NEIGHBOURS`); None (keep all) otherwise."""
    far = change.abs().amax(dim=-1) > OCCLUSION_CHANGE
    if bool(far.any()):
        grid = torch.zeros(2, hw[0] * hw[1], dtype=torch.float32)
        grid[0, rays] = far.float()
        grid[1, rays] = 1.0
        counts = F.avg_pool2d(grid.view(1, 2, *hw), 3, stride=1, padding=1, divisor_override=1).view(2, -1)[:, rays]
        far = far & (counts[0] >= OCCLUSION_NEIGHBOURS * counts[1])
    if far.numel() == 0 or float(far.double().mean()) < OCCLUSION_SHARE:
        return None
    return (~far).repeat_interleave(per_pixel)


def on_rows(keep: Tensor, target: Tensor, predict, jac):
    """``target``, ``predict`` and ``jac`` restricted to the rows ``keep``."""

    def jac_kept(x: Tensor) -> Optional[Tensor]:
        j = jac(x)
        return None if j is None else j[keep]

    return target[keep], (lambda x: predict(x)[keep]), jac_kept


def without_columns(columns: Float[Tensor, "M P"], target: Tensor, predict, jac):
    """``target``, ``predict`` and ``jac`` projected onto the complement of ``columns``' span: a least-squares fit of
    the message then equals the joint fit of the message and free coefficients of ``columns``."""
    q = torch.linalg.qr(columns.double())[0]

    def project(x: Tensor) -> Tensor:
        x64 = x.double()
        return (x64 - q @ (q.T @ x64)).to(x.dtype)

    def jac_projected(x: Tensor) -> Optional[Tensor]:
        j = jac(x)
        return None if j is None else project(j)

    return project(target), (lambda x: project(predict(x))), jac_projected


VALUE_MARGIN = 0.25
"""An image is read by its V channel when its V differs from the base render's by at most this share of how much its
RGB differs (mean squared): a hue shift moves RGB and leaves V; the mark alone moves both alike."""


def reads_value(image: Float[Tensor, "H W 3"], base: Float[Tensor, "3 H W"], margin: float = VALUE_MARGIN) -> bool:
    """Whether ``image`` looks like a hue-shifted render of ``base`` (see :data:`VALUE_MARGIN`); image and base only."""
    x, b = image.float(), base.float().permute(1, 2, 0)
    rgb_err = float(((x - b) ** 2).mean())
    value_err = float(((x.amax(dim=-1) - b.amax(dim=-1)) ** 2).mean())
    return rgb_err > 0 and value_err < margin * rgb_err


# ================================================================================================================
# degradations the decoder can match: estimated from the base render alone, never from the message
# ================================================================================================================

DEGRADATION_GRID: Dict[str, Tuple[float, ...]] = {
    "blur": tuple(round(0.25 * i, 2) for i in range(1, 17)),  # Gaussian sigma 0.25 .. 4 px
    "resize": tuple(round(0.2 + 0.05 * i, 2) for i in range(16)),  # scale 0.2 .. 0.95
    "rotate": tuple(float(d) for d in range(-45, 46) if d != 0),  # degrees, 1 degree apart
    "jpeg": (100.0, 95.0, 90.0, 80.0, 70.0, 60.0, 50.0, 40.0, 30.0, 20.0, 10.0),  # quality
}
"""The image decoder's search grid (``degradations="match"``): each image's degradation is the entry whose
transform of the *base render* is closest to the image (least squares over all pixels; the identity unless one
is clearly closer, :data:`MATCH_MARGIN`).
It contains every strength the protocol's curves test: the curves then measure the mark given a correctly
identified degradation, an upper bound for decoding an image of unknown processing."""


@dataclass(frozen=True)
class Degradation:
    """An image transform of :mod:`gsticker_plugin.attacks` (``blur``, ``resize``, ``rotate``, ``jpeg``; ``none``)."""

    name: str = "none"
    strength: float = 0.0

    def apply(self, x: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B 3 H W"]:
        """The attack itself (clamped, rotation's white fill): what it does to the base render."""
        return x if self.name == "none" else ATTACKS[self.name](x, self.strength)

    def linear(self, x: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B 3 H W"]:
        """The attack's linear part, unclamped: what it does to a small change of the image (rotation's fill is
        0; for JPEG the identity: the fit reads its luma, which the codec keeps whole before quantizing)."""
        if self.name == "none":
            return x
        if self.name == "blur":
            return gaussian_blur(x, self.strength, clamp=False)
        if self.name == "resize":
            return resize(x, self.strength, clamp=False)
        if self.name == "rotate":
            return rotate(x, self.strength, fill=0.0, clamp=False)
        if self.name == "jpeg":  # read through its luma (:attr:`luma`), which the codec does not resample
            return x
        raise GStickerError(f"unknown degradation {self.name!r}")

    @property
    def luma(self) -> bool:
        """Whether an image of this degradation is read by its luma alone: JPEG halves the chroma resolution (4:2:0,
        kornia's codec and most encoders' default) with filters that differ between encoders, and keeps luma whole;
        its quantization is noise the fit lives with."""
        return self.name == "jpeg"

    def label(self) -> str:
        return "none" if self.name == "none" else f"{self.name}={self.strength:g}"


MATCH_MARGIN = 0.5
"""A degradation is chosen over the identity only when its transform of the base render leaves at most this share
of the identity's squared error: the mark itself is a (small) difference between image and base that a mild blur
can happen to reduce (seen on a 32 px scene with a strong mark), while a real blur, resize or rotation of a scene
with edges leaves a few percent of it."""


def match_degradation(
    image: Float[Tensor, "H W 3"],
    base: Float[Tensor, "3 H W"],
    grid: Optional[Dict[str, Sequence[float]]] = None,
    margin: float = MATCH_MARGIN,
) -> Tuple[Degradation, float]:
    """The degradation of ``grid`` whose transform of the base render is closest to ``image``, or the identity when
    none leaves less than ``margin`` of the identity's squared error; returns it and its mean squared error. Uses
    the image and the base only (not the message or the sticker)."""
    grid = DEGRADATION_GRID if grid is None else grid
    x = image.permute(2, 0, 1)[None].float()
    b = base[None].float()
    identity_err = float(((x - b) ** 2).mean())
    best, best_err = Degradation(), float("inf")
    for c in (Degradation(n, float(v)) for n, vals in grid.items() for v in vals):
        err = float(((x - c.apply(b)) ** 2).mean())
        if err < best_err:
            best, best_err = c, err
    if best_err < margin * identity_err:
        return best, best_err
    return Degradation(), identity_err


def amplitude_spectrum(x: Float[Tensor, "... H W"]) -> Float[Tensor, "... H F"]:
    """``|FFT(x)|`` of each channel, its mean taken off and a Hann window applied: unchanged by a small shift of the
    content (a camera a few tenths of a degree off), changed by a blur."""
    h, w = x.shape[-2:]
    win = torch.hann_window(h, periodic=False, dtype=x.dtype)[:, None] * torch.hann_window(
        w, periodic=False, dtype=x.dtype
    )
    return torch.fft.rfft2((x - x.mean(dim=(-2, -1), keepdim=True)) * win).abs()


def match_blur_spectrum(
    image: Float[Tensor, "H W 3"],
    base: Float[Tensor, "3 H W"],
    sigmas: Optional[Sequence[float]] = None,
    margin: float = MATCH_MARGIN,
) -> Degradation:
    """The Gaussian blur (``sigmas``, default :data:`DEGRADATION_GRID`'s) whose blur of the base render has the
    amplitude spectrum nearest the image's, or the identity unless it leaves at most ``margin`` of the identity's
    squared spectral error. :func:`match_degradation` compares pixels and so needs the camera exact; this needs it
    only roughly."""
    sigmas = DEGRADATION_GRID["blur"] if sigmas is None else sigmas
    target = amplitude_spectrum(image.permute(2, 0, 1).double())
    b = base[None].double()
    identity_err = float(((target - amplitude_spectrum(b[0])) ** 2).sum())
    best, best_err = Degradation(), float("inf")
    for sigma in sigmas:
        c = Degradation("blur", float(sigma))
        err = float(((target - amplitude_spectrum(c.apply(b)[0])) ** 2).sum())
        if err < best_err:
            best, best_err = c, err
    return best if best_err < margin * identity_err else Degradation()


def decode_degraded_view(
    ref: ImageReferenceView,
    sticker: Sticker,
    image: Float[Tensor, "H W 3"],
    degradation: Degradation,
    generator: torch.Generator,
    iterations: int = 10,
    luma: Optional[bool] = None,
    pose_columns: Optional[Float[Tensor, "M 6"]] = None,
) -> Dict[str, Any]:
    """:func:`decode_image_view` for an image the degradation ``D`` was applied to: the image is compared with
    ``D(base render)`` over every pixel, and the change is predicted as ``D_lin(change on the base's rays)``;
    ``luma`` (default: the degradation's own :attr:`Degradation.luma`): compare luma only. ``pose_columns``: d base
    render / d pose at the rays (RGB rows ``r * 3 + c``), taken through ``D_lin`` too and fitted beside the message
    (:func:`without_columns`)."""

    luma = degradation.luma if luma is None else luma
    if degradation.name == "none":
        d = decode_image_view(
            ref, sticker, image_at_rays(image, ref.view.rays, ref.view.hw), generator, iterations, luma=luma
        )
        d["degradation"] = "none"
        return d
    h, w = ref.view.hw
    rays = ref.view.rays
    base = ref.view.image.float()  # [3 H W]
    target = observe(
        (image.float().permute(2, 0, 1) - degradation.apply(base[None])[0]).permute(1, 2, 0).reshape(-1), luma
    )

    def spread(per_ray: Tensor) -> Tensor:  # [R 3 ...] at the rays -> D_lin of the whole image, rows p * 3 + c
        cols = per_ray.reshape(rays.numel(), 3, -1)
        full = torch.zeros(h * w, 3, cols.shape[-1], dtype=cols.dtype).index_copy(0, rays, cols)
        img = full.permute(2, 1, 0).reshape(-1, 3, h, w)  # [K 3 H W]
        return observe(degradation.linear(img).reshape(-1, 3, h * w).permute(2, 1, 0).reshape(h * w * 3, -1), luma)

    def predict(sg: Tensor) -> Tensor:
        return spread(predict_image_change(ref, sticker, sg) - ref.base_rgb)[:, 0]

    def jac(sg: Tensor) -> Optional[Tensor]:
        j = image_change_jacobian(ref, sticker, sg)
        return None if j is None else spread(j)

    plain, cols = (target, predict), None
    if pose_columns is not None:  # the fit sees only what a small pose change of the degraded render cannot explain
        cols = spread(pose_columns.float())
        target, predict, jac = without_columns(cols, target, predict, jac)
    fit, bits, undetermined = fit_and_decide(
        predict, jac, target, sticker.num_bits, rays.numel() > 0, generator, iterations
    )
    out = {
        "bits": bits,
        **fit_summary(fit, undetermined, int(rays.numel())),
        "signals": ["luma" if luma else "rgb"],
        "degradation": degradation.label(),
    }
    if cols is not None:  # the pose change fitted beside the message (a step for the camera)
        with torch.no_grad():
            rest = plain[0] - (plain[1](fit.signs) - plain[1](torch.zeros_like(fit.signs)))
            step = torch.linalg.lstsq(cols.double(), rest.double()[:, None]).solution[:, 0]
        out["pose_step"] = [float(v) for v in step]
    return out


def residual_cost(ref: ImageReferenceView, image: Float[Tensor, "H W 3"], d: Dict[str, Any]) -> float:
    """The squared residual a fit leaves over the whole image: an identity fit reads the rays only, the pixels
    outside them count with the image's whole difference from the base render."""
    h, w = ref.view.hw
    luma = d["signals"] == ["luma"]
    m = (1 if luma else 3) * (h * w if d["degradation"] != "none" else int(ref.view.rays.numel()))
    cost = (1.0 - d["explained"]) * d["residual_rms"] ** 2 * m
    if d["degradation"] == "none":
        outside = torch.ones(h * w, dtype=torch.bool)
        outside[ref.view.rays] = False
        diff = image.float().reshape(-1, 3) - ref.view.image.float().permute(1, 2, 0).reshape(-1, 3)
        cost += float((observe(diff[outside].reshape(-1), luma).double() ** 2).sum())
    return cost


def decode_selected(
    ref: ImageReferenceView,
    sticker: Sticker,
    image: Float[Tensor, "H W 3"],
    degradation: Degradation,
    generator: torch.Generator,
    iterations: int = 10,
) -> Dict[str, Any]:
    """Decode through ``degradation`` and, when it is not the identity, also without it; keep the fit that leaves
    the smaller residual over the whole image (a strong mark on a plain scene can make a transform of the base look
    closer than the base itself); both are compared in the channels the matched degradation keeps (JPEG: luma), and
    an identity that wins is then read in RGB, as an unmatched image is. Both fits use the image, the base and the sticker only, never the message."""
    if degradation.name == "none":
        return decode_degraded_view(ref, sticker, image, degradation, generator, iterations)
    state = generator.get_state()
    fits = []
    for deg in (Degradation(), degradation):  # both read what the matched degradation keeps (JPEG: luma)
        g = torch.Generator().set_state(state)
        d = decode_degraded_view(ref, sticker, image, deg, g, iterations, luma=degradation.luma)
        fits.append((residual_cost(ref, image, d), d, g))
    cost, d, g = min(fits, key=lambda f: f[0])
    if d["degradation"] == "none" and degradation.luma:  # the identity won: read all three channels, as unmatched
        g = torch.Generator().set_state(state)
        d = decode_degraded_view(ref, sticker, image, Degradation(), g, iterations)
    generator.set_state(g.get_state())
    d["residual_cost_none"], d["residual_cost_matched"] = fits[0][0], fits[1][0]
    return d


def image_at_rays(image: Float[Tensor, "H W 3"], rays: Int[Tensor, " R"], hw: Tuple[int, int]) -> Float[Tensor, "R 3"]:
    if tuple(image.shape[:2]) != tuple(hw) or image.shape[-1] != 3:
        raise GStickerError(
            f"an image of {tuple(image.shape)} for a {hw[0]}x{hw[1]} camera; the image decoder needs "
            "RGB images of the cameras' size (resize them to it)"
        )
    return image.float().reshape(-1, 3)[rays]


def decode_posed_images(
    key,
    reference,
    images: Sequence[Float[Tensor, "H W 3"]],
    cameras: Sequence[Tuple[str, Any]],
    seed: int,
    iterations: int = 10,
    ref_cache: Optional[Dict[Any, Any]] = None,
    progress: bool = False,
    degradations: Optional[str] = "match",
    value_mode: bool = True,
) -> Decoded:
    """Decode ``images[i]``, taken at ``cameras[i] = (name, camera)`` of the owner's scene, with the informed image
    decoder. ``images``: a ``[V H W 3]`` tensor or a list of ``[H W 3]`` images (sizes may differ, each its camera's).

    ``reference``: the owner's base with the key's sticker and gates
    (:func:`gsticker_plugin.decoders.reference.load_base_reference`). ``ref_cache``: a dict the caller keeps to reuse the
    base's reference views of these cameras (the same keys as the geometric decoder's, so one cache serves both).
    ``degradations="match"``: first estimate each image's blur, resize, rotation or JPEG quality from the base
    render alone (:func:`match_degradation` over :data:`DEGRADATION_GRID`), fit through it and without it, and keep
    the fit with the smaller residual (:func:`decode_selected`);
    ``None``: compare the image with the base render as it is. ``value_mode``: read an image whose V matches the base
    render's far better than its RGB (a hue shift, :func:`reads_value`) by its V channel.
    Returns per image ``bits``, ``matches``, ``bit_acc``, ``pvalues``, ``scores`` (None) and ``image`` (the fits).
    """

    if len(images) != len(cameras) or any(im.ndim != 3 for im in images):
        raise GStickerError(f"{len(images)} images for {len(cameras)} cameras: pass one [H W 3] image per camera")
    st = cpu_sticker(reference.model)
    background = reference.model.background_color()
    gen = tie_generator(seed)
    ref_cache = {} if ref_cache is None else ref_cache
    bits: List[Tensor] = []
    details: List[Dict[str, Any]] = []
    for (name, cam), image in progress_bar(list(zip(cameras, images)), "image decoding", progress):
        ref_view = any_reference_view(reference, name, cam, ref_cache)
        ref = image_reference(ref_view, background)
        image_at_rays(image, ref_view.rays, ref_view.hw)  # checks the size
        deg = match_degradation(image, ref_view.image)[0] if degradations == "match" else Degradation()
        if value_mode and degradations == "match" and deg.name == "none" and reads_value(image, ref_view.image):
            d = decode_image_view(
                ref, st, image_at_rays(image, ref_view.rays, ref_view.hw), gen, iterations, value=True
            )
            d["degradation"] = "none"
        else:
            d = decode_selected(ref, st, image, deg, gen, iterations)
        bits.append(d.pop("bits"))
        details.append(d)
    return decoded(key, bits, "image", details)


# ================================================================================================================
# cameras of suspect images (ns-verify-owner --images DIR --cameras transforms.json)
# ================================================================================================================


POSE_DATAPARSERS = (BlenderDataParserConfig, NerfstudioDataParserConfig)
"""Dataparsers whose pose normalization is fully recorded in their outputs' ``dataparser_transform`` and
``dataparser_scale`` (what nerfstudio writes to ``dataparser_transforms.json``)."""


def base_pose_map(reference) -> PoseMap:
    """How the owner's base run maps a transforms file's poses to its own coordinates: Blender-format data (the
    translation times ``scale_factor``) or nerfstudio-data (the run's recorded orientation, centering and scale)."""
    dm = reference.pipeline.datamanager
    parser_cfg = getattr(getattr(dm, "config", None), "dataparser", None)
    if not isinstance(parser_cfg, POSE_DATAPARSERS):
        raise GStickerError(
            f"--cameras needs a base trained with the blender-data or nerfstudio-data dataparser; this base used "
            f"{type(parser_cfg).__name__}, whose pose normalization gsticker does not read; decode these images "
            "without --cameras"
        )
    outputs = dm.train_dataparser_outputs
    return PoseMap(outputs.dataparser_transform.detach().float().cpu(), float(outputs.dataparser_scale))


def posed_views(views: Views, frames: Dict[str, Frame], pose_map: PoseMap) -> Tuple[Views, List[Tuple[str, Any]]]:
    """The images that have a camera in ``frames`` (:func:`gsticker_plugin.decoders.image.read_cameras_file`), each
    with a camera of its own size; the others are added to ``skipped``."""

    out = Views(kind=views.kind, source=views.source, skipped=list(views.skipped), details=dict(views.details))
    cams: List[Tuple[str, Any]] = []
    for v in views.views:
        f = match_frame(v.name, frames)
        if f is None:
            out.skipped.append(
                {
                    "name": v.name,
                    "reason": "no camera for it in --cameras (frames are matched by file name without extension)",
                }
            )
            continue
        h, w = v.image.shape[-2:]
        try:
            cam = camera_for_image(frames[f], int(h), int(w), pose_map)
        except GStickerError as e:
            out.skipped.append({"name": v.name, "reason": str(e)})
            continue
        note = f"camera {f}" + (f"; {v.note}" if v.note else "")
        out.views.append(View(name=v.name, image=v.image, note=note))
        cams.append((f"image/{f}/{int(h)}x{int(w)}", cam))
    if not out.views:
        raise GStickerError(
            f"none of the {len(views.views)} images has a camera in --cameras (frames are matched by "
            "file name without extension, e.g. r_0.png <-> ./test/r_0); pass the transforms JSON "
            "of these images"
        )
    out.details["cameras"] = len(cams)
    return out, cams


def decode_images_at_cameras(
    key: OwnerKey, ref, views: Views, frames: Dict[str, Frame], seed: int, progress: bool
) -> Tuple[Views, Decoded]:
    """The informed image decoder on the images of ``views`` that have a camera in ``frames``, against the owner's
    base ``ref`` (:func:`gsticker_plugin.decoders.reference.load_base_reference`): the posed views and the decoded bits."""

    posed, cams = posed_views(views, frames, base_pose_map(ref))
    with contextlib.redirect_stdout(sys.stderr):
        dec = decode_posed_images(
            key, ref, [v.image.permute(1, 2, 0) for v in posed.views], cams, seed, progress=progress
        )
    return posed, dec
