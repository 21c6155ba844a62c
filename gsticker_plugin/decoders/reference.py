"""The owner's base rebuilt with the key's sticker, and its per-camera reference views (what the sticker can change)."""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch
from jaxtyping import Float, Int
from torch import Tensor

from gsticker_plugin import hashgrid, runs
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.fastpath import cache_view
from gsticker_plugin.key import file_sha256
from gsticker_plugin.model import GeometryStickerModelConfig
from gsticker_plugin.runs import load_run
from gsticker_plugin.sticker import Sticker, render_weights

ACCUMULATION_KEYS = ("accumulation", "accumulation_fine")


EXPECTED_DEPTH_KEYS = ("expected_depth",)


@dataclass
class ReferenceView:
    """One camera of the owner's base: the rays the sticker can change and everything needed to predict them."""

    name: str
    hw: Tuple[int, int]
    rays: Int[Tensor, " R"]  # flat pixel indices of rays with at least one gate-open sample
    density: Float[Tensor, "R S 1"]  # base density of the final field's samples
    deltas: Float[Tensor, "R S 1"]
    steps: Float[Tensor, "R S 1"]  # distance of each sample from the camera along the (unit) ray direction
    open_index: Int[Tensor, " N"]  # flat (ray * S + sample) index of the gate-open samples
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
        raise GStickerError(
            f"the suspect renders no accumulation (outputs: {sorted(outputs)[:12]}); geometric "
            "decoding needs a NeRF-style model: use --decode extractor"
        )
    acc = outputs[acc_key].float().reshape(-1)
    if not use_depth:
        return acc[None], ("accumulation",)
    depth_key = next(k for k in EXPECTED_DEPTH_KEYS if isinstance(outputs.get(k), Tensor))
    return torch.stack([acc, acc * outputs[depth_key].float().reshape(-1)]), ("accumulation", "expected_depth")


def has_expected_depth(outputs: Dict[str, Any]) -> bool:
    return any(isinstance(outputs.get(k), Tensor) for k in EXPECTED_DEPTH_KEYS)


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
    return (
        f"the owner key {key_path} has no geometry reference (a version-1 key); add it with `ns-verify-owner "
        f"export-key --load-config WATERMARKED_RUN/config.yml --key {key_path}` (or retrain), or pass "
        "--decode extractor"
    )


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
        raise GStickerError(
            f"the owner's base run {cfg} ({where}) does not exist here; geometric decoding needs "
            "the unwatermarked base: pass --base-config BASE_RUN/config.yml (or --decode extractor)"
        )
    return cfg


def base_checkpoint(key, config_path: Path, only_beside: bool = False) -> Path:
    """The base checkpoint the key was made on, beside ``config_path`` or (unless ``only_beside``: the user
    named the base run) where the key recorded it; sha256 checked."""

    recorded = (key.base or {}).get("checkpoint")
    want = (key.base or {}).get("checkpoint_sha256")
    if not recorded or not want:
        raise GStickerError(
            "the owner key does not record its base checkpoint and sha256; retrain the sticker "
            "with this gsticker (ns-train geometrysticker --load-checkpoint ...)"
        )
    name = Path(recorded).name
    candidates = [config_path.parent / "nerfstudio_models" / name] + ([] if only_beside else [Path(recorded)])
    found = next((c for c in candidates if c.is_file()), None)
    if found is None:
        raise GStickerError(
            f"the base checkpoint {name} the key was made on is not in "
            f"{config_path.parent / 'nerfstudio_models'}; pass --base-config with the base run "
            "the watermark was made on"
        )
    got = file_sha256(found)
    if got != want:
        raise GStickerError(
            f"base checkpoint {found} has sha256 {got[:12]}... but the key was made on "
            f"{want[:12]}...; pass --base-config with the exact base run the watermark was made on"
        )
    return found


