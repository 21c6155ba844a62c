"""Model-level recoloring: a companion Nerfstudio model that wraps any run and edits its fields' color output.

:class:`RecolorModel` rebuilds the wrapped run's model (a stock nerfacto / vanilla-nerf / TensoRF run, a
geometrysticker run, or another recolor run) from the config recorded in its own config, keeps it frozen in
eval mode as ``self.inner``, and replaces ``get_outputs`` on the *instances* of the inner model's color fields
so that the per-sample RGB (``FieldHeadNames.RGB``) is re-mixed with the edited palette and/or hue-rotated
*before* compositing. Density, the samplers and the proposal networks are untouched, so depth, accumulation
and weights are bit-identical to the wrapped run's.

The palette (source and edited colors), the softness and the hue shift are buffers (saved in the checkpoint)
and recorded in the config (so the viewer's color controls start at the saved edit). In ``ns-viewer`` each
palette entry is an RGB color control and the hue shift a slider; changing them re-renders live.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple, Type

import torch
import tyro
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.base_field import Field
from nerfstudio.models.base_model import Model, ModelConfig
from torch import Tensor, nn
from torch.nn import Parameter

from gsticker_plugin.errors import GStickerError
from gsticker_plugin.recolor import palette as P

# ---------------------------------------------------------------------------------------------- color fields


def _density_only(module: nn.Module) -> bool:
    try:
        # deferred: optional field class
        from nerfstudio.fields.density_fields import HashMLPDensityField
    except Exception:  # pragma: no cover
        return False
    return isinstance(module, HashMLPDensityField)


def color_fields(model: nn.Module) -> List[Tuple[str, nn.Module]]:
    """The outermost Field modules of ``model`` that output color (proposal / density-only fields excluded)."""
    taken: List[str] = []
    out: List[Tuple[str, nn.Module]] = []
    for name, module in model.named_modules():
        if not isinstance(module, Field) or not name:
            continue
        if any(name.startswith(t + ".") for t in taken):
            continue
        taken.append(name)
        if _density_only(module) or "proposal" in name:
            continue
        if type(module).get_outputs is Field.get_outputs:  # abstract: no color head
            continue
        out.append((name, module))
    return out


def require_color_fields(model: nn.Module) -> List[Tuple[str, nn.Module]]:
    fields = color_fields(model)
    if not fields:
        raise GStickerError(
            f"{type(model).__name__} has no field with a separable color output (no Nerfstudio Field "
            "with an RGB head); recolor a NeRF-style run (nerfacto, vanilla-nerf, tensorf, instant-ngp, "
            "or a geometrysticker run of one)"
        )
    return fields


class ColorWrap:
    """Installs ``transform(rgb)`` on the per-sample RGB that a field instance's ``get_outputs`` returns; removable."""

    def __init__(self, fld: nn.Module, transform: Callable[[Tensor], Tensor]) -> None:
        self.field = fld
        self.transform = transform
        self.previous = fld.__dict__.get("get_outputs")  # an earlier instance override, if any
        self.original = fld.get_outputs
        object.__setattr__(fld, "get_outputs", self.get_outputs)

    def get_outputs(self, ray_samples, *args, **kwargs):
        out = self.original(ray_samples, *args, **kwargs)
        if isinstance(out, dict):
            rgb = out.get(FieldHeadNames.RGB)
            if isinstance(rgb, Tensor):
                out = dict(out)
                out[FieldHeadNames.RGB] = self.transform(rgb)
        elif isinstance(out, Tensor) and out.shape[-1] == 3:  # TensoRF's get_outputs returns the rgb tensor
            out = self.transform(out)
        return out

    def remove(self) -> None:
        if self.field.__dict__.get("get_outputs") == self.get_outputs:
            if self.previous is not None:
                object.__setattr__(self.field, "get_outputs", self.previous)
            else:
                del self.field.__dict__["get_outputs"]


def unwrap(model: nn.Module) -> nn.Module:
    """The innermost stock model (through recolor and geometrysticker wrappers)."""
    while True:
        nxt = getattr(model, "inner", None) if isinstance(model, RecolorModel) else getattr(model, "base", None)
        if not isinstance(nxt, Model):
            return model
        model = nxt


# ---------------------------------------------------------------------------------------------- model


