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
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import torch
from jaxtyping import Float, Int
from torch import Tensor

from gsticker_plugin.errors import GStickerError
from gsticker_plugin.sticker import Sticker, render_weights

GEOMETRY_REFERENCE_VERSION = 1
ACCUMULATION_KEYS = ("accumulation", "accumulation_fine")
EXPECTED_DEPTH_KEYS = ("expected_depth",)


# ================================================================================================================
# the key's geometry reference
# ================================================================================================================


def geometry_reference(model) -> Dict[str, Any]:
    """What the geometric decoder needs from a GeometrySticker model, for the owner key (small: the sticker)."""
    cfg = model.config
    return {
        "version": GEOMETRY_REFERENCE_VERSION,
        "sticker_config": {"kind": cfg.sticker_kind, "num_bits": int(cfg.num_bits),
                           "num_frequencies": int(cfg.num_frequencies), "hidden_dim": int(cfg.sticker_hidden_dim),
                           "num_layers": int(cfg.sticker_num_layers)},
        "gate_threshold": float(cfg.gate_threshold),
        "wrap_proposal_networks": bool(cfg.wrap_proposal_networks),
        "mark_sampling_passes": bool(cfg.mark_sampling_passes),
        "sticker_state": {k: v.detach().cpu().clone() for k, v in model.sticker.state_dict().items()},
        "gates_state": {k: v.detach().cpu().clone() for k, v in model.gates.state_dict().items()},
        "fields": [w.name for w in model.wraps],
        "final_field": model.final_wrap.name,
        "aabb": {w.name: w.aabb.detach().cpu().float().clone() for w in model.wraps},
        "null": None,
    }


# ================================================================================================================
# pure functions: one view's reference, the prediction, the fit, the decision
# ================================================================================================================


@dataclass
class ReferenceView:
    """One camera of the owner's base: the rays the sticker can change and everything needed to predict them."""

    name: str
    hw: Tuple[int, int]
    rays: Int[Tensor, "R"]  # flat pixel indices of rays with at least one gate-open sample
    density: Float[Tensor, "R S 1"]  # base density of the final field's samples
    deltas: Float[Tensor, "R S 1"]
    steps: Float[Tensor, "R S 1"]  # distance of each sample from the camera along the (unit) ray direction
    open_index: Int[Tensor, "N"]  # flat (ray * S + sample) index of the gate-open samples
    psi_scale: Float[Tensor, "N 1"]  # psi * gate scale at the open samples
    features: Float[Tensor, "N F"]  # Sticker.features of the open samples' normalized positions
    base_signal: Float[Tensor, "C R"]  # the base's own outputs at the rays (accumulation[, acc * expected depth])
    depth_scale: float  # divides acc * depth so both signals are O(1) per unit of weight
    signals: Tuple[str, ...]  # ("accumulation",) or ("accumulation", "expected_depth")
    image: Optional[Tensor] = None  # [3 H W] the base render (for figures)
    rgb: Optional[Float[Tensor, "R S 3"]] = None  # the base's colour at the samples (the informed image decoder's)


def geometry_signal(outputs: Dict[str, Tensor], use_depth: bool) -> Tuple[Float[Tensor, "C P"], Tuple[str, ...]]:
    """A render's geometry per pixel: accumulation and (when asked) accumulation x expected depth.

    Nerfstudio names: nerfacto ``accumulation`` + ``expected_depth`` (its ``depth`` is the *median* depth, a step
    function of the weights: not used); TensoRF ``accumulation``; vanilla-nerf ``accumulation_fine``. Expected
    depth is normalized by accumulation and measured along unit-norm ray directions, so ``acc * depth`` is the
    weighted sum of the sample distances.
    """
    acc_key = next((k for k in ACCUMULATION_KEYS if isinstance(outputs.get(k), Tensor)), None)
    if acc_key is None:
        raise GStickerError(f"the suspect renders no accumulation (outputs: {sorted(outputs)[:12]}); geometric "
                            "decoding needs a NeRF-style model: use --decode extractor")
    acc = outputs[acc_key].float().reshape(-1)
    if not use_depth:
        return acc[None], ("accumulation",)
    depth_key = next(k for k in EXPECTED_DEPTH_KEYS if isinstance(outputs.get(k), Tensor))
    return torch.stack([acc, acc * outputs[depth_key].float().reshape(-1)]), ("accumulation", "expected_depth")


