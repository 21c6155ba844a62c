"""The shared run: a stock run of the base's own method whose field carries the owner's message (the field mark).

:func:`mark_base` loads the owner's base run strictly, adds the signed per-bit patterns to its density field's hash
table (``T~ = T + a sum_k s_k P_k / sqrt(K)``, :mod:`gsticker_plugin.fieldmark`) and writes the result as a new run of
the base's method: the base's config.yml (relocated) and its checkpoint with that one tensor replaced. Nothing else
changes: the same method, the same state-dict keys and shapes, no gsticker module, so stock ``ns-viewer`` and
``ns-render`` open it and there is nothing to switch off. What the owner keeps (the message, the patterns' secret
seed, the amplitude, the levels and the base's reference) goes into the owner key's ``field_mark`` and ``base``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple

import torch
import yaml
from torch import Tensor

from gsticker_plugin import fieldmark as FM
from gsticker_plugin import metrics, runs
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.key import file_sha256, plain

DEFAULT_LEVELS: Tuple[int, ...] = (0, 1, 2, 3)
"""Hash levels the per-bit patterns live on: the coarse ones, so each bit spreads over the whole object."""
DEFAULT_AMPLITUDE = 0.01
"""Pattern amplitude on a hash table: on the lego100 nerfacto-small base, 48/48 bits on 25 test views at 50.3 dB
render PSNR vs the base (docs/experiments/bench-fieldmark.md)."""

DEFAULT_PLANES_AMPLITUDE = 0.03
"""Pattern amplitude on TensoRF's density planes (their entries spread ~0.34 on the lego100 tensorf-small base)."""


def default_amplitude(host: str) -> float:
    """The amplitude a host's mark gets unless one is given."""
    return DEFAULT_PLANES_AMPLITUDE if host == "planes" else DEFAULT_AMPLITUDE


@dataclass
class SharedRun:
    """A marked run ready to be written (:meth:`write`) and what the owner key records of it."""

    config: Any
    """The base's TrainerConfig relocated to :attr:`run_dir`."""
    state: Dict[str, Any]
    """The base's checkpoint with the marked table."""
    run_dir: Path
    field_mark: Dict[str, Any]
    base: Dict[str, Any]
    psnr_vs_base: float
    """Mean render PSNR of the shared run vs the base over the measured training views (dB)."""

    def write(self) -> Path:
        """Write the run (:func:`write_run`); returns its config.yml."""
        if (self.run_dir / "config.yml").exists():
            raise GStickerError(f"{self.run_dir} already holds a run; pass another --timestamp or --output-dir")
        return write_run(self.config, self.state, self.run_dir)


def table_name(model) -> str:
    """The pipeline state-dict name of the tensor the mark goes into (``_model.`` + its parameter name): the density
    hash table, or TensoRF's density planes."""
    table = FM.marked_parameter(model.field)
    for name, p in model.named_parameters():
        if p is table:
            return "_model." + name
    raise GStickerError(f"{type(model).__name__}'s density table is not one of its parameters")


def stock_method_name(config) -> str:
    """The run's method name when Nerfstudio itself defines it, else the first of Nerfstudio's own methods with the
    same model class (a base trained with one of gsticker's presets is shared as that method: stock tools look the
    name up, and a recipient has no gsticker)."""
    from nerfstudio.configs.method_configs import method_configs

    if config.method_name in method_configs:
        return config.method_name
    model_type = type(config.pipeline.model)
    for name, cfg in method_configs.items():
        if type(getattr(getattr(cfg, "pipeline", None), "model", None)) is model_type:
            return name
    raise GStickerError(
        f"no Nerfstudio method builds a {model_type.__name__} (the base's method {config.method_name}); the shared "
        "run must open without gsticker: train the base with a stock method"
    )


def as_stock_method(config, method: str) -> None:
    """Make ``config`` (a base's TrainerConfig) a run of Nerfstudio's ``method``: its name, and its data manager
    config of the class that method uses (stock loaders set the data manager's target from the method's, so the
    config must be of the class that target takes), every shared field kept."""
    from nerfstudio.configs.method_configs import method_configs

    config.method_name = method
    want = type(method_configs[method].pipeline.datamanager)
    old = config.pipeline.datamanager
    if type(old) is not want:
        new = want()
        names = {f.name for f in dataclasses.fields(want)} - {"_target"}
        for f in dataclasses.fields(old):
            if f.name in names:
                setattr(new, f.name, getattr(old, f.name))
        config.pipeline.datamanager = new


