"""GeometrySticker model: a frozen base model whose rendering fields' density carries the sticker.

The base (any stock model: nerfacto, vanilla-nerf, TensoRF, ...) is rebuilt from its own config and kept
as ``self.base`` (frozen, always in eval mode). Rendering, metrics and images are the base's own, so stock
``ns-viewer``, ``ns-render`` and ``ns-eval`` work unchanged; the watermark is only the density wrap.
"""

from __future__ import annotations

import secrets
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Dict, Iterator, List, Literal, Optional, Tuple, Type

import torch
import tyro
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.base_field import Field
from nerfstudio.models.base_model import Model, ModelConfig
from torch import Tensor, nn
from torch.nn import Parameter

from gsticker_plugin.background import Background, background_of
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.sticker import DensityWrap, FoldedSticker, Gate, Sticker, WrapState

GEOMETRY_REFERENCE_VERSION = 1


@dataclass
class GeometryStickerModelConfig(ModelConfig):
    """Sticker and gate hyper-parameters; the base model config is filled in from the base run."""

    _target: Type = field(default_factory=lambda: GeometryStickerModel)
    enable_collider: bool = False
    """The base applies its own collider."""
    base_model: tyro.conf.Suppress[Optional[Any]] = None
    """The base run's ModelConfig (copied from its config.yml; not a CLI option)."""
    base_step: tyro.conf.Suppress[Optional[int]] = None
    """The base checkpoint's training step: the base is sized for it when rebuilt (TensoRF's grids grow during
    training); recorded from the checkpoint, not a CLI option."""
    num_bits: int = 48
    """Message length."""
    sticker_hidden_dim: int = 64
    """Width of the sticker MLP's two hidden layers."""
    sticker_num_layers: int = 2
    """Hidden layers of the sticker MLP."""
    sticker_kind: Literal["bilinear", "concat"] = "bilinear"
    """bilinear: per-bit learned 3D patterns flipped by the bits (fast to learn); concat: the paper's MLP of [gamma(x), M]."""
    sticker_init_scale: float = 0.5
    """Uniform init range of the sticker's output layer (its first renders must be visible to the extractor)."""
    num_frequencies: int = 5
    """Octaves of the positional encoding gamma(x) (3 + 6L dims)."""
    gate_quantile: float = 0.5
    """Gate centre mu = this weighted quantile of the base density over visible samples."""
    beta_ratio: float = 0.1
    """Initial gate width beta = beta_ratio * mu (then learned)."""
    sticker_amplitude: float = 10.0
    """Largest density change of the sticker, in units of mu (10 mu: about 30 dB at full strength on lego)."""
    gate_threshold: float = 1e-3
    """The sticker is evaluated only at samples whose psi exceeds this."""
    wrap_proposal_networks: bool = False
    """Also wrap nerfacto's proposal density fields (they only place samples; off by default)."""
    mark_sampling_passes: bool = True
    """Also mark the density evaluations that only place samples or answer queries: TensoRF's coarse (uniform)
    pass, vanilla-nerf's coarse field, direct ``get_density``/``density_fn`` calls. False (what ``ns-train
    geometrysticker`` writes): the sticker acts only inside the final field's rendering pass, so every base draws
    its own samples (the fast path and the geometric decoder are then exact for TensoRF and vanilla-nerf too).
    Runs written before this option had it on and load so."""


