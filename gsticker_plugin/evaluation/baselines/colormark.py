"""A color-branch baseline ("CopyRNeRF-style"): the owner's message in the *color* of the base, not its density.

The evaluation suite needs a watermark that lives where recoloring acts, to show on one chart that it falls to
chance after a recolor while the density sticker survives. :class:`ColorMarkModel` is a GeometrySticker model
with exactly the same modules and state dict (a watermarked run's checkpoint loads strictly), but:

* density is the base's, bit for bit (the density wraps are removed from the base fields);
* every sample of the final (rendering) field gets ``rgb + a * psi(sigma) * m(normalize(x), M)`` added to its
  per-sample RGB, the same value on the three channels, where ``psi`` is the final field's gate at the sample's
  base density, ``m`` the sticker (same patterns as the density sticker) and ``a`` the config's
  ``color_amplitude``; only where ``psi`` exceeds ``gate_threshold``, like :class:`DensityWrap`.

It is built from a trained geometrysticker run, not trained (:func:`write_color_marked_run`);
:func:`match_amplitude` picks ``a`` for a target PSNR against the unmarked render, and
:func:`decode_color_suspect` is the informed color decoder, the analogue of
:func:`gsticker_plugin.decoders.geometric.decode_suspect`: it fits the continuous message to the suspect's RGB change
``sum_j w_j * a * psi_j * m_j(s)`` (base weights ``w``: density is unchanged) at the base's rays.

Order with recoloring: the mark wraps the final field instance's ``get_outputs`` when the model is built, so a
:class:`gsticker_plugin.recolor.model.RecolorModel` built on a color-marked run (ns-recolor palette / hue) wraps
the already-marked method and edits the marked RGB.

Bases: nerfacto (tested end to end on real runs); TensoRF and vanilla-nerf get the same wrap (the mark and the
unchanged density are tested on untrained in-memory models; the decoder is not exercised on them).

Honest limits: the mark is a gray offset. A pure HSV hue rotation maps ``rgb + d`` to ``hue(rgb) + d`` wherever
``rgb + d`` stays in [0, 1] (max and min, hence V and the chroma, move together with ``d``), so a hue-shifted
color-marked model still *carries* the offset; what the recolor breaks is the decoder's reference (the
suspect's RGB is no longer the base's plus the mark), and how far it falls depends on the size of the edit
relative to the mark (a strong mark on a faintly colored base survives a hue turn). A decoder that knew the
edit (a hue-shifted reference) could undo it.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Type

import torch
import yaml
from jaxtyping import Float, Int
from nerfstudio.field_components.field_heads import FieldHeadNames
from torch import Tensor

from gsticker_plugin import metrics
from gsticker_plugin.decoders.fit import fit_and_decide, fit_summary, per_ray_jacobian, tie_generator
from gsticker_plugin.decoders.geometric import suspect_renders
from gsticker_plugin.decoders.reference import any_reference_view, cpu_sticker
from gsticker_plugin.decoders.result import decoded
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.model import GeometryStickerModel, GeometryStickerModelConfig
from gsticker_plugin.recolor import runs
from gsticker_plugin.recolor.model import color_fields, iter_models
from gsticker_plugin.runs import final_rgb
from gsticker_plugin.sticker import DensityWrap, Sticker, WrapState, render_weights
from gsticker_plugin.views import View, select_cameras

# ================================================================================================================
# the model
# ================================================================================================================


@dataclass
class ColorMarkModelConfig(GeometryStickerModelConfig):
    """A geometrysticker run's sticker and gates, with the mark added to the final field's color, not its density."""

    _target: Type = field(default_factory=lambda: ColorMarkModel)
    color_amplitude: float = 0.05
    """Largest per-sample RGB change of the color mark (at psi = 1 and |m| = 1), the same on the 3 channels."""


class ColorMarkWrap:
    """Installs the color mark on a field instance: ``get_density`` is only watched (density and samples of the
    call are remembered, the result is returned untouched) and ``get_outputs`` adds ``a * psi * m`` to the
    per-sample RGB. Removable; the density wrap supplies the gate, the sticker and the position normalization."""

    def __init__(self, wrap: DensityWrap, state: WrapState, amplitude: Callable[[], float]) -> None:
        self.wrap = wrap
        self.field = wrap.field
        self.state = state
        self.amplitude = amplitude
        self.previous = {name: self.field.__dict__.get(name) for name in ("get_density", "get_outputs")}
        self.original_density = self.field.get_density
        self.original_outputs = self.field.get_outputs
        self.pending: Optional[Tuple[Any, Tensor]] = None  # (ray_samples, density) of the last get_density call
        object.__setattr__(self.field, "get_density", self.get_density)
        object.__setattr__(self.field, "get_outputs", self.get_outputs)

    def remove(self) -> None:
        for name, mine in (("get_density", self.get_density), ("get_outputs", self.get_outputs)):
            if self.field.__dict__.get(name) == mine:
                if self.previous[name] is not None:
                    object.__setattr__(self.field, name, self.previous[name])
                else:
                    del self.field.__dict__[name]

    @property
    def active(self) -> bool:
        has_sticker = self.state.message is not None or self.state.folded is not None  # folded: a shared run
        return self.state.enabled and has_sticker and bool(self.wrap.gate.calibrated)

    def get_density(self, ray_samples, *args, **kwargs):
        result = self.original_density(ray_samples, *args, **kwargs)
        density = result[0] if isinstance(result, tuple) else result
        self.pending = (ray_samples, density.detach())
        return result

    def color_delta(self, density: Float[Tensor, "*bs 1"], positions: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 1"]:
        """``a * psi * m`` per sample (zero where the gate is closed): the density wrap's delta over its scale."""
        delta, _ = self.wrap.delta(density, positions, self.state.message)
        return delta * (float(self.amplitude()) / self.wrap.gate.scale)

    def get_outputs(self, ray_samples, *args, **kwargs):
        out = self.original_outputs(ray_samples, *args, **kwargs)
        pending, self.pending = self.pending, None
        if not self.active:
            return out

        rgb = out.get(FieldHeadNames.RGB) if isinstance(out, dict) else out
        if not isinstance(rgb, Tensor) or rgb.shape[-1] != 3:
            return out
        if pending is not None and pending[0] is ray_samples:
            density = pending[1]
        else:  # get_outputs without its own get_density call: evaluate the (unchanged) density here
            result = self.original_density(ray_samples)
            density = (result[0] if isinstance(result, tuple) else result).detach()
        positions = ray_samples.frustums.get_positions().reshape(*density.shape[:-1], 3)
        marked = rgb + self.color_delta(density, positions).reshape(*rgb.shape[:-1], 1).to(rgb)
        if isinstance(out, dict):
            out = dict(out)
            out[FieldHeadNames.RGB] = marked
            return out
        return marked  # TensoRF's get_outputs returns the rgb tensor