def has_expected_depth(outputs: Dict[str, Any]) -> bool:
    return any(isinstance(outputs.get(k), Tensor) for k in EXPECTED_DEPTH_KEYS)


def predict_change(ref: ReferenceView, sticker: Sticker, signs: Float[Tensor, "K"]) -> Float[Tensor, "C R"]:
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


def jacobian(fn: Callable[[Tensor], Tensor], s: Float[Tensor, "K"], chunk: int = 16) -> Float[Tensor, "M K"]:
    """d fn / d s by forward-mode AD, ``chunk`` directions at a time (memory stays bounded)."""
    from torch.func import jvp, vmap

    eye = torch.eye(s.numel(), dtype=s.dtype, device=s.device)
    cols = []
    for i in range(0, s.numel(), chunk):
        cols.append(vmap(lambda v: jvp(fn, (s,), (v,))[1].reshape(-1))(eye[i: i + chunk]))
    return torch.cat(cols).T


def per_ray_jacobian(change: Callable[[Tensor], Tensor], sticker: Sticker, features: Float[Tensor, "N F"],
                     signs: Float[Tensor, "K"], ray_of_sample: Int[Tensor, "N"],
                     num_rays: int) -> Optional[Float[Tensor, "C R K"]]:
    """d change(mix(features, s)) / d s at ``signs``, when output ``[c, r]`` of ``change`` ([C R], a function of the
    sticker values at the gate-open samples) depends on the samples of ray ``r`` only; None for a sticker without a
    closed-form :meth:`Sticker.mix_jacobian` (``concat``: use :func:`jacobian`).

    Then d sum_r change[c, r] / d m_j is d change[c, ray(j)] / d m_j, so C backward passes give every sample's
    derivative, and the chain rule through the sticker's own Jacobian sums them per ray: the same matrix as
    forward-mode AD over the K directions, without K passes of the renderer.
    """
    if sticker.kind != "bilinear":
        return None
    with torch.no_grad():
        m = sticker.mix(features, signs)
    dm_ds = sticker.mix_jacobian(features, m)
    m = m.requires_grad_(True)
    with torch.enable_grad():
        out = change(m)
        grads = [torch.autograd.grad(out[c].sum(), m, retain_graph=c + 1 < out.shape[0])[0]
                 for c in range(out.shape[0])]
    k = dm_ds.shape[1]
    return torch.stack([torch.zeros(num_rays, k, dtype=dm_ds.dtype, device=dm_ds.device)
                        .index_add(0, ray_of_sample, g * dm_ds) for g in grads])