def data_if_missing(config_path: Path, data: Optional[Path]) -> Optional[Path]:
    """``data`` only when the run's recorded dataset does not exist from here."""
    cfg = runs.load_run_config(config_path)
    dm = cfg.pipeline.datamanager
    recorded = getattr(dm, "data", None) or getattr(getattr(dm, "dataparser", None), "data", None)
    return None if (recorded is not None and Path(recorded).exists()) else data


def load_base_reference(
    key, key_path, base_config: Optional[Path], data: Optional[Path], device: torch.device
) -> BaseReference:
    """Rebuild the owner's base (strictly, sha256-checked) wrapped by a GeometrySticker model with the key's
    sticker and gates. ``data``: dataset folder used when the base's recorded one does not exist here."""
    geo = key.geometry
    if not geo:
        raise GStickerError(missing_geometry_message(key_path))
    cfg_path = base_config_path(key, key_path, base_config)
    ckpt = base_checkpoint(key, cfg_path, only_beside=base_config is not None)
    with contextlib.redirect_stdout(sys.stderr):
        config, pipeline, _ = load_run(cfg_path, data=data_if_missing(cfg_path, data), device=device)
    if hasattr(pipeline.model, "sticker_enabled"):
        raise GStickerError(
            f"{cfg_path} is a watermarked run, not the unwatermarked base; pass --base-config with "
            "the base run the watermark was made on"
        )
    sc = geo["sticker_config"]
    base_model_cfg = config.pipeline.model
    mcfg = GeometryStickerModelConfig(
        base_model=base_model_cfg,
        num_bits=int(sc["num_bits"]),
        num_frequencies=int(sc["num_frequencies"]),
        sticker_hidden_dim=int(sc["hidden_dim"]),
        sticker_num_layers=int(sc["num_layers"]),
        sticker_kind=sc["kind"],
        gate_threshold=float(geo["gate_threshold"]),
        base_step=runs.checkpoint_step(ckpt),
        wrap_proposal_networks=bool(geo["wrap_proposal_networks"]),
        mark_sampling_passes=bool(geo.get("mark_sampling_passes", True)),  # keys written before the option: on
        eval_num_rays_per_chunk=int(getattr(base_model_cfg, "eval_num_rays_per_chunk", 4096)),
    )
    ds = pipeline.datamanager.train_dataset
    with contextlib.redirect_stdout(sys.stderr):
        model = mcfg.setup(scene_box=ds.scene_box, num_train_data=len(ds), metadata=ds.metadata, device=device)
    state = runs.load_checkpoint_state(ckpt)
    runs.strict_load(model.base, runs.model_state_from_pipeline_state(state["pipeline"]), len(ds))
    names = [w.name for w in model.wraps]
    if names != list(geo["fields"]):
        raise GStickerError(
            f"the key's sticker wraps fields {list(geo['fields'])} but the base rebuilds {names}; "
            "pass --base-config with the base run the watermark was made on"
        )
    try:
        model.sticker.load_state_dict(geo["sticker_state"], strict=True)
        model.gates.load_state_dict(geo["gates_state"], strict=True)
    except RuntimeError as e:
        raise GStickerError(
            f"the key's sticker does not fit its own configuration ({str(e).splitlines()[0]}); "
            "the key is damaged: use your original copy"
        ) from None
    notes = []
    if sc["kind"] == "bilinear" and int(sc["hidden_dim"]) + 1 < int(sc["num_bits"]):
        notes.append(
            f"the bilinear sticker's {sc['hidden_dim']} hidden units span fewer than its {sc['num_bits']} "
            "bit patterns: some bits are not identifiable from geometry (decoded near chance)"
        )
    for w in model.wraps:
        stored = geo["aabb"][w.name].to(w.aabb)
        if not torch.allclose(stored, w.aabb):
            notes.append(f"{w.name}: position normalization taken from the key (rebuilt base differs)")
        w.aabb = stored
    model.to(device)
    model.eval()
    hashgrid.speed_up(model)
    # nerfacto's proposal networks place its samples and are not wrapped (by default): its samples do not move;
    # without marked sampling passes no base's samples move
    follows = mcfg.mark_sampling_passes and not (
        hasattr(model.base, "proposal_sampler") and not mcfg.wrap_proposal_networks
    )
    return BaseReference(
        config_path=cfg_path,
        checkpoint=ckpt,
        method=config.method_name,
        pipeline=pipeline,
        model=model,
        notes=notes,
        samples_follow_sticker=follows,
    )