class ColorMarkModel(GeometryStickerModel):
    """Same modules and state as :class:`GeometryStickerModel`; the mark is added to color, density is the base's.

    ``sticker_enabled(False)`` (and the viewer's "Sticker on" box) turns the color mark off.
    """

    config: ColorMarkModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()
        for w in self.wraps:
            w.remove()  # density bit-identical to the base's: the density wraps stay as gate/sticker holders only

        final = self.final_wrap.field
        if not any(f is final for _, f in color_fields(self.base)):
            raise GStickerError(
                f"{type(self.base).__name__}'s final field {self.final_wrap.name} has no per-sample "
                "RGB output for the color mark; build the color-branch baseline on a nerfacto "
                "(or vanilla-nerf / tensorf) geometrysticker run"
            )
        self.color_wrap = ColorMarkWrap(self.final_wrap, self.wrap_state, lambda: self.config.color_amplitude)


# ================================================================================================================
# writing a color-marked run from a geometrysticker run
# ================================================================================================================


def color_mark_config(model_config: GeometryStickerModelConfig, amplitude: float) -> ColorMarkModelConfig:
    """The same field values as ``model_config`` (a geometrysticker model config), as a color-mark config."""
    if not isinstance(model_config, GeometryStickerModelConfig):
        raise GStickerError(
            f"the run's model is {type(model_config).__name__}, not a geometrysticker model; build the "
            "color-branch baseline from a watermarked run (ns-train geometrysticker ...)"
        )
    check_amplitude(amplitude)
    values = {
        f.name: copy.deepcopy(getattr(model_config, f.name))
        for f in dataclasses.fields(model_config)
        if f.init and f.name not in ("_target", "color_amplitude")
    }
    return ColorMarkModelConfig(**values, color_amplitude=float(amplitude))