class GeometryStickerModel(Model):
    """A frozen base model plus the sticker on the density of its rendering fields."""

    config: GeometryStickerModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()
        if self.config.base_model is None:
            raise GStickerError(
                "this geometrysticker config has no base model; train it with "
                "`ns-train geometrysticker --load-checkpoint BASE_RUN/nerfstudio_models/step-N.ckpt`"
            )
        self.base: Model = self.config.base_model.setup(
            scene_box=self.scene_box, num_train_data=self.num_train_data, **self.kwargs
        )
        if self.config.base_step is not None:
            self.base.update_to_step(int(self.config.base_step))  # e.g. TensoRF's grid resolution at that step
        self.base.requires_grad_(False)
        self.base.eval()
        # the sticker's initial weights come from a secret seed, never from machine.seed: what the fold mixes with
        # the message (the per-bit patterns) cannot be regenerated from a shared run's config
        self.sticker_seed = secrets.randbits(63)
        self.sticker = seeded_sticker(sticker_config(self.config), self.sticker_seed)
        self.register_buffer("message", torch.zeros(self.config.num_bits, dtype=torch.long))
        # the shared form: the sticker of the owner's message, folded (no bits, no per-bit patterns)
        self.folded_sticker = FoldedSticker(
            self.config.num_frequencies, self.config.sticker_hidden_dim, self.config.sticker_num_layers
        )
        self.register_buffer("folded", torch.tensor(False))
        self.register_load_state_dict_pre_hook(GeometryStickerModel._fill_unshared)
        self.wrap_state = WrapState(enabled=True, final_only=not self.config.mark_sampling_passes)
        self.gates = nn.ModuleDict()
        self.wraps: List[DensityWrap] = []
        for name, fld in self.rendering_fields():
            gate = Gate()
            self.gates[name.replace(".", "__")] = gate
            aabb = getattr(fld, "aabb", None)
            aabb = aabb if isinstance(aabb, Tensor) and aabb.shape == (2, 3) else self.scene_box.aabb
            self.wraps.append(
                DensityWrap(
                    fld, name, self.sticker, gate, self.wrap_state, aabb.detach().clone(), self.config.gate_threshold
                )
            )
        if not self.wraps:
            raise GStickerError(
                f"{type(self.base).__name__} has no density field that gsticker can wrap; "
                "use a NeRF-style base (nerfacto, vanilla-nerf, tensorf, instant-ngp)"
            )
        self.wraps[-1].is_final = True
        self._viewer_elements()

    def _viewer_elements(self) -> None:
        try:
            # deferred: the viewer is optional
            from nerfstudio.viewer.viewer_elements import ViewerCheckbox
        except Exception:  # pragma: no cover - viewer extras missing
            return

        def toggle(element) -> None:
            self.wrap_state.enabled = bool(element.value)

        self.viewer_sticker_on = ViewerCheckbox(
            "Sticker on", True, cb_hook=toggle, hint="Render with (on) or without (off) the ownership sticker"
        )

    # ------------------------------------------------------------------------------------------ structure
    def rendering_fields(self) -> Iterator[Tuple[str, nn.Module]]:
        """Density fields that produce rendered samples (outermost Field modules of the base)."""
        taken: List[str] = []
        for name, module in self.base.named_modules():
            if not isinstance(module, Field) or not name:
                continue
            if any(name.startswith(t + ".") for t in taken):
                continue
            if name.startswith("proposal_networks") and not self.config.wrap_proposal_networks:
                continue
            taken.append(name)
            yield name, module

    @property
    def final_wrap(self) -> DensityWrap:
        """The field whose samples make the final image (vanilla-nerf: the fine field)."""
        return self.wraps[-1]

    def train(self, mode: bool = True):
        super().train(mode)
        self.base.eval()  # deterministic samples, no camera-optimizer or random-background behaviour
        return self

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        return {"sticker": list(self.sticker.parameters()) + [g.log_beta for g in self.gates.values()]}

    def get_training_callbacks(self, training_callback_attributes):
        return []  # the base is frozen: none of its schedules apply

    @property
    def calibrated(self) -> bool:
        return all(bool(g.calibrated) for g in self.gates.values())

    @torch.no_grad()
    def reseed_sticker(self, seed: int) -> None:
        """Re-initialise the sticker from ``seed`` in place (its parameters stay the ones the optimizers hold)."""
        fresh = seeded_sticker(sticker_config(self.config), seed)
        for mine, new in zip(self.sticker.parameters(), fresh.parameters()):
            mine.copy_(new.to(mine))
        self.sticker_seed = int(seed)

    def set_message(self, message: Tensor) -> None:
        self.message.copy_(message.to(self.message))

    # ------------------------------------------------------------------------------------------ shared form
    SECRET_PREFIXES = ("sticker.", "message")
    """State entries that never leave the owner: the per-bit sticker and the message (they go into the owner key)."""

    def shareable_state_dict(self, prefix: str = "") -> Dict[str, Tensor]:
        """This model's state as a shared run holds it: the sticker folded with the owner's message, and no sticker
        with a message input and no message bits."""
        state = dict(self.state_dict(prefix=prefix))
        if not bool(self.folded):
            for k, v in self.sticker.fold(self.message).items():
                state[prefix + "folded_sticker." + k] = v
            state[prefix + "folded"] = torch.tensor(True)
        return {k: v for k, v in state.items() if not any(k[len(prefix) :].startswith(s) for s in self.SECRET_PREFIXES)}

    def unfold(self, sticker_state: Dict[str, Tensor], message: Tensor, sticker_seed: int = -1) -> None:
        """Back from the shared form to the trainable sticker (resuming a run): the key's sticker and message."""
        self.sticker.load_state_dict(sticker_state, strict=True)
        self.sticker_seed = sticker_seed
        self.set_message(message)
        self.folded.fill_(False)

    @staticmethod
    def _fill_unshared(
        module, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ) -> None:
        """Load hook: a shared state has no per-bit sticker and message (filled with this model's own, unused in the
        folded form); a run written before the shared form has no folded sticker (filled, ``folded`` False)."""
        if prefix + "folded" not in state_dict:
            if prefix + "message" in state_dict:  # the older, unfolded layout
                for k, v in module.folded_sticker.state_dict().items():
                    state_dict.setdefault(prefix + "folded_sticker." + k, v)
                state_dict[prefix + "folded"] = torch.tensor(False)
            return
        if bool(state_dict[prefix + "folded"]):
            for k, v in module.sticker.state_dict().items():
                state_dict.setdefault(prefix + "sticker." + k, v)
            state_dict.setdefault(prefix + "message", module.message)

    @contextmanager
    def sticker_enabled(self, enabled: bool):
        old = self.wrap_state.enabled
        self.wrap_state.enabled = enabled
        try:
            yield
        finally:
            self.wrap_state.enabled = old

    # ------------------------------------------------------------------------------------------ rendering
    def get_outputs(self, ray_bundle: RayBundle) -> Dict[str, Any]:
        folded = bool(self.folded)
        self.wrap_state.message = None if folded else self.message
        self.wrap_state.folded = self.folded_sticker if folded else None
        self.wrap_state.record = True
        try:
            with self.final_pass() as masks:
                outputs = self.base.forward(ray_bundle)
        finally:
            self.wrap_state.record = False
        if "rgb" not in outputs and isinstance(outputs.get("rgb_fine"), Tensor):
            outputs["rgb"] = outputs["rgb_fine"]  # vanilla-nerf names its final image rgb_fine
        delta = self.final_wrap.last.get("delta") if self.wrap_state.enabled else None
        mask = masks[-1] if masks else None
        if delta is not None and isinstance(mask, Tensor) and mask.dtype == torch.bool and not bool(mask.all()):
            if delta.shape[0] == int(mask.sum()):
                full = delta.new_zeros((mask.shape[0], *delta.shape[1:]))
                full[mask] = delta
                delta = full
            else:
                delta = None  # the final field evaluated no density (the record is an earlier call's)
        rgb = outputs.get("rgb")
        if isinstance(rgb, Tensor):
            if delta is not None and delta.shape[0] == rgb.shape[0]:
                # Sticker magnitude along each ray, in units of the gate's density scale.
                outputs["sticker_delta"] = delta.abs().sum(dim=-2) / self.final_wrap.gate.scale
            else:
                outputs["sticker_delta"] = torch.zeros_like(rgb[..., :1])
        self.final_wrap.last = {}
        return outputs

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        return self.base.get_metrics_dict(outputs, batch)

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        return self.base.get_loss_dict(outputs, batch, metrics_dict)

    def get_image_metrics_and_images(self, outputs, batch):
        return self.base.get_image_metrics_and_images(outputs, batch)

    @contextmanager
    def final_pass(self) -> Iterator[List[Any]]:
        """While the base renders inside this block, its final field's ``forward`` calls are the *final pass* (the
        only density the sticker marks with ``mark_sampling_passes=False``); yields the ``mask`` argument of each
        call (TensoRF's final field evaluates density only on the rays of a mask: the recorded per-sample delta is
        put back on all rays with it)."""
        fld = self.final_wrap.field
        inner = fld.__dict__.get("forward")  # an instance override (capture_final_samples) or None
        call = inner if inner is not None else type(fld).forward.__get__(fld)
        masks: List[Any] = []

        def forward(ray_samples, *args, **kwargs):
            masks.append(kwargs.get("mask"))
            self.wrap_state.in_final = True
            try:
                return call(ray_samples, *args, **kwargs)
            finally:
                self.wrap_state.in_final = False

        object.__setattr__(fld, "forward", forward)
        try:
            yield masks
        finally:
            if inner is not None:
                object.__setattr__(fld, "forward", inner)
            else:
                del fld.__dict__["forward"]

    # ------------------------------------------------------------------------------------------ capture
    @contextmanager
    def capture_final_samples(self, message: Optional[Tensor] = None):
        """Record (positions, deltas, base density, rgb) of the final field's forward calls.

        Sticker off by default. With ``message`` the model renders with the sticker of that message on, so the
        samples are the ones the *marked* model draws (TensoRF and vanilla-nerf place their fine samples by the
        wrapped density), while the recorded density and rgb are still the base's at those samples (the final
        field is evaluated a second time with the sticker off).
        """
        fld = self.final_wrap.field
        records: List[Dict[str, Tensor]] = []
        original_forward = fld.forward

        def forward(ray_samples, *args, **kwargs):
            out = original_forward(ray_samples, *args, **kwargs)
            base = out
            if message is not None:
                with self.sticker_enabled(False):
                    base = original_forward(ray_samples, *args, **kwargs)
            records.append(
                {
                    "positions": ray_samples.frustums.get_positions().detach(),
                    "deltas": ray_samples.deltas.detach(),
                    "density": base[FieldHeadNames.DENSITY].detach(),
                    "rgb": base[FieldHeadNames.RGB].detach(),
                }
            )
            return out

        if message is not None and bool(self.folded):
            raise GStickerError(
                "this run holds the shared (folded) sticker and no message; render another message "
                "with the owner key's sticker (gsticker_plugin.decoders.reference.load_base_reference)"
            )
        old_message = None if message is None else self.message.clone()
        object.__setattr__(fld, "forward", forward)
        try:
            if message is not None:
                self.set_message(message)
            with self.sticker_enabled(message is not None):
                yield records
        finally:
            del fld.__dict__["forward"]
            if old_message is not None:
                self.set_message(old_message)

    def background_color(self) -> Background:
        """The base's background (any Nerfstudio setting; see :class:`gsticker_plugin.background.Background`)."""
        return background_of(self.base)