@torch.no_grad()
def reference_view(
    ref: BaseReference, name: str, camera, use_depth: bool, message: Optional[Int[Tensor, " K"]] = None
) -> ReferenceView:
    """Render the base at ``camera`` once (sticker off) and keep the rays whose samples the sticker can change.

    ``use_depth`` is honoured only when the base renders expected depth too (vanilla-nerf does not): the view's
    ``signals`` say which were kept, and :func:`suspect_signal` takes the same ones from the suspect.

    ``message``: take the samples the base marked with ``message`` draws instead (see
    :func:`relinearized_view`); the returned ``base_signal`` is then the render's, to be replaced by the caller.
    """

    model = ref.model
    outputs: Dict[str, Tensor] = {}
    cam = camera.to(model.device)
    view = cache_view(model, cam, novel=False, outputs_into=outputs, full_precision=True, message=message)
    h, w = view.hw
    wrap = model.final_wrap
    density = view.density.float()  # [A S 1]
    psi, open_ = (t.cpu() for t in wrap.open_samples(density.to(model.device)))
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
    feats = (
        model.sticker.features(wrap.normalize(pos_open.to(model.device))).cpu()
        if open_index.numel()
        else torch.zeros(0, model.sticker.num_bits)
    )
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
    return ReferenceView(
        name=name,
        hw=(h, w),
        rays=rays,
        density=density,
        deltas=deltas,
        steps=steps,
        open_index=open_index,
        psi_scale=psi_scale,
        features=feats,
        base_signal=base_signal,
        depth_scale=depth_scale,
        signals=names,
        image=view.image.permute(2, 0, 1).contiguous(),
        rgb=rgb,
    )


def cached_reference_view(
    reference: BaseReference, name: str, cam, use_depth: bool, ref_cache: Optional[Dict[Any, ReferenceView]]
) -> ReferenceView:
    """:func:`reference_view`, kept in ``ref_cache`` (when given) under ``(name, use_depth)``. The view without
    depth is the one with depth less its second signal (the same rays and base render): derived, not re-rendered."""
    if ref_cache is not None and (name, use_depth) in ref_cache:
        return ref_cache[(name, use_depth)]
    with_depth = ref_cache.get((name, True)) if ref_cache is not None and not use_depth else None
    ref_view = (
        without_depth(with_depth)
        if with_depth is not None
        else reference_view(reference, name, cam, use_depth=use_depth)
    )
    if ref_cache is not None:
        ref_cache[(name, use_depth)] = ref_view
    return ref_view


def without_depth(view: ReferenceView) -> ReferenceView:
    """The reference view that reads accumulation only (what :func:`reference_view` returns for ``use_depth=False``)."""
    return dataclasses.replace(view, base_signal=view.base_signal[:1], signals=view.signals[:1])


def any_reference_view(
    reference: BaseReference, name: str, cam, ref_cache: Optional[Dict[Any, ReferenceView]]
) -> ReferenceView:
    """A cached reference view of camera ``name`` (either signal set), else one with depth (its rays do not depend
    on the signals read)."""
    for k in ((name, True), (name, False)):
        if ref_cache is not None and k in ref_cache:
            return ref_cache[k]
    return cached_reference_view(reference, name, cam, True, ref_cache)


def cpu_sticker(model) -> Sticker:
    """A frozen CPU copy of the model's sticker (the fit runs on the CPU)."""
    return copy.deepcopy(model.sticker).cpu().requires_grad_(False).eval()