@dataclass
class RecolorModelConfig(ModelConfig):
    """A wrapped run with its fields' per-sample color re-mixed by an edited palette and/or hue-rotated."""

    _target: Type = field(default_factory=lambda: RecolorModel)
    enable_collider: bool = False
    """The wrapped model applies its own collider."""
    inner_model: tyro.conf.Suppress[Optional[Any]] = None
    """The wrapped run's ModelConfig (copied from its config.yml by ns-recolor; not a CLI option)."""
    palette_source: List[str] = field(default_factory=list)
    """The extracted palette (hex), in index order."""
    palette_target: List[str] = field(default_factory=list)
    """The edited palette (hex); entries equal to the source are unchanged."""
    softness: float = 5.0
    """Width (Lab dE) of the soft assignment of sample colors to palette entries."""
    hue_shift: float = 0.0
    """HSV hue rotation applied to every sample's color, in turns (-0.5..0.5)."""
    wrapped_run: tyro.conf.Suppress[Dict[str, Any]] = field(default_factory=dict)
    """Provenance: the wrapped run's method, config, checkpoint and its sha256 (filled in by ns-recolor)."""


class RecolorModel(Model):
    """Frozen wrapped model; per-sample color edits on its color fields (density untouched)."""

    config: RecolorModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()
        if self.config.inner_model is None:
            raise GStickerError(
                "this recolor config wraps no model; make recolored runs with "
                "`ns-recolor palette|hue --load-config RUN/config.yml --output-dir OUT`"
            )
        self.inner: Model = self.config.inner_model.setup(
            scene_box=self.scene_box, num_train_data=self.num_train_data, **self.kwargs
        )
        self.inner.requires_grad_(False)
        self.inner.eval()
        src = [P.parse_color(c) for c in self.config.palette_source]
        tgt = [P.parse_color(c) for c in self.config.palette_target] or list(src)
        if len(tgt) != len(src):
            raise GStickerError(
                f"palette_target has {len(tgt)} entries but palette_source {len(src)}; recreate the run with ns-recolor"
            )
        self.register_buffer("palette_source", torch.tensor(src, dtype=torch.float32).reshape(-1, 3))
        self.register_buffer("palette_target", torch.tensor(tgt, dtype=torch.float32).reshape(-1, 3))
        self.register_buffer("softness", torch.tensor(float(self.config.softness)))
        self.register_buffer("hue_shift", torch.tensor(float(self.config.hue_shift)))
        self.recolor_enabled = True
        self.color_wraps = [ColorWrap(f, self.transform) for _, f in require_color_fields(self.inner)]
        self._viewer_elements()

    # ------------------------------------------------------------------------------------------ the edit
    def transform(self, rgb: Tensor) -> Tensor:
        """Per-sample color edit: palette re-mix, then hue rotation."""
        if not self.recolor_enabled:
            return rgb
        out = rgb
        if self.palette_source.shape[0] and not torch.equal(self.palette_source, self.palette_target):
            src = P.rgb_to_lab(self.palette_source.to(rgb))
            tgt = P.rgb_to_lab(self.palette_target.to(rgb))
            out = P.recolor(out, src, tgt, self.softness.to(rgb))
        shift = float(self.hue_shift)
        if shift != 0.0:
            out = P.hue_rotate(out, shift).to(rgb.dtype)
        return out

    def set_target(self, index: int, rgb) -> None:
        with torch.no_grad():
            self.palette_target[index] = torch.as_tensor(rgb, dtype=torch.float32).to(self.palette_target)

    def _viewer_elements(self) -> None:
        try:
            # deferred: the viewer is optional
            from nerfstudio.viewer.viewer_elements import ViewerCheckbox, ViewerRGB, ViewerSlider
        except Exception:  # pragma: no cover - viewer extras missing
            return

        def on_color(i: int):
            def cb(element) -> None:
                self.set_target(i, [c / 255.0 for c in element.value])

            return cb

        for i in range(self.palette_source.shape[0]):
            default = tuple(int(round(float(c) * 255)) for c in self.palette_target[i])
            setattr(
                self,
                f"viewer_palette_{i}",
                ViewerRGB(
                    f"Palette {i} (was {P.to_hex(self.palette_source[i])})",
                    default,
                    cb_hook=on_color(i),
                    hint="Edited color of this palette entry; the render re-mixes every sample's color with it",
                ),
            )

        def on_hue(element) -> None:
            self.hue_shift.fill_(float(element.value))

        def on_softness(element) -> None:
            self.softness.fill_(max(float(element.value), 0.5))

        def on_enabled(element) -> None:
            self.recolor_enabled = bool(element.value)

        self.viewer_recolor_on = ViewerCheckbox(
            "Recolor on", True, cb_hook=on_enabled, hint="Render with (on) or without (off) the color edit"
        )
        self.viewer_recolor_hue = ViewerSlider(
            "Hue shift (turns)",
            float(self.config.hue_shift),
            -0.5,
            0.5,
            0.01,
            cb_hook=on_hue,
            hint="HSV hue rotation of every sample's color",
        )
        if self.palette_source.shape[0]:
            self.viewer_recolor_softness = ViewerSlider(
                "Palette softness (dE)",
                float(self.config.softness),
                1.0,
                40.0,
                0.5,
                cb_hook=on_softness,
                hint="Width of the soft assignment of colors to palette entries",
            )

    # ------------------------------------------------------------------------------------------ plumbing
    def train(self, mode: bool = True):
        super().train(mode)
        self.inner.eval()
        return self

    def update_to_step(self, step: int) -> None:
        self.inner.update_to_step(step)  # e.g. TensoRF's grid resolution at the saved step

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        return {}

    def get_training_callbacks(self, training_callback_attributes):
        return []

    def get_outputs(self, ray_bundle: RayBundle) -> Dict[str, Any]:
        outputs = self.inner.forward(ray_bundle)
        if "rgb" not in outputs and isinstance(outputs.get("rgb_fine"), Tensor):
            outputs["rgb"] = outputs["rgb_fine"]  # vanilla-nerf names its final image rgb_fine
        return outputs

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        return self.inner.get_metrics_dict(outputs, batch)

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        return self.inner.get_loss_dict(outputs, batch, metrics_dict)

    def get_image_metrics_and_images(self, outputs, batch):
        return self.inner.get_image_metrics_and_images(outputs, batch)

    # The geometrysticker interface of a wrapped geometrysticker run (verification and evaluation tools use it).
    _DELEGATED = frozenset(
        {
            "sticker_enabled",
            "message",
            "calibrated",
            "background_color",
            "sticker",
            "gates",
            "final_wrap",
            "wraps",
            "wrap_state",
            "capture_final_samples",
            "rendering_fields",
        }
    )

    def __getattr__(self, name: str):
        try:
            return super().__getattr__(name)
        except AttributeError:
            inner = self.__dict__.get("_modules", {}).get("inner") if name in self._DELEGATED else None
            if inner is not None:
                return getattr(inner, name)
            raise

    def edit_summary(self) -> str:
        edits = [
            f"{i}: {P.to_hex(s)} -> {P.to_hex(t)}"
            for i, (s, t) in enumerate(zip(self.palette_source.tolist(), self.palette_target.tolist()))
            if s != t
        ]
        parts = []
        if edits:
            parts.append("palette " + ", ".join(edits))
        if float(self.hue_shift) != 0.0:
            parts.append(f"hue {float(self.hue_shift):+.3f} turns")
        return "; ".join(parts) or "no edit"


def iter_models(model: nn.Module) -> Iterator[nn.Module]:
    yield model
    while True:
        nxt = getattr(model, "inner", None) if isinstance(model, RecolorModel) else getattr(model, "base", None)
        if not isinstance(nxt, Model):
            return
        model = nxt
        yield model


# ---------------------------------------------------------------------------------------------- trainer


from nerfstudio.engine.trainer import Trainer, TrainerConfig  # noqa: E402

from gsticker_plugin.trainer import exit_with_error


@dataclass
class RecolorTrainerConfig(TrainerConfig):
    """Recolored runs are made by ns-recolor, not trained."""

    _target: Type = field(default_factory=lambda: RecolorTrainer)


class RecolorTrainer(Trainer):
    def setup(self, test_mode="val") -> None:
        exit_with_error(
            GStickerError(
                f"{self.config.method_name} runs are written by ns-recolor, there is nothing to train; run "
                "`ns-recolor palette|hue --load-config RUN/config.yml --output-dir OUT` instead"
            )
        )