def shareable_state(model: nn.Module) -> Dict[str, Tensor]:
    """``model``'s state as a shared run holds it: every GeometrySticker model inside it (a recolor run wraps one) in
    its folded form, without message or per-bit sticker."""
    state = dict(model.state_dict())
    for name, m in model.named_modules():
        if isinstance(m, GeometryStickerModel):
            prefix = name + "." if name else ""
            state = {k: v for k, v in state.items() if not k.startswith(prefix)}
            state.update(m.shareable_state_dict(prefix=prefix))
    return state


def sticker_config(cfg: GeometryStickerModelConfig) -> Dict[str, Any]:
    """The sticker's shape as the key's geometry reference records it."""
    return {
        "kind": cfg.sticker_kind,
        "num_bits": int(cfg.num_bits),
        "num_frequencies": int(cfg.num_frequencies),
        "hidden_dim": int(cfg.sticker_hidden_dim),
        "num_layers": int(cfg.sticker_num_layers),
        "init_scale": float(cfg.sticker_init_scale),
    }


def seeded_sticker(sc: Dict[str, Any], seed: Optional[int] = None) -> Sticker:
    """A :class:`Sticker` of shape ``sc`` (:func:`sticker_config`) initialised from ``seed`` alone (the global
    generators are left as they were); ``seed`` None: the global generator's next draws."""

    def build() -> Sticker:
        return Sticker(
            int(sc["num_bits"]),
            int(sc["num_frequencies"]),
            int(sc["hidden_dim"]),
            int(sc["num_layers"]),
            float(sc.get("init_scale", 0.5)),
            sc["kind"],
        )

    if seed is None:
        return build()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return build()