def check_amplitude(amplitude: float) -> float:
    a = float(amplitude)
    if not math.isfinite(a) or a <= 0.0:
        raise GStickerError(f"color amplitude {amplitude} must be a positive number (e.g. 0.05, or match_amplitude's)")
    return a


def write_color_marked_run(
    watermarked_config: Path, output_dir: Path, amplitude: float, overwrite: bool = False
) -> Path:
    """Write ``output_dir/config.yml`` (the watermarked run's config with a :class:`ColorMarkModelConfig` of the same
    field values plus ``color_amplitude``) and a copy of its latest checkpoint in ``output_dir/nerfstudio_models``.

    Opens with :func:`gsticker_plugin.runs.load_run` and ``ns-recolor ... --load-config`` (both find the
    checkpoint beside config.yml). Stock ``ns-viewer`` / ``ns-render`` look for it under
    ``output_dir/experiment/method/timestamp`` instead, which this layout does not have. Returns the config path.
    """

    run_cfg, run_dir, ckpt = runs.check_input_config(Path(watermarked_config))
    out = runs.check_output_dir(output_dir, run_dir, overwrite)
    config = copy.deepcopy(run_cfg)
    config.pipeline.model = color_mark_config(run_cfg.pipeline.model, amplitude)
    config.output_dir = out
    config.experiment_name = config.experiment_name or "colormark"
    config.timestamp = "colormark"
    config.load_dir = config.load_checkpoint = config.load_step = config.load_config = None
    staged = runs.StagedDir(out)
    try:
        (staged.tmp / config.relative_model_dir).mkdir(parents=True)
        shutil.copy2(ckpt, staged.tmp / config.relative_model_dir / ckpt.name)
        if (run_dir / "dataparser_transforms.json").is_file():
            shutil.copy2(run_dir / "dataparser_transforms.json", staged.tmp / "dataparser_transforms.json")
        (staged.tmp / "config.yml").write_text(yaml.dump(config), "utf8")
        staged.commit()
    except BaseException:
        staged.abort()
        raise
    return out / "config.yml"


# ================================================================================================================
# amplitude for a target PSNR
# ================================================================================================================


def color_mark_model(model) -> ColorMarkModel:
    """The ColorMarkModel in ``model`` (itself or the one a recolor run wraps); one-line error otherwise."""
    found = next((m for m in iter_models(model) if isinstance(m, ColorMarkModel)), None)
    if found is None:
        raise GStickerError(
            f"{type(model).__name__} carries no color mark; load a run written by "
            "gsticker_plugin.evaluation.baselines.colormark.write_color_marked_run"
        )
    return found


@torch.no_grad()
def mark_psnr(model, cameras: Sequence[Tuple[str, Any]]) -> Float[Tensor, " V"]:
    """Per-view PSNR of the color-marked render against the same model with the mark off (renders clamped)."""

    def render(cam) -> Tensor:
        rgb = model.get_outputs_for_camera(cam.to(model.device))["rgb"]
        return rgb.detach().float().clamp(0, 1).cpu().permute(2, 0, 1)[None]

    values = []
    for _, cam in cameras:
        with model.sticker_enabled(True):
            on = render(cam)
        with model.sticker_enabled(False):
            off = render(cam)
        values.append(metrics.psnr(on, off)[0])
    return torch.stack(values)


MATCH_MEASUREMENTS = 6
"""Most PSNR measurements :func:`match_amplitude` makes."""


