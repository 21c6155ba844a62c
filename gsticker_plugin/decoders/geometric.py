"""Informed geometric decoding: read the owner's message from a suspect model's *geometry*, given the base.

The sticker changes only the density of the frozen base: ``sigma~ = relu(sigma + psi(sigma) * scale * m(x, M))``.
Recoloring (palette, hue, a color-only fine-tune) never touches density, so the suspect's geometry outputs
(accumulation, and for nerfacto the expected depth) still carry ``M`` exactly. When the owner holds the
unwatermarked base run (the owner key references it by path and sha256) and the sticker and gates (stored in the
key since version 2), the message can be read back by fitting:

1. render the owner's base once per view camera, capturing its final samples (positions, deltas, density) and
   its own accumulation / depth outputs (:func:`gsticker_plugin.fastpath.cache_view`);
2. render the suspect (any Nerfstudio run, a black box) at the same camera and take its accumulation / depth;
3. model the suspect as ``base outputs + [G(s) - G(0)]`` where ``G`` composites the base's samples with the
   sticker of a *continuous* message ``s in [-1, 1]^K`` (:meth:`Sticker.mix` accepts any signs), and fit ``s`` to
   the suspect by damped Gauss-Newton (Levenberg-Marquardt, clamped to the box);
4. decode bit ``i`` as ``s_i > 0``; bits the suspect does not determine (``|s_i| <= tol``, e.g. every bit when
   the suspect *is* the base: zero residual) are undetermined and count as mismatches, so the unmarked base
   reads 0/48, never a match.

Why the binomial null holds: the fit uses the suspect, the base and the sticker, never the owner's message; the
sticker was trained on uniformly random messages (``--pipeline.owner-message-prob 0``), so for a model that was
not marked with ``M`` the decoded bits are independent of ``M``, and with ``M`` uniformly random the matches are
``Binomial(K, 1/2)`` whatever the decoded bits are.

Limits: it needs the owner's base run (an *informed* decoder), works on models (not on images), and models only
the final field's density on the base's own samples (bases whose fine samples follow the wrapped coarse density,
TensoRF and vanilla-nerf, are fitted approximately; nerfacto's proposal samplers are not wrapped by default, so
its fit is exact).
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable, Dict, List, Optional, Tuple

import torch
from jaxtyping import Float, Int
from nerfstudio.models.base_model import Model
from torch import Tensor

from gsticker_plugin.decoders.fit import fit_and_decide, per_ray_jacobian, tie_generator
from gsticker_plugin.decoders.reference import (
    ACCUMULATION_KEYS,
    BaseReference,
    ReferenceView,
    any_reference_view,
    cached_reference_view,
    cpu_sticker,
    geometry_signal,
    has_expected_depth,
    reference_view,
)
from gsticker_plugin.decoders.result import decoded
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.sticker import Sticker, render_weights
from gsticker_plugin.views import View, progress_bar, select_cameras

# ================================================================================================================
# pure functions: one view's reference, the prediction, the fit, the decision
# ================================================================================================================


def predict_change(ref: ReferenceView, sticker: Sticker, signs: Float[Tensor, " K"]) -> Float[Tensor, "C R"]:
    """G(s): the geometry signal of the base's samples with the sticker of continuous message ``signs``.

    Same wrap as :class:`gsticker_plugin.sticker.DensityWrap` (``relu(sigma + psi * scale * m)``, zero where
    the gate is closed) and the same quadrature as Nerfstudio's renderer; differentiable in ``signs``.
    """
    return signal_of_sticker(ref, sticker.mix(ref.features, signs))


def marked_density(ref: ReferenceView, m: Float[Tensor, "N 1"]) -> Float[Tensor, "R S 1"]:
    """The base's sample densities wrapped with sticker values ``m`` at the gate-open samples (as ``DensityWrap``)."""
    r, s = ref.density.shape[:2]
    delta = torch.zeros(r * s, 1, dtype=m.dtype, device=m.device).index_add(0, ref.open_index, ref.psi_scale * m)
    return torch.relu(ref.density + delta.reshape(r, s, 1))