def geometry_reference(model: "GeometryStickerModel") -> Dict[str, Any]:
    """The key's geometry reference: the sticker and gates the informed decoders rebuild on the owner's base."""
    cfg = model.config
    return {
        "version": GEOMETRY_REFERENCE_VERSION,
        "sticker_config": sticker_config(cfg),
        "gate_threshold": float(cfg.gate_threshold),
        "wrap_proposal_networks": bool(cfg.wrap_proposal_networks),
        "mark_sampling_passes": bool(cfg.mark_sampling_passes),
        "sticker_state": {k: v.detach().cpu().clone() for k, v in model.sticker.state_dict().items()},
        "sticker_seed": int(model.sticker_seed),
        "gates_state": {k: v.detach().cpu().clone() for k, v in model.gates.state_dict().items()},
        "fields": [w.name for w in model.wraps],
        "final_field": model.final_wrap.name,
        "aabb": {w.name: w.aabb.detach().cpu().float().clone() for w in model.wraps},
        "null": None,
    }


def folds_to(
    geometry: Dict[str, Any], message: Tensor, pipeline_state: Dict[str, Any], prefix: str = "_model."
) -> bool:
    """Whether a key's sticker (its geometry reference) with ``message`` folds to the shared sticker of a run's
    checkpoint ``pipeline_state``: the key belongs to that run."""
    shared = {
        k[len(prefix + "folded_sticker.") :]: v
        for k, v in pipeline_state.items()
        if k.startswith(prefix + "folded_sticker.")
    }
    try:
        sticker = seeded_sticker(geometry["sticker_config"], 0)
        sticker.load_state_dict(geometry["sticker_state"], strict=True)
        folded = sticker.fold(message)
    except (KeyError, TypeError, ValueError, RuntimeError):
        return False
    return set(folded) == set(shared) and all(
        folded[k].shape == shared[k].shape and torch.allclose(folded[k].float(), shared[k].float(), atol=1e-6)
        for k in folded
    )