def match_amplitude(
    pipeline,
    target_psnr: float,
    num_views: int = 4,
    sampled_share: float = 0.0,
    seed: int = 0,
    trial_amplitude: Optional[float] = None,
) -> float:
    """The color amplitude whose mark has mean PSNR ``target_psnr`` against the unmarked render.

    The RGB change is linear in the amplitude up to the final [0, 1] clamp, so every view's PSNR moves by
    ``-20 log10(a / a0)``: ``a = a0 * 10 ** ((psnr(a0) - target) / 20)`` from a measurement at ``trial_amplitude``
    (default: the model's own), then again from a measurement at that ``a`` until the PSNR is within 0.05 dB of the
    target, at most :data:`MATCH_MEASUREMENTS` measurements (the clamp bends the line for strong marks). Views where
    the gate never opens (infinite PSNR) are ignored.
    """

    model = color_mark_model(pipeline.model)
    cams = select_cameras(pipeline, num_views, sampled_share, seed)
    a = check_amplitude(model.config.color_amplitude if trial_amplitude is None else trial_amplitude)
    old = model.config.color_amplitude
    try:
        for _ in range(MATCH_MEASUREMENTS):
            model.config.color_amplitude = a
            psnr = mark_psnr(model, cams)
            finite = psnr[torch.isfinite(psnr)]
            if finite.numel() == 0:
                raise GStickerError(
                    "the color mark changes no pixel in the chosen views (the gate never opens); pass "
                    "more --num-views or check that the run's gates are calibrated"
                )
            off = float(finite.mean()) - float(target_psnr)
            if abs(off) <= 0.05:
                break
            a = a * 10.0 ** (off / 20.0)
    finally:
        model.config.color_amplitude = old
    return a


# ================================================================================================================
# the informed color decoder
# ================================================================================================================


@dataclass
class ColorReferenceView:
    """One reference view in the color decoder's terms: what the suspect's RGB change at the rays depends on."""

    view: Any  # gsticker_plugin.decoders.reference.ReferenceView
    psi: Float[Tensor, "N 1"]  # the gate at the open samples (psi_scale without the gate's density scale)
    weights: Float[Tensor, "R S 1"]  # the base's render weights (the color mark leaves density unchanged)
    base_rgb: Float[Tensor, "R 3"]  # the base render at the rays


def color_reference(ref_view, gate_scale: float) -> ColorReferenceView:
    h, w = ref_view.hw
    base = ref_view.image.permute(1, 2, 0).reshape(h * w, 3)[ref_view.rays].float()
    return ColorReferenceView(
        view=ref_view,
        psi=ref_view.psi_scale / float(gate_scale),
        weights=render_weights(ref_view.density, ref_view.deltas),
        base_rgb=base,
    )


def predict_color_change(
    ref: ColorReferenceView, sticker: Sticker, signs: Float[Tensor, " K"], amplitude: float
) -> Float[Tensor, "R 3"]:
    """The suspect's RGB change at the rays for continuous message ``signs``: ``clamp(base + sum_j w_j a psi_j
    m_j(s)) - base`` (the renderer clamps the composite to [0, 1]); differentiable in ``signs``."""
    return color_of_sticker(ref, sticker.mix(ref.view.features, signs), amplitude)


def color_of_sticker(ref: ColorReferenceView, m: Float[Tensor, "N 1"], amplitude: float) -> Float[Tensor, "R 3"]:
    """The RGB change at the rays for sticker values ``m`` at the gate-open samples."""
    v = ref.view
    r, s = v.density.shape[:2]
    per_sample = torch.zeros(r * s, 1, dtype=m.dtype, device=m.device).index_add(
        0, v.open_index, amplitude * ref.psi * m
    )
    change = (ref.weights * per_sample.reshape(r, s, 1)).sum(dim=-2)  # [R 1], the same on the 3 channels
    return (ref.base_rgb + change).clamp(0.0, 1.0) - ref.base_rgb


def color_change_jacobian(
    ref: ColorReferenceView, sticker: Sticker, signs: Float[Tensor, " K"], amplitude: float
) -> Optional[Float[Tensor, "M K"]]:
    """d predict_color_change / d signs, flattened like ``predict_color_change(...).reshape(-1)`` (None: no closed
    form)."""

    v = ref.view
    r, s = v.density.shape[:2]
    j = per_ray_jacobian(
        lambda x: color_of_sticker(ref, x, amplitude).T, sticker, v.features, signs, v.open_index // s, r
    )
    return None if j is None else j.permute(1, 0, 2).reshape(-1, j.shape[-1])  # [3 R K] -> rows r * 3 + c