def signal_of_sticker(ref: ReferenceView, m: Float[Tensor, "N 1"]) -> Float[Tensor, "C R"]:
    """The geometry signal of the base's samples with sticker values ``m`` at the gate-open samples."""
    w = render_weights(marked_density(ref, m), ref.deltas)
    acc = w.sum(dim=-2)[:, 0]
    if len(ref.signals) == 1:
        return acc[None]
    return torch.stack([acc, (w * ref.steps).sum(dim=-2)[:, 0] / ref.depth_scale])


def change_jacobian(ref: ReferenceView, sticker: Sticker, signs: Float[Tensor, " K"]) -> Optional[Float[Tensor, "M K"]]:
    """d predict_change / d signs, flattened like ``predict_change(...).reshape(-1)`` (None: no closed form)."""
    r, s = ref.density.shape[:2]
    j = per_ray_jacobian(lambda x: signal_of_sticker(ref, x), sticker, ref.features, signs, ref.open_index // s, r)
    return None if j is None else j.reshape(-1, j.shape[-1])


# ================================================================================================================
# the owner's base with the key's sticker
# ================================================================================================================


def relinearized_view(
    ref: BaseReference, name: str, camera, use_depth: bool, bits: Int[Tensor, " K"], sticker: Sticker
) -> ReferenceView:
    """A reference view around a first estimate ``bits`` of the message, for bases whose final samples follow the
    wrapped density (TensoRF's and vanilla-nerf's PDF samplers): the samples are the ones the base marked with
    ``bits`` draws, the density at them is the base's, and the zero point is the prediction of the message 0 on
    those samples, so ``base_signal + G(s) - G(0)`` is the composite of the base's density plus the sticker of
    ``s`` on the marked model's samples. Independent of the owner's message (``bits`` come from the suspect)."""
    view = reference_view(ref, name, camera, use_depth, message=bits)
    with torch.no_grad():
        view.base_signal = predict_change(view, sticker, torch.zeros(sticker.num_bits))
    return view


def suspect_signal(outputs: Dict[str, Tensor], ref: ReferenceView) -> Float[Tensor, "C R"]:
    """The suspect's geometry at the reference view's rays, in the reference's units."""
    signal, _ = geometry_signal(outputs, len(ref.signals) == 2)
    h, w = ref.hw
    if signal.shape[1] != h * w:
        raise GStickerError(
            f"the suspect rendered {signal.shape[1]} pixels for a {h}x{w} camera; geometric decoding "
            "needs renders at the base's cameras"
        )
    out = signal[:, ref.rays].clone()
    if out.shape[0] == 2:
        out[1] /= ref.depth_scale
    return out


SCENE_AGREEMENT_TOLERANCE = 0.25
"""Accumulation difference under which the suspect and the base agree at a ray (:func:`scene_agreement`)."""


def scene_agreement(suspect: Float[Tensor, "C R"], ref: ReferenceView) -> float:
    """Share of the base's surface rays (those the sticker can change) where the suspect's accumulation is within
    :data:`SCENE_AGREEMENT_TOLERANCE` of the base's: near 1 for any model of the base's scene (marked, recoloured or
    retrained), low for another scene. NaN for a view with no such ray."""
    if suspect.shape[1] == 0:
        return float("nan")
    return float(((suspect[0] - ref.base_signal[0]).abs() < SCENE_AGREEMENT_TOLERANCE).float().mean())


def decode_view(
    ref_view: ReferenceView,
    sticker: Sticker,
    suspect: Float[Tensor, "C R"],
    generator: torch.Generator,
    iterations: int = 10,
) -> Dict[str, Any]:
    """Fit the continuous message to one view's suspect geometry and decide the bits."""
    target = (suspect - ref_view.base_signal).float()
    fit, bits, undetermined = fit_and_decide(
        lambda s: predict_change(ref_view, sticker, s),
        lambda s: change_jacobian(ref_view, sticker, s),
        target,
        sticker.num_bits,
        ref_view.rays.numel() > 0,
        generator,
        iterations,
    )
    return {
        "bits": bits,
        "signs": fit.signs,
        "undetermined": undetermined,
        "explained": fit.explained,
        "residual_rms": fit.residual_rms,
        "iterations": fit.iterations,
        "rays": int(ref_view.rays.numel()),
    }


# ================================================================================================================
# a suspect model, all views
# ================================================================================================================


def decode_suspect(
    key,
    reference: BaseReference,
    suspect_model,
    num_views: int,
    sampled_share: float,
    seed: int,
    sticker: Optional[bool] = None,
    progress: bool = False,
    iterations: int = 10,
    ref_cache: Optional[Dict[Any, ReferenceView]] = None,
    cameras: Optional[List[Tuple[str, Any]]] = None,
    relinearize: int = 1,
    full_renders: bool = True,
):
    """Render the base and the suspect at ``num_views`` cameras of the base run (or the given ``(name, camera)``
    list), fit and decode every view.

    Returns ``(dec, views)``: ``dec`` holds per view ``bits``, ``matches``, ``bit_acc``, ``pvalues`` (as
    :func:`gsticker_plugin.decoders.blind.decode_views`; ``scores`` is None: the classifier reads images, not geometry)
    and ``geometry`` (per-view fit details); ``views`` are :class:`gsticker_plugin.views.View` with the suspect's
    RGB renders (for the report's figure). ``ref_cache``: a dict kept by the caller to reuse the base's reference
    views across suspects decoded with the same reference, cameras and seed. ``relinearize``: for bases whose
    samples follow the wrapped density, refit this many times around the previous fit's bits
    (:func:`relinearized_view`; a reference render and a fit more per view). ``full_renders=False``: render the
    suspect only at the rays the fit reads (:func:`suspect_renders`; the same numbers, a quarter of the rays on
    lego100) and return no views (there is no whole suspect image to show).
    """
    st = cpu_sticker(reference.model)
    gen = tie_generator(seed)
    bits, details, views = [], [], []
    ref_cache = {} if ref_cache is None else ref_cache  # one base render per camera
    rays_for = None if full_renders else (lambda name, cam: any_reference_view(reference, name, cam, ref_cache).rays)
    for name, cam, out in suspect_renders(
        reference,
        suspect_model,
        num_views,
        sampled_share,
        seed,
        sticker,
        progress,
        "geometric decoding",
        cameras,
        rays_for=rays_for,
    ):
        use_depth = has_expected_depth(out)
        ref_view = cached_reference_view(reference, name, cam, use_depth, ref_cache)
        signal = suspect_signal(out, ref_view)
        d = decode_view(ref_view, st, signal, gen, iterations)
        agreement = scene_agreement(signal, ref_view)
        rounds = relinearize if reference.samples_follow_sticker else 0
        for _ in range(rounds):
            first = d["bits"]
            rv = relinearized_view(reference, name, cam, use_depth, first, st)
            if not full_renders:  # the marked samples may open the gate on rays the first view did not keep
                out = complete_rays(suspect_model, cam, out, rv.rays)
            d = decode_view(rv, st, suspect_signal(out, rv), gen, iterations)
            d["bits_changed_by_relinearizing"] = int((d["bits"] != first).sum())
        d["relinearized"] = rounds
        d["scene_agreement"] = agreement
        bits.append(d.pop("bits"))
        d["signs_abs_mean"] = float(d.pop("signs").abs().mean())
        d["signals"] = list(ref_view.signals)
        details.append(d)
        if full_renders:
            rgb = out.get("rgb", out.get("rgb_fine"))
            img = rgb.clamp(0, 1).permute(2, 0, 1).contiguous() if rgb is not None else ref_view.image
            views.append(View(name=name, image=img))
    return decoded(key, bits, "geometry", details), views


def suspect_renders(
    reference: BaseReference,
    suspect_model,
    num_views: int,
    sampled_share: float,
    seed: int,
    sticker: Optional[bool],
    progress: bool,
    desc: str,
    cameras: Optional[List[Tuple[str, Any]]] = None,
    rays_for: Optional[Callable[[str, Any], Int[Tensor, " R"]]] = None,
):
    """Yield ``(name, camera, outputs)`` of the suspect at the base run's chosen cameras, or at ``cameras``
    (outputs float [H W C], on the CPU); ``sticker``: render with the suspect's sticker on/off (None: as it is).

    ``rays_for(name, camera)``: render only these flat pixel indices (the rays a decoder reads) through the
    model's public ``get_outputs_for_camera_ray_bundle``; the other pixels of the outputs are NaN. Nerfstudio's
    ray-based models render every ray on its own, so the rendered pixels equal a whole render's (tested); a model
    that overrides ``get_outputs_for_camera`` is rendered whole.
    """
    cams = cameras if cameras is not None else select_cameras(reference.pipeline, num_views, sampled_share, seed)
    ctx = (
        suspect_model.sticker_enabled(sticker)
        if (sticker is not None and hasattr(suspect_model, "sticker_enabled"))
        else contextlib.nullcontext()
    )
    per_ray = rays_for is not None and renders_rays_alone(suspect_model)
    with ctx:
        for name, cam in progress_bar(cams, desc, progress):
            rays = rays_for(name, cam) if per_ray else None
            with torch.no_grad():
                if rays is None or rays.numel() == 0:
                    out = suspect_model.get_outputs_for_camera(cam.to(suspect_model.device))
                else:
                    out = render_rays(suspect_model, cam, rays)
            yield name, cam, {k: v.detach().float().cpu() for k, v in out.items() if isinstance(v, Tensor)}


def complete_rays(model, camera, outputs: Dict[str, Tensor], rays: Int[Tensor, " R"]) -> Dict[str, Tensor]:
    """``outputs`` of :func:`render_rays` with the pixels of ``rays`` that were not rendered yet rendered too."""
    acc_key = next((k for k in ACCUMULATION_KEYS if isinstance(outputs.get(k), Tensor)), None)
    if acc_key is None or rays.numel() == 0:
        return outputs
    missing = rays[torch.isnan(outputs[acc_key].reshape(-1)[rays])]
    return render_rays(model, camera, missing, into=outputs) if missing.numel() else outputs


def renders_rays_alone(model) -> bool:
    """Whether ``model`` renders a camera through the stock ``Model.get_outputs_for_camera`` (every ray alone)."""
    return type(model).get_outputs_for_camera is Model.get_outputs_for_camera


RAY_CHUNK = 4096
"""Rays per pass of a model rendered for a decoder: on a CPU a pass of a few thousand rays costs least per ray (a
100 x 100 nerfacto-small render 1.1 s in chunks of 4096, 1.5 s in one pass of 32768; 200 x 200 4.4 s and 9 s)."""


def outputs_in_chunks(model, bundle) -> Dict[str, Tensor]:
    """``model.get_outputs_for_camera_ray_bundle`` of a ``[N 1]`` ray ``bundle``, :data:`RAY_CHUNK` rays a call:
    ``{key: [N 1 C]}`` (every ray renders alone, so chunks change nothing but speed)."""
    n = bundle.shape[0]
    parts = [model.get_outputs_for_camera_ray_bundle(bundle[i : i + RAY_CHUNK]) for i in range(0, n, RAY_CHUNK)]
    keys = [k for k, v in parts[0].items() if isinstance(v, Tensor)]
    return {k: torch.cat([p[k] for p in parts], dim=0) for k in keys}


@torch.no_grad()
def render_rays(model, camera, rays: Int[Tensor, " R"], into: Optional[Dict[str, Tensor]] = None) -> Dict[str, Tensor]:
    """The model's outputs at the flat pixel indices ``rays`` of a one-camera ``camera``, scattered into whole
    [H W C] images whose other pixels are NaN, or into copies of ``into``'s images (on their device and dtype)."""
    bundle = camera.to(model.device).generate_rays(camera_indices=0, keep_shape=True)
    h, w = bundle.origins.shape[:2]
    index = rays.to(model.device)
    sub = outputs_in_chunks(model, bundle.flatten()[index].reshape((-1, 1)))
    out: Dict[str, Tensor] = dict(into) if into is not None else {}
    for k, v in sub.items():
        if not isinstance(v, Tensor) or v.shape[0] != index.numel() or (into is not None and k not in into):
            continue
        flat = v.reshape(index.numel(), -1)
        if into is not None:
            full = into[k].clone().reshape(h * w, -1)
            flat = flat.to(full)
        else:
            full = torch.full((h * w, flat.shape[1]), float("nan"), dtype=flat.dtype, device=flat.device)
        full[index.to(full.device)] = flat
        out[k] = full.reshape(h, w, -1)
    return out
