"""Informed decoding of the field mark: read the owner's message from a suspect model's geometry, given the base.

The shared run's density field differs from the base's by the signed per-bit patterns in its hash table
(:mod:`gsticker_plugin.shared`). Per view camera: render the owner's base once, keeping its final samples and their
per-bit features (:func:`gsticker_plugin.fieldmark.field_view`); render the suspect (any Nerfstudio run, a black
box) at the same camera; fit the continuous message ``s in [-1, 1]^K`` whose density change
``sigma * exp(a * features @ s)`` best explains the suspect's accumulation and depth against the base's
(:func:`gsticker_plugin.decoders.fit.fit_and_decide`); bit ``i`` is ``s_i > 0``, undetermined bits (the suspect *is*
the base: nothing to explain) count as mismatches.

A TensoRF base (the mark in its density planes) is read at its samples instead: TensoRF places its fine samples by
the density it renders, so a suspect's renders move them, while density is a function of position that any field
answers (``get_density``). The suspect's density at the base's fine samples is fitted to ``relu(pre + a f @ s)``,
exact in the planes (:func:`decode_density`).

The fit reads the suspect, the base and the patterns, never the message: for a model not marked with the message the
decoded bits are independent of it, and with the message uniformly random and secret the matches are
``Binomial(K, 1/2)``.
"""

from __future__ import annotations

import contextlib
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch
from torch import Tensor

from gsticker_plugin import fieldmark as FM
from gsticker_plugin import runs
from gsticker_plugin.decoders.fit import fit_and_decide, tie_generator
from gsticker_plugin.decoders.geometric import SCENE_AGREEMENT_TOLERANCE, suspect_renders
from gsticker_plugin.decoders.reference import base_checkpoint, base_config_path, data_if_missing
from gsticker_plugin.decoders.result import decoded
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.views import View

SURFACE_ACCUMULATION = 0.5
"""Rays where the base's accumulation is above this are its surface (where :func:`scene_agreement` compares)."""


@dataclass
class FieldReference:
    """The owner's base run rebuilt from the key's reference, with the key's per-bit patterns."""

    config_path: Path
    checkpoint: Path
    method: str
    pipeline: Any  # the base run's pipeline (cameras)
    model: Any  # the base model (stock)
    patterns: Tensor  # [K N F]
    amplitude: float
    notes: List[str] = field(default_factory=list)


def load_field_reference(
    key, key_path: Path, base_config: Optional[Path], data: Optional[Path], device: torch.device
) -> FieldReference:
    """Rebuild the owner's base (strictly, its checkpoint's sha256 checked against the key) and the key's patterns."""
    mark = key.field_mark
    if not mark:
        raise GStickerError(f"{key_path} is a sticker key, not a field-mark key")
    cfg_path = base_config_path(key, key_path, base_config)
    ckpt = base_checkpoint(key, cfg_path, only_beside=base_config is not None)
    with contextlib.redirect_stdout(sys.stderr):
        config, pipeline, _ = runs.load_run_at(cfg_path, ckpt, data=data_if_missing(cfg_path, data), device=device)
    model = pipeline.model
    names = {"_model." + n: p for n, p in model.named_parameters()}
    host = FM.host_of(model.field)
    if host != mark.get("host", "hash") or names.get(mark["table"]) is not FM.marked_parameter(model.field):
        raise GStickerError(
            f"the key marks {mark['table']}, which is not the density {host} of {cfg_path}; pass --base-config "
            "with the base run the mark was made on"
        )
    pats = FM.key_patterns(model.field, mark, key.num_bits)
    model.eval()
    return FieldReference(
        config_path=cfg_path,
        checkpoint=ckpt,
        method=config.method_name,
        pipeline=pipeline,
        model=model,
        patterns=pats,
        amplitude=float(mark["amplitude"]),
    )


def decode_view(view: FM.FieldView, suspect_outputs: Dict[str, Tensor], amplitude: float, generator: torch.Generator):
    """Fit the signs to a suspect's geometry at the view's rays (against the base's own) and decide the bits; returns
    (bits, fit)."""
    h_w = view.hw[0] * view.hw[1]
    if h_w and suspect_outputs["accumulation"].numel() != h_w:
        raise GStickerError(
            f"the suspect rendered {suspect_outputs['accumulation'].numel()} pixels for a {view.hw[0]}x{view.hw[1]} "
            "camera; the field-mark decoder needs renders at the base's cameras"
        )
    sig = FM.geometry_of(suspect_outputs)[:, view.rays]
    target = torch.cat([sig[0] - view.base_signal[0], (sig[1] - view.base_signal[1]) / view.depth_scale])
    k = view.features.shape[-1]
    fit, bits, _ = fit_and_decide(
        lambda s: FM.predict(view, s, amplitude),
        lambda s: FM.predict_jacobian(view, s, amplitude),
        target,
        k,
        view.rays.numel() > 0,
        generator,
    )
    return bits, fit