def decode_color_view(
    ref: ColorReferenceView,
    sticker: Sticker,
    suspect_rgb: Float[Tensor, "R 3"],
    amplitude: float,
    generator: torch.Generator,
    iterations: int = 10,
) -> Dict[str, Any]:
    """Fit the continuous message to one view's RGB change (suspect minus base) and decide the bits."""
    target = (suspect_rgb.float() - ref.base_rgb).reshape(-1)
    fit, bits, undetermined = fit_and_decide(
        lambda x: predict_color_change(ref, sticker, x, amplitude),
        lambda x: color_change_jacobian(ref, sticker, x, amplitude),
        target,
        sticker.num_bits,
        ref.view.rays.numel() > 0,
        generator,
        iterations,
    )
    return {"bits": bits, **fit_summary(fit, undetermined, int(ref.view.rays.numel())), "signals": ["rgb"]}


def suspect_rgb_at(outputs: Dict[str, Tensor], rays: Int[Tensor, " R"], hw: Tuple[int, int]) -> Float[Tensor, "R 3"]:
    rgb = final_rgb(outputs)
    flat = rgb.float().reshape(-1, 3)
    if flat.shape[0] != hw[0] * hw[1]:
        raise GStickerError(
            f"the suspect rendered {flat.shape[0]} pixels for a {hw[0]}x{hw[1]} camera; the color "
            "decoder needs renders at the base's cameras"
        )
    return flat[rays]


def decode_color_suspect(
    key,
    reference,
    suspect_model,
    num_views: int,
    sampled_share: float,
    seed: int,
    amplitude: float,
    sticker: Optional[bool] = None,
    progress: bool = False,
    iterations: int = 10,
    ref_cache: Optional[Dict[Any, Any]] = None,
    full_renders: bool = True,
):
    """The informed color decoder: :func:`gsticker_plugin.decoders.geometric.decode_suspect` with the suspect's RGB instead of
    its geometry, and the color mark of ``amplitude`` as the model of the change.

    ``reference``: the owner's base with the key's sticker and gates
    (:func:`gsticker_plugin.decoders.reference.load_base_reference`). ``sticker``: render the suspect with its mark on/off
    (None: as it is). ``ref_cache``: a dict the caller keeps to reuse reference views (same keys as
    ``decode_suspect``'s). Returns ``(dec, views)``: ``dec`` holds per view ``bits``, ``matches``, ``bit_acc``,
    ``pvalues``, ``scores`` (None) and ``color`` (per-view fit details); ``views`` the suspect's RGB renders
    (none with ``full_renders=False``: the suspect is rendered only at the rays the fit reads).
    """

    check_amplitude(amplitude)
    st = cpu_sticker(reference.model)
    gate_scale = float(reference.model.final_wrap.gate.scale)
    gen = tie_generator(seed)
    per_view: List[Dict[str, Any]] = []
    bits, views = [], []
    ref_cache = {} if ref_cache is None else ref_cache  # one base render per camera
    rays_for = None if full_renders else (lambda name, cam: any_reference_view(reference, name, cam, ref_cache).rays)
    for name, cam, rendered in suspect_renders(
        reference, suspect_model, num_views, sampled_share, seed, sticker, progress, "color decoding", rays_for=rays_for
    ):
        # any reference view of this camera will do (the color fit uses no depth)
        ref_view = any_reference_view(reference, name, cam, ref_cache)
        ref = color_reference(ref_view, gate_scale)
        d = decode_color_view(
            ref, st, suspect_rgb_at(rendered, ref_view.rays, ref_view.hw), float(amplitude), gen, iterations
        )
        bits.append(d.pop("bits"))
        per_view.append(d)
        if full_renders:
            img = final_rgb(rendered)
            views.append(View(name=name, image=img.clamp(0, 1).permute(2, 0, 1).contiguous()))
    return decoded(key, bits, "color", per_view), views