def change_jacobian(ref: ReferenceView, sticker: Sticker, signs: Float[Tensor, "K"]) -> Optional[Float[Tensor, "M K"]]:
    """d predict_change / d signs, flattened like ``predict_change(...).reshape(-1)`` (None: no closed form)."""
    r, s = ref.density.shape[:2]
    j = per_ray_jacobian(lambda x: signal_of_sticker(ref, x), sticker, ref.features, signs, ref.open_index // s, r)
    return None if j is None else j.reshape(-1, j.shape[-1])


@dataclass
class Fit:
    signs: Float[Tensor, "K"]
    explained: float  # 1 - |residual after| ^2 / |residual before| ^2 (0 when there is nothing to explain)
    residual_rms: float  # of the target (suspect minus base), in signal units
    iterations: int


def fit_message(predict: Callable[[Tensor], Tensor], target: Float[Tensor, "M"], num_bits: int,
                iterations: int = 10, damping: float = 1e-3,
                jac: Optional[Callable[[Tensor], Optional[Tensor]]] = None) -> Fit:
    """Least squares ``min_s |target - (predict(s) - predict(0))|^2`` over ``s in [-1, 1]^K``.

    Levenberg-Marquardt from ``s = 0`` (Jacobians from ``jac(s)`` when it gives one, else by forward-mode AD;
    normal equations in float64, steps clamped to the box). A zero target returns ``s = 0`` exactly.
    """
    s = torch.zeros(num_bits, dtype=target.dtype, device=target.device)
    with torch.no_grad():
        f0 = predict(s).reshape(-1)
    target = target.reshape(-1)
    cost0 = float((target.double() ** 2).sum())
    rms = (cost0 / max(1, target.numel())) ** 0.5
    if cost0 == 0.0:
        return Fit(signs=s, explained=0.0, residual_rms=0.0, iterations=0)
    e = target.clone()
    cost = cost0
    lam = damping
    it = 0
    for it in range(1, iterations + 1):
        j = jac(s) if jac is not None else None
        if j is None:
            j = jacobian(lambda x: predict(x).reshape(-1) - f0, s)
        j = j.double()
        a = j.T @ j
        g = j.T @ e.double()
        diag = torch.diagonal(a).clone()
        ridge = 1e-12 * float(diag.max()) if float(diag.max()) > 0 else 1e-30
        improved = False
        while lam < 1e8:
            step = torch.linalg.solve(a + torch.diag(lam * diag + ridge), g)
            s_try = (s + step.to(s.dtype)).clamp(-1.0, 1.0)
            with torch.no_grad():
                e_try = target - (predict(s_try).reshape(-1) - f0)
            c_try = float((e_try.double() ** 2).sum())
            if c_try < cost:
                s, e, improved = s_try, e_try, True
                gain = cost - c_try
                cost = c_try
                lam = max(lam / 3.0, 1e-9)
                break
            lam *= 10.0
        if not improved or gain <= 1e-10 * cost0:
            break
    return Fit(signs=s.detach(), explained=1.0 - cost / cost0, residual_rms=rms, iterations=it)


def fit_and_decide(predict: Callable[[Tensor], Tensor], jac: Callable[[Tensor], Optional[Tensor]],
                   target: Float[Tensor, "M"], num_bits: int, has_rays: bool, generator: torch.Generator,
                   iterations: int = 10) -> Tuple[Fit, Int[Tensor, "K"], int]:
    """:func:`fit_message` then :func:`decide_bits`, shared by every informed decoder; a view with no ray the gate
    opens on (``has_rays`` false) has nothing to read: ``s = 0``, every bit a coin flip."""
    if not has_rays:
        fit = Fit(signs=torch.zeros(num_bits), explained=0.0, residual_rms=0.0, iterations=0)
    else:
        fit = fit_message(predict, target, num_bits, iterations=iterations, jac=jac)
    bits, undetermined = decide_bits(fit.signs, generator)
    return fit, bits, undetermined


def fit_summary(fit: Fit, undetermined: int, rays: int) -> Dict[str, Any]:
    """The per-view fit details the colour and image decoders report."""
    return {"signs_abs_mean": float(fit.signs.abs().mean()), "undetermined": undetermined, "explained": fit.explained,
            "residual_rms": fit.residual_rms, "iterations": fit.iterations, "rays": rays}


UNDETERMINED = -1
"""The value of a bit the suspect does not determine: it matches no message bit (counted as a mismatch)."""


def decide_bits(signs: Float[Tensor, "K"], generator: Optional[torch.Generator] = None,
                tol: float = 1e-6) -> Tuple[Int[Tensor, "K"], int]:
    """Bit ``i`` = ``signs_i > 0``; bits with ``|signs_i| <= tol`` (not determined by the suspect) are
    :data:`UNDETERMINED`, a mismatch whatever the message (deterministic and conservative: the matches of an unmarked
    suspect are then at most Binomial). Returns the bits and how many are undetermined. ``generator`` is unused."""
    bits = (signs > 0).long().cpu()
    tie = (signs.abs() <= tol).cpu()
    bits = torch.where(tie, torch.full_like(bits, UNDETERMINED), bits)
    return bits, int(tie.sum())


# ================================================================================================================
# the owner's base with the key's sticker
# ================================================================================================================


@dataclass
class BaseReference:
    """The owner's base run rebuilt with the key's sticker and gates (sticker off: renders are the base's)."""

    config_path: Path
    checkpoint: Path
    method: str
    pipeline: Any  # the base run's pipeline (cameras)
    model: Any  # GeometryStickerModel wrapping the base
    notes: List[str] = field(default_factory=list)
    samples_follow_sticker: bool = False  # the final samples are placed by a wrapped density (TensoRF, vanilla-nerf)


def missing_geometry_message(key_path) -> str:
    return (f"the owner key {key_path} has no geometry reference (a version-1 key); add it with `ns-verify-owner "
            f"export-key --load-config WATERMARKED_RUN/config.yml --key {key_path}` (or retrain), or pass "
            "--decode extractor")


def recorded_base_config(key) -> Optional[Path]:
    cfg = (key.base or {}).get("config")
    return Path(cfg) if cfg else None


def base_config_path(key, key_path, base_config: Optional[Path]) -> Path:
    """The base run's config.yml: ``--base-config`` or the path recorded in the key; one-line error otherwise."""
    cfg = Path(base_config) if base_config is not None else recorded_base_config(key)
    if cfg is not None and cfg.is_dir() and (cfg / "config.yml").is_file():
        cfg = cfg / "config.yml"
    if cfg is None or not cfg.is_file():
        where = "given with --base-config" if base_config is not None else "recorded in the key"
        raise GStickerError(f"the owner's base run {cfg} ({where}) does not exist here; geometric decoding needs "
                            "the unwatermarked base: pass --base-config BASE_RUN/config.yml (or --decode extractor)")
    return cfg


def base_checkpoint(key, config_path: Path, only_beside: bool = False) -> Path:
    """The base checkpoint the key was made on, beside ``config_path`` or (unless ``only_beside``: the user
    named the base run) where the key recorded it; sha256 checked."""
    from gsticker_plugin.key import file_sha256

    recorded = (key.base or {}).get("checkpoint")
    want = (key.base or {}).get("checkpoint_sha256")
    if not recorded or not want:
        raise GStickerError("the owner key does not record its base checkpoint and sha256; retrain the sticker "
                            "with this gsticker (ns-train geometrysticker --load-checkpoint ...)")
    name = Path(recorded).name
    candidates = [config_path.parent / "nerfstudio_models" / name] + ([] if only_beside else [Path(recorded)])
    found = next((c for c in candidates if c.is_file()), None)
    if found is None:
        raise GStickerError(f"the base checkpoint {name} the key was made on is not in "
                            f"{config_path.parent / 'nerfstudio_models'}; pass --base-config with the base run "
                            "the watermark was made on")
    got = file_sha256(found)
    if got != want:
        raise GStickerError(f"base checkpoint {found} has sha256 {got[:12]}... but the key was made on "
                            f"{want[:12]}...; pass --base-config with the exact base run the watermark was made on")
    return found


def data_if_missing(config_path: Path, data: Optional[Path]) -> Optional[Path]:
    """``data`` only when the run's recorded dataset does not exist from here."""
    from gsticker_plugin import base_run

    cfg = base_run.load_run_config(config_path)
    dm = cfg.pipeline.datamanager
    recorded = getattr(dm, "data", None) or getattr(getattr(dm, "dataparser", None), "data", None)
    return None if (recorded is not None and Path(recorded).exists()) else data


def load_base_reference(key, key_path, base_config: Optional[Path], data: Optional[Path],
                        device: torch.device) -> BaseReference:
    """Rebuild the owner's base (strictly, sha256-checked) wrapped by a GeometrySticker model with the key's
    sticker and gates. ``data``: dataset folder used when the base's recorded one does not exist here."""
    from gsticker_plugin import base_run
    from gsticker_plugin.model import GeometryStickerModelConfig
    from gsticker_plugin.verify import load_run

    geo = key.geometry
    if not geo:
        raise GStickerError(missing_geometry_message(key_path))
    cfg_path = base_config_path(key, key_path, base_config)
    ckpt = base_checkpoint(key, cfg_path, only_beside=base_config is not None)
    with contextlib.redirect_stdout(sys.stderr):
        config, pipeline, _ = load_run(cfg_path, data=data_if_missing(cfg_path, data), device=device)
    if hasattr(pipeline.model, "sticker_enabled"):
        raise GStickerError(f"{cfg_path} is a watermarked run, not the unwatermarked base; pass --base-config with "
                            "the base run the watermark was made on")
    sc = geo["sticker_config"]
    base_model_cfg = config.pipeline.model
    mcfg = GeometryStickerModelConfig(
        base_model=base_model_cfg, num_bits=int(sc["num_bits"]), num_frequencies=int(sc["num_frequencies"]),
        sticker_hidden_dim=int(sc["hidden_dim"]), sticker_num_layers=int(sc["num_layers"]),
        sticker_kind=sc["kind"], gate_threshold=float(geo["gate_threshold"]), base_step=base_run.checkpoint_step(ckpt),
        wrap_proposal_networks=bool(geo["wrap_proposal_networks"]),
        mark_sampling_passes=bool(geo.get("mark_sampling_passes", True)),  # keys written before the option: on
        eval_num_rays_per_chunk=int(getattr(base_model_cfg, "eval_num_rays_per_chunk", 4096)))
    ds = pipeline.datamanager.train_dataset
    with contextlib.redirect_stdout(sys.stderr):
        model = mcfg.setup(scene_box=ds.scene_box, num_train_data=len(ds), metadata=ds.metadata, device=device)
    state = base_run.load_checkpoint_state(ckpt)
    base_run.strict_load(model.base, base_run.model_state_from_pipeline_state(state["pipeline"]), len(ds))
    names = [w.name for w in model.wraps]
    if names != list(geo["fields"]):
        raise GStickerError(f"the key's sticker wraps fields {list(geo['fields'])} but the base rebuilds {names}; "
                            "pass --base-config with the base run the watermark was made on")
    try:
        model.sticker.load_state_dict(geo["sticker_state"], strict=True)
        model.gates.load_state_dict(geo["gates_state"], strict=True)
    except RuntimeError as e:
        raise GStickerError(f"the key's sticker does not fit its own configuration ({str(e).splitlines()[0]}); "
                            "the key is damaged: use your original copy") from None
    notes = []
    if sc["kind"] == "bilinear" and int(sc["hidden_dim"]) + 1 < int(sc["num_bits"]):
        notes.append(f"the bilinear sticker's {sc['hidden_dim']} hidden units span fewer than its {sc['num_bits']} "
                     "bit patterns: some bits are not identifiable from geometry (decoded near chance)")
    for w in model.wraps:
        stored = geo["aabb"][w.name].to(w.aabb)
        if not torch.allclose(stored, w.aabb):
            notes.append(f"{w.name}: position normalization taken from the key (rebuilt base differs)")
        w.aabb = stored
    model.to(device)
    model.eval()
    # nerfacto's proposal networks place its samples and are not wrapped (by default): its samples do not move;
    # without marked sampling passes no base's samples move
    follows = mcfg.mark_sampling_passes and not (hasattr(model.base, "proposal_sampler")
                                                 and not mcfg.wrap_proposal_networks)
    return BaseReference(config_path=cfg_path, checkpoint=ckpt, method=config.method_name, pipeline=pipeline,
                         model=model, notes=notes, samples_follow_sticker=follows)


@torch.no_grad()
def reference_view(ref: BaseReference, name: str, camera, use_depth: bool,
                   message: Optional[Int[Tensor, "K"]] = None) -> ReferenceView:
    """Render the base at ``camera`` once (sticker off) and keep the rays whose samples the sticker can change.

    ``use_depth`` is honoured only when the base renders expected depth too (vanilla-nerf does not): the view's
    ``signals`` say which were kept, and :func:`suspect_signal` takes the same ones from the suspect.

    ``message``: take the samples the base marked with ``message`` draws instead (see
    :func:`relinearized_view`); the returned ``base_signal`` is then the render's, to be replaced by the caller.
    """
    from gsticker_plugin.fastpath import cache_view

    model = ref.model
    outputs: Dict[str, Tensor] = {}
    cam = camera.to(model.device)
    view = cache_view(model, cam, novel=False, outputs_into=outputs, full_precision=True, message=message)
    h, w = view.hw
    wrap = model.final_wrap
    density = view.density.float()  # [A S 1]
    psi = wrap.gate(density.to(model.device)).cpu()
    open_ = (psi > wrap.gate_threshold).squeeze(-1) & bool(wrap.gate.calibrated)  # the wrap's own rule
    keep = open_.any(dim=-1)
    rays = view.active[keep]
    density, open_, psi = density[keep], open_[keep], psi[keep]
    rgb = view.rgb[keep].float()
    positions = view.positions[keep].float()
    deltas = view.deltas[keep].float()
    origin = cam.camera_to_worlds[0, :3, 3].float().cpu()
    steps = (positions - origin).norm(dim=-1, keepdim=True)
    open_index = open_.reshape(-1).nonzero().squeeze(-1)
    pos_open = positions.reshape(-1, 3)[open_index]
    feats = model.sticker.features(wrap.normalize(pos_open.to(model.device))).cpu() if open_index.numel() else \
        torch.zeros(0, model.sticker.num_bits)
    psi_scale = psi.reshape(-1, 1)[open_index] * float(wrap.gate.scale)
    use_depth = use_depth and has_expected_depth(outputs)  # e.g. a vanilla-nerf base: accumulation only
    signal, names = geometry_signal(outputs, use_depth)
    weights = render_weights(density, deltas)
    wsum = float(weights.sum())
    depth_scale = float((weights * steps).sum()) / wsum if wsum > 0 else 1.0
    base_signal = signal[:, rays]
    if use_depth:
        base_signal = base_signal.clone()
        base_signal[1] /= depth_scale
    return ReferenceView(name=name, hw=(h, w), rays=rays, density=density, deltas=deltas, steps=steps,
                         open_index=open_index, psi_scale=psi_scale, features=feats, base_signal=base_signal,
                         depth_scale=depth_scale, signals=names,
                         image=view.image.permute(2, 0, 1).contiguous(), rgb=rgb)


def relinearized_view(ref: BaseReference, name: str, camera, use_depth: bool, bits: Int[Tensor, "K"],
                      sticker: Sticker) -> ReferenceView:
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
        raise GStickerError(f"the suspect rendered {signal.shape[1]} pixels for a {h}x{w} camera; geometric decoding "
                            "needs renders at the base's cameras")
    out = signal[:, ref.rays].clone()
    if out.shape[0] == 2:
        out[1] /= ref.depth_scale
    return out


def decode_view(ref_view: ReferenceView, sticker: Sticker, suspect: Float[Tensor, "C R"],
                generator: torch.Generator, iterations: int = 10) -> Dict[str, Any]:
    """Fit the continuous message to one view's suspect geometry and decide the bits."""
    target = (suspect - ref_view.base_signal).float()
    fit, bits, undetermined = fit_and_decide(lambda s: predict_change(ref_view, sticker, s),
                                             lambda s: change_jacobian(ref_view, sticker, s), target, sticker.num_bits,
                                             ref_view.rays.numel() > 0, generator, iterations)
    return {"bits": bits, "signs": fit.signs, "undetermined": undetermined, "explained": fit.explained,
            "residual_rms": fit.residual_rms, "iterations": fit.iterations, "rays": int(ref_view.rays.numel())}


# ================================================================================================================
# a suspect model, all views
# ================================================================================================================


def cpu_sticker(model) -> Sticker:
    """A frozen CPU copy of the model's sticker (the fit runs on the CPU)."""
    import copy

    return copy.deepcopy(model.sticker).cpu().requires_grad_(False).eval()


def decode_suspect(key, reference: BaseReference, suspect_model, num_views: int, sampled_share: float, seed: int,
                   sticker: Optional[bool] = None, progress: bool = False, iterations: int = 10,
                   ref_cache: Optional[Dict[Any, ReferenceView]] = None, cameras: Optional[List[Tuple[str, Any]]] = None,
                   relinearize: int = 1, full_renders: bool = True):
    """Render the base and the suspect at ``num_views`` cameras of the base run (or the given ``(name, camera)``
    list), fit and decode every view.

    Returns ``(dec, views)``: ``dec`` holds per view ``bits``, ``matches``, ``bit_acc``, ``pvalues`` (as
    :func:`gsticker_plugin.verify.decode_views`; ``scores`` is None: the classifier reads images, not geometry)
    and ``geometry`` (per-view fit details); ``views`` are :class:`gsticker_plugin.verify.View` with the suspect's
    RGB renders (for the report's figure). ``ref_cache``: a dict kept by the caller to reuse the base's reference
    views across suspects decoded with the same reference, cameras and seed. ``relinearize``: for bases whose
    samples follow the wrapped density, refit this many times around the previous fit's bits
    (:func:`relinearized_view`; a reference render and a fit more per view). ``full_renders=False``: render the
    suspect only at the rays the fit reads (:func:`suspect_renders`; the same numbers, a quarter of the rays on
    lego100) and return no views (there is no whole suspect image to show).
    """
    from gsticker_plugin.verify import View

    st = cpu_sticker(reference.model)
    gen = tie_generator(seed)
    bits, details, views = [], [], []
    ref_cache = {} if ref_cache is None else ref_cache  # one base render per camera
    rays_for = None if full_renders else (lambda name, cam: any_reference_view(reference, name, cam, ref_cache).rays)
    for name, cam, out in suspect_renders(reference, suspect_model, num_views, sampled_share, seed, sticker, progress,
                                          "geometric decoding", cameras, rays_for=rays_for):
        use_depth = has_expected_depth(out)
        ref_view = cached_reference_view(reference, name, cam, use_depth, ref_cache)
        d = decode_view(ref_view, st, suspect_signal(out, ref_view), gen, iterations)
        rounds = relinearize if reference.samples_follow_sticker else 0
        for _ in range(rounds):
            first = d["bits"]
            rv = relinearized_view(reference, name, cam, use_depth, first, st)
            if not full_renders:  # the marked samples may open the gate on rays the first view did not keep
                out = complete_rays(suspect_model, cam, out, rv.rays)
            d = decode_view(rv, st, suspect_signal(out, rv), gen, iterations)
            d["bits_changed_by_relinearizing"] = int((d["bits"] != first).sum())
        d["relinearized"] = rounds
        bits.append(d.pop("bits"))
        d["signs_abs_mean"] = float(d.pop("signs").abs().mean())
        d["signals"] = list(ref_view.signals)
        details.append(d)
        if full_renders:
            rgb = out.get("rgb", out.get("rgb_fine"))
            img = rgb.clamp(0, 1).permute(2, 0, 1).contiguous() if rgb is not None else ref_view.image
            views.append(View(name=name, image=img))
    return decoded(key, bits, "geometry", details), views


def tie_generator(seed: int) -> torch.Generator:
    """A generator seeded by the verification seed (the decoders' signature; undetermined bits are mismatches)."""
    return torch.Generator().manual_seed(104729 + 7919 * int(seed))


def suspect_renders(reference: BaseReference, suspect_model, num_views: int, sampled_share: float, seed: int,
                    sticker: Optional[bool], progress: bool, desc: str, cameras: Optional[List[Tuple[str, Any]]] = None,
                    rays_for: Optional[Callable[[str, Any], Int[Tensor, "R"]]] = None):
    """Yield ``(name, camera, outputs)`` of the suspect at the base run's chosen cameras, or at ``cameras``
    (outputs float [H W C], on the CPU); ``sticker``: render with the suspect's sticker on/off (None: as it is).

    ``rays_for(name, camera)``: render only these flat pixel indices (the rays a decoder reads) through the
    model's public ``get_outputs_for_camera_ray_bundle``; the other pixels of the outputs are NaN. Nerfstudio's
    ray-based models render every ray on its own, so the rendered pixels equal a whole render's (tested); a model
    that overrides ``get_outputs_for_camera`` is rendered whole.
    """
    from gsticker_plugin.verify import _tqdm, select_cameras

    cams = cameras if cameras is not None else select_cameras(reference.pipeline, num_views, sampled_share, seed)
    ctx = (suspect_model.sticker_enabled(sticker) if (sticker is not None and hasattr(suspect_model, "sticker_enabled"))
           else contextlib.nullcontext())
    per_ray = rays_for is not None and renders_rays_alone(suspect_model)
    with ctx:
        for name, cam in _tqdm(cams, desc, progress):
            rays = rays_for(name, cam) if per_ray else None
            with torch.no_grad():
                if rays is None or rays.numel() == 0:
                    out = suspect_model.get_outputs_for_camera(cam.to(suspect_model.device))
                else:
                    out = render_rays(suspect_model, cam, rays)
            yield name, cam, {k: v.detach().float().cpu() for k, v in out.items() if isinstance(v, Tensor)}


def complete_rays(model, camera, outputs: Dict[str, Tensor], rays: Int[Tensor, "R"]) -> Dict[str, Tensor]:
    """``outputs`` of :func:`render_rays` with the pixels of ``rays`` that were not rendered yet rendered too."""
    acc_key = next((k for k in ACCUMULATION_KEYS if isinstance(outputs.get(k), Tensor)), None)
    if acc_key is None or rays.numel() == 0:
        return outputs
    missing = rays[torch.isnan(outputs[acc_key].reshape(-1)[rays])]
    return render_rays(model, camera, missing, into=outputs) if missing.numel() else outputs


def renders_rays_alone(model) -> bool:
    """Whether ``model`` renders a camera through the stock ``Model.get_outputs_for_camera`` (every ray alone)."""
    from nerfstudio.models.base_model import Model

    return type(model).get_outputs_for_camera is Model.get_outputs_for_camera


@torch.no_grad()
def render_rays(model, camera, rays: Int[Tensor, "R"], into: Optional[Dict[str, Tensor]] = None) -> Dict[str, Tensor]:
    """The model's outputs at the flat pixel indices ``rays`` of a one-camera ``camera``, scattered into whole
    [H W C] images whose other pixels are NaN, or into copies of ``into``'s images (on their device and dtype)."""
    bundle = camera.to(model.device).generate_rays(camera_indices=0, keep_shape=True)
    h, w = bundle.origins.shape[:2]
    index = rays.to(model.device)
    sub = model.get_outputs_for_camera_ray_bundle(bundle.flatten()[index].reshape((-1, 1)))
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


def cached_reference_view(reference: BaseReference, name: str, cam, use_depth: bool,
                          ref_cache: Optional[Dict[Any, ReferenceView]]) -> ReferenceView:
    """:func:`reference_view`, kept in ``ref_cache`` (when given) under ``(name, use_depth)``. The view without
    depth is the one with depth less its second signal (the same rays and base render): derived, not re-rendered."""
    if ref_cache is not None and (name, use_depth) in ref_cache:
        return ref_cache[(name, use_depth)]
    with_depth = ref_cache.get((name, True)) if ref_cache is not None and not use_depth else None
    ref_view = without_depth(with_depth) if with_depth is not None else \
        reference_view(reference, name, cam, use_depth=use_depth)
    if ref_cache is not None:
        ref_cache[(name, use_depth)] = ref_view
    return ref_view


def without_depth(view: ReferenceView) -> ReferenceView:
    """The reference view that reads accumulation only (what :func:`reference_view` returns for ``use_depth=False``)."""
    import dataclasses

    return dataclasses.replace(view, base_signal=view.base_signal[:1], signals=view.signals[:1])


def any_reference_view(reference: BaseReference, name: str, cam,
                       ref_cache: Optional[Dict[Any, ReferenceView]]) -> ReferenceView:
    """A cached reference view of camera ``name`` (either signal set), else one with depth (its rays do not depend
    on the signals read)."""
    for k in ((name, True), (name, False)):
        if ref_cache is not None and k in ref_cache:
            return ref_cache[k]
    return cached_reference_view(reference, name, cam, True, ref_cache)


def decoded(key, bits: List[Tensor], details_name: str, details: List[Dict[str, Any]]) -> Dict[str, Any]:
    """Per-view bits -> matches, bit accuracy and binomial p-values against the owner's message."""
    from gsticker_plugin import metrics

    b = torch.stack(bits)
    m = metrics.count_matches(b, key.message)
    return {"bits": b, "matches": m, "bit_acc": metrics.bit_accuracy(b, key.message),
            "pvalues": metrics.binomial_tail_pvalues(m, key.num_bits), "scores": None, details_name: details}