def decode_density(view: FM.DensityView, suspect_model, amplitude: float, generator: torch.Generator):
    """Fit the signs to a suspect's density at a TensoRF view's samples (:func:`gsticker_plugin.fieldmark.
    probe_density`) against the base's own and decide the bits; returns (bits, fit)."""
    target = FM.probe_density(suspect_model, view.world) - torch.relu(view.pre)
    fit, bits, _ = fit_and_decide(
        lambda s: FM.density_at(view, s, amplitude),
        lambda s: FM.density_jacobian(view, s, amplitude),
        target,
        view.features.shape[-1],
        view.pre.numel() > 0,
        generator,
    )
    return bits, fit


def base_accumulation(view) -> Tuple[Tensor, Tensor]:
    """(pixels, the base's accumulation there) of a view: the rays it holds, or every pixel of a density view."""
    if isinstance(view, FM.DensityView):
        return torch.arange(view.accumulation.numel()), view.accumulation
    return view.rays, view.base_signal[0]


def scene_agreement(view, suspect_outputs: Dict[str, Tensor]) -> Optional[float]:
    """Share of the base's surface pixels (accumulation above :data:`SURFACE_ACCUMULATION`) where the suspect's
    accumulation is within :data:`SCENE_AGREEMENT_TOLERANCE` of the base's; None for a view without surface."""
    pixels, base = base_accumulation(view)
    surface = base > SURFACE_ACCUMULATION
    if not bool(surface.any()):
        return None
    acc = FM.geometry_of(suspect_outputs)[0, pixels]
    return float(((acc - base)[surface].abs() < SCENE_AGREEMENT_TOLERANCE).float().mean())


def decode_suspect(
    key,
    reference: FieldReference,
    suspect_model,
    num_views: int,
    sampled_share: float,
    seed: int,
    progress: bool = False,
    cameras: Optional[List] = None,
    full_renders: bool = True,
    cache: Optional[Dict[str, Any]] = None,
):
    """Render the base and the suspect at ``num_views`` cameras of the base run (or the given ``(name, camera)``
    list), fit and decode every view. Returns ``(dec, views)`` as :func:`gsticker_plugin.decoders.geometric.
    decode_suspect` (``geometry`` holds the per-view fit details; ``views`` the suspect's renders, none without
    ``full_renders``). ``cache``: a dict kept by the caller to reuse the base's views (by camera name) across
    suspects read with the same reference."""
    cache = {} if cache is None else cache
    gen = tie_generator(seed)
    bits, details, views = [], [], []
    renders = suspect_renders(
        reference, suspect_model, num_views, sampled_share, seed, None, progress, "field-mark decoding", cameras
    )
    for name, cam, out in renders:
        if name not in cache:
            cache[name] = FM.view_of(reference.model, cam.to(reference.model.device), reference.patterns)
        fv = cache[name]
        density = isinstance(fv, FM.DensityView)
        if density:
            b, fit = decode_density(fv, suspect_model, reference.amplitude, gen)
        else:
            b, fit = decode_view(fv, out, reference.amplitude, gen)
        bits.append(b)
        details.append(
            {
                "undetermined": int((b < 0).sum()),
                "explained": fit.explained,
                "residual_rms": fit.residual_rms,
                "iterations": fit.iterations,
                "rays": int((fv.accumulation > 0).sum() if density else fv.rays.numel()),
                "signs_abs_mean": float(fit.signs.abs().mean()),
                "scene_agreement": scene_agreement(fv, out),
                "signals": ["density"] if density else list(fv.signals),
                **({"samples": int(fv.pre.numel())} if density else {}),
            }
        )
        if full_renders:
            views.append(View(name=name, image=runs.final_rgb(out).clamp(0, 1).permute(2, 0, 1).contiguous()))
    return decoded(key, bits, "geometry", details), views