def marked_pipeline_state(
    pipeline_state: Dict[str, Tensor], name: str, pats: Tensor, message: Tensor, amplitude: float
) -> Dict[str, Tensor]:
    """A copy of a checkpoint's pipeline state with the table ``name`` carrying ``message`` (nothing else changed)."""
    out = dict(pipeline_state)
    out[name] = FM.marked_table(pipeline_state[name], pats, FM.signs_of(message), amplitude).detach().clone()
    return out


def write_run(config, state: Dict[str, Any], run_dir: Path) -> Path:
    """Write ``config`` (already relocated to ``run_dir``) and ``state`` as a Nerfstudio run: ``config.yml`` and
    ``nerfstudio_models/step-N.ckpt`` (each written to a temporary name first). Returns the config path."""
    models = run_dir / "nerfstudio_models"
    models.mkdir(parents=True, exist_ok=True)
    ckpt = models / f"step-{int(state['step']):09d}.ckpt"
    torch.save(state, ckpt.with_suffix(".ckpt.tmp"))
    os.replace(ckpt.with_suffix(".ckpt.tmp"), ckpt)
    cfg = run_dir / "config.yml"
    cfg.with_suffix(".yml.tmp").write_text(yaml.dump(config))
    os.replace(cfg.with_suffix(".yml.tmp"), cfg)
    return cfg


def mark_base(
    base_config: Path,
    checkpoint: Path,
    message: Tensor,
    pattern_seed: int,
    output_dir: Path,
    experiment_name: str,
    timestamp: str,
    amplitude: Optional[float] = None,
    levels: Sequence[int] = DEFAULT_LEVELS,
    psnr_views: int = 4,
    data: Optional[Path] = None,
    device: Optional[torch.device] = None,
) -> SharedRun:
    """The shared run of ``base_config`` (its checkpoint ``checkpoint``) marked with ``message``, to be written as
    ``output_dir/experiment_name/METHOD/timestamp`` (``METHOD`` the base's, Nerfstudio's layout), with its render
    PSNR vs the base measured on ``psnr_views`` evenly spaced training cameras. Nothing is written here."""
    device = device or torch.device("cpu")
    with contextlib.redirect_stdout(sys.stderr):
        config, pipeline, state = runs.load_run_at(base_config, checkpoint, data=data, device=device)
    shared = runs.load_run_config(base_config)
    if data is not None:
        shared.pipeline.datamanager.data = shared.pipeline.datamanager.dataparser.data = Path(data)
    method = stock_method_name(config)
    run_dir = runs.relocate(shared, output_dir, experiment_name, method, timestamp)
    as_stock_method(shared, method)
    if (run_dir / "config.yml").exists():
        raise GStickerError(f"{run_dir} already holds a run; pass another --timestamp or --output-dir")
    model = pipeline.model
    host = FM.host_of(model.field)
    amplitude = default_amplitude(host) if amplitude is None else float(amplitude)
    name = table_name(model)
    if host == "planes":
        mark = {"host": "planes", "grid": FM.PLANES_GRID, "levels": [], "init_scale": 0.0}
    else:
        init_scale = float(FM.parts(model.field)[0].hash_init_scale)
        mark = {"levels": [int(lv) for lv in levels], "init_scale": init_scale}
    mark.update(table=name, pattern_seed=int(pattern_seed), amplitude=amplitude)
    pats = FM.key_patterns(model.field, mark, int(message.numel()))
    # numpy scalars (the base's optimizer state) become Python ones: stock torch >= 2.6 loads the run as it is
    state = plain({**state, "pipeline": marked_pipeline_state(state["pipeline"], name, pats, message, amplitude)})
    cams = pipeline.datamanager.train_dataset.cameras
    picks = [int(round(i * (len(cams) - 1) / max(1, psnr_views - 1))) for i in range(psnr_views)]
    psnrs = []
    param = FM.marked_parameter(model.field)
    saved = param.data
    for i in picks:
        with torch.no_grad():
            clean = runs.final_rgb(model.get_outputs_for_camera(cams[i : i + 1].to(device)))
            param.data = state["pipeline"][name].to(saved)
            try:
                marked = runs.final_rgb(model.get_outputs_for_camera(cams[i : i + 1].to(device)))
            finally:
                param.data = saved
        psnrs.append(float(metrics.psnr(marked.permute(2, 0, 1), clean.permute(2, 0, 1))))
    return SharedRun(
        config=shared,
        state=state,
        run_dir=run_dir,
        field_mark=mark,
        base={
            "method": config.method_name,
            "shared_method": method,
            "model": type(config.pipeline.model).__name__,
            "config": str(Path(base_config).resolve()),
            "checkpoint": str(Path(checkpoint).resolve()),
            "checkpoint_sha256": file_sha256(checkpoint),
        },
        psnr_vs_base=sum(psnrs) / len(psnrs),
    )
