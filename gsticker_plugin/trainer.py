"""Trainer for ``ns-train geometrysticker``: loads a foreign base run strictly, saves without the secret heads.

* ``--load-checkpoint BASE/nerfstudio_models/step-N.ckpt`` (or ``--load-dir``) of a *foreign* run (any stock
  method): its config.yml rebuilds the base model and data settings, its weights are loaded strictly into
  the frozen base, and training starts at step 0 of our own schedule.
* The same flags pointing at one of *our* runs resume it (sticker, gates and optimizers from the
  checkpoint, heads and their optimizer from the owner key).
* At every save the owner key (default: the per-user keys folder, :func:`gsticker_plugin.key.default_key_path`;
  signed with the owner identity) is written and read back first, then the checkpoint, which holds what a
  recipient may see: the folded sticker, no message, no extractor/classifier, no optimizer state of the sticker.
  config.yml never keeps an owner ID, message or key path, not even when setup fails. A key path that cannot be
  written, or lies inside the run folder, is refused before training; a resume takes only the run's own key.
* Several processes (``--machine.num-devices N``): rank 0 draws the message and the others take it; the optimizers
  average the gradients over the ranks before each step; only rank 0 writes config.yml, checkpoints and the key.
"""

from __future__ import annotations

import contextlib
import copy
import os
import secrets
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Literal, Optional, Tuple, Type

import torch
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import comms
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.rich_utils import CONSOLE
from torch.nn import Parameter

from gsticker_plugin import runs
from gsticker_plugin.errors import GStickerError, print_error
from gsticker_plugin.key import (
    KEY_SUFFIX,
    OwnerKey,
    bits_to_str,
    commitment,
    default_key_path,
    file_sha256,
    owner_identity,
)
from gsticker_plugin.model import folds_to
from gsticker_plugin.pipeline import (
    GeometryStickerPipeline,
    GeometryStickerPipelineConfig,
)
from gsticker_plugin.runs import copy_datamanager
from gsticker_plugin.shared import SharedRun, mark_base


@dataclass
class GeometryStickerTrainerConfig(TrainerConfig):
    """ns-train geometrysticker: stick an owner message onto a trained model's geometry."""

    _target: Type = field(default_factory=lambda: GeometryStickerTrainer)
    pipeline: GeometryStickerPipelineConfig = field(default_factory=GeometryStickerPipelineConfig)

    def set_experiment_name(self) -> None:
        """Unless ``--experiment-name`` or ``--data`` says otherwise, the base run's experiment name: the shared run
        goes beside the base (``outputs/EXPERIMENT/METHOD/TIMESTAMP``), not under "unnamed"."""
        if self.experiment_name is None and self.data is None and self.pipeline.datamanager.data is None:
            try:
                ckpt = runs.resolve_checkpoint(self.load_checkpoint, self.load_dir, self.load_step)
                if ckpt is not None:
                    self.experiment_name = runs.run_config_path(ckpt).parent.parent.parent.name
            except GStickerError:
                pass  # setup() names the problem in one line
        super().set_experiment_name()


def step_key_path(key_path: Path, step: int) -> Path:
    """The owner key of checkpoint ``step`` (written beside the key with --save-only-latest-checkpoint False)."""
    return Path(key_path).with_name(f"{Path(key_path).stem}.step-{step:09d}{Path(key_path).suffix}")


OWNER_INPUTS = {"owner_id": "", "message": None, "key_path": None, "sticker_seed": None, "pattern_seed": None}
"""The pipeline-config fields that hold the owner's secrets, with the values a shared config.yml holds instead."""


def strip_owner_inputs(pipeline_config) -> None:
    """Replace the owner's secrets in a pipeline config by :data:`OWNER_INPUTS` (what config.yml may record)."""
    for name, value in OWNER_INPUTS.items():
        setattr(pipeline_config, name, value)


def check_key_path(path: Path, run_dir: Path) -> None:
    """Refuse, before any training, an owner key path that cannot be written or that lies inside the run folder (what
    is shared)."""
    path = Path(path)
    if path.is_dir():
        raise GStickerError(
            f"--pipeline.key-path {path} is a folder; pass a file path such as {path / ('owner' + KEY_SUFFIX)}"
        )
    resolved = path.expanduser().resolve()
    if resolved == Path(run_dir).resolve() or Path(run_dir).resolve() in resolved.parents:
        raise GStickerError(
            f"--pipeline.key-path {path} lies inside the run folder {run_dir}, which is what you share; "
            "pass a path outside it (default: the per-user keys folder)"
        )
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        probe = tempfile.NamedTemporaryFile(dir=path.parent, prefix=path.name + ".", suffix=".probe", delete=True)
        probe.close()
    except OSError as e:
        raise GStickerError(
            f"cannot write the owner key at {path} ({e.strerror or type(e).__name__}); pass --pipeline.key-path "
            "with a writable file path"
        ) from None


def write_key(key: OwnerKey, path: Path, backup: bool = True) -> None:
    """Write ``key`` atomically (the previous file kept as ``KEY.gskey.bak`` with ``backup``), read it back and check
    it is the same key (message and commitment)."""
    path = Path(path)
    if backup and path.is_file():
        shutil.copy2(path, path.with_name(path.name + ".bak"))
    key.save(path)
    back = OwnerKey.load(path)
    if not torch.equal(back.message, key.message.cpu().long()) or commitment(back) != commitment(key):
        raise GStickerError(f"the owner key written to {path} does not read back; check the disk and retry")


def resume_key(ckpt: Path, run_cfg, key_path: Optional[Path]) -> Tuple[Path, OwnerKey]:
    """The owner key of the run being resumed: ``key_path``, else the key's default place for that run, else (runs
    written before the keys folder) beside the run folder; each with its ``.bak``. A key is taken only when its
    sticker and message fold to the run's shared sticker (it belongs to this run)."""
    run_dir = ckpt.resolve().parent.parent
    places = (
        [Path(key_path)]
        if key_path is not None
        else [
            default_key_path(run_cfg.experiment_name, run_cfg.method_name, run_cfg.timestamp),
            run_dir.with_name(run_dir.name + KEY_SUFFIX),
        ]
    )
    existing = [p for place in places for p in (place, place.with_name(place.name + ".bak")) if p.is_file()]
    if not existing:
        raise GStickerError(
            f"resuming {run_dir} needs its owner key (looked at {', '.join(map(str, places))}); "
            "pass --pipeline.key-path OWNER.gskey"
        )
    pipeline_state = runs.load_checkpoint_state(ckpt)["pipeline"]
    for p in existing:
        key = OwnerKey.load(p)
        if key.geometry and folds_to(key.geometry, key.message, pipeline_state):
            return p, key
    raise GStickerError(
        f"the owner key {existing[0]} does not belong to {run_dir} (its sticker and message do not fold to the "
        "run's shared sticker); pass --pipeline.key-path with this run's own key"
    )


def field_host(model_config) -> Optional[str]:
    """Where a base's field mark would live: ``hash`` (nerfacto with the torch implementation), ``planes`` (TensoRF,
    vector-matrix), None (no field mark for this model)."""
    from nerfstudio.models.nerfacto import NerfactoModelConfig
    from nerfstudio.models.tensorf import TensoRFModelConfig

    if isinstance(model_config, TensoRFModelConfig):
        return "planes" if model_config.tensorf_encoding == "vm" else None
    if isinstance(model_config, NerfactoModelConfig) and model_config.implementation == "torch":
        return "hash"
    return None


def chosen_mark(choice: str, model_config) -> str:
    """``--pipeline.mark`` resolved for a base: field or sticker (one-line error for a field mark it cannot host)."""
    host = field_host(model_config)
    if choice == "auto":
        return "sticker" if host is None else "field"
    if choice == "field" and host is None:
        raise GStickerError(
            f"the field mark needs a nerfacto base with the torch implementation or a TensoRF base (vector-matrix), not "
            f"{type(model_config).__name__}; "
            "pass --pipeline.mark sticker"
        )
    return choice


def exit_with_error(error: GStickerError) -> None:
    """One line ``error: <message>`` on stderr, exit status 2 (the plugin's convention for bad input)."""
    raise SystemExit(print_error(str(error)))


class GradientAveragingOptimizers(Optimizers):
    """The host's optimizers, each step preceded by ``average`` on the gradients of the groups it steps (a
    distributed run: :meth:`GeometryStickerPipeline.average_gradients`)."""

    def __init__(
        self, config: Dict, param_groups: Dict[str, List[Parameter]], average: Callable[[List[Parameter]], None]
    ) -> None:
        super().__init__(config, param_groups)
        self.average = average

    def _average(self, groups: List[str]) -> None:
        self.average([p for group in groups for p in self.parameters[group]])

    def optimizer_step(self, param_group_name: str) -> None:
        self._average([param_group_name])
        super().optimizer_step(param_group_name)

    def optimizer_step_all(self) -> None:
        self._average(list(self.optimizers))
        super().optimizer_step_all()

    def optimizer_scaler_step_all(self, grad_scaler) -> None:
        self._average(list(self.optimizers))
        super().optimizer_scaler_step_all(grad_scaler)

    def optimizer_scaler_step_some(self, grad_scaler, param_groups: List[str]) -> None:
        self._average(list(param_groups))
        super().optimizer_scaler_step_some(grad_scaler, param_groups)


class GeometryStickerTrainer(Trainer):
    config: GeometryStickerTrainerConfig
    pipeline: GeometryStickerPipeline

    def __init__(self, config: GeometryStickerTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        super().__init__(config, local_rank, world_size)
        self._checkpoint: Optional[Path] = None
        self._resume = False
        self._key_path: Optional[Path] = None
        self._resume_key: Optional[OwnerKey] = None
        self._identity = None
        self._field: Optional[Dict] = None

    @property
    def key_path(self) -> Path:
        """Where the owner key is written (set by :meth:`setup`)."""
        if self._key_path is None:
            raise GStickerError("the owner key path is set by setup(); call it before saving")
        return self._key_path

    def save_shared_config(self) -> None:
        """config.yml as a recipient sees it: no owner ID, message, sticker seed or key path (they live in the key)."""
        shared = copy.deepcopy(self.config)
        strip_owner_inputs(shared.pipeline)
        shared.save_config()

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        """Stock setup around a strict load of the base (or of our run, to resume).

        Bad input (GStickerError) stops ``ns-train`` here, before any training: one line ``error: ...`` on
        stderr and exit status 2, instead of a traceback.
        """
        try:
            self._setup(test_mode)
        except GStickerError as e:
            exit_with_error(e)

    def _setup(self, test_mode: Literal["test", "val", "inference"]) -> None:
        cfg = self.config
        pcfg = cfg.pipeline
        # the owner's inputs leave the config first: Nerfstudio wrote config.yml with them before this ran, and a
        # failure below must not leave them in the run folder
        owner = copy.copy(pcfg)
        strip_owner_inputs(pcfg)
        if comms.is_main_process():
            self.save_shared_config()
        ckpt = runs.resolve_checkpoint(cfg.load_checkpoint, cfg.load_dir, cfg.load_step)
        if ckpt is None and pcfg.model.base_model is None:
            raise GStickerError(
                "geometrysticker needs a trained base: pass --load-checkpoint "
                "BASE_RUN/nerfstudio_models/step-N.ckpt (any nerfacto, vanilla-nerf or tensorf run)"
            )
        GeometryStickerPipeline.resolve_message(owner)  # a malformed message stops here, before any work
        if ckpt is not None:
            run_cfg = runs.load_run_config(runs.run_config_path(ckpt))
            if isinstance(run_cfg.pipeline, GeometryStickerPipelineConfig):
                self._resume = True
                # The trained shapes (sticker, gates, heads) are the run's own, whatever the CLI defaults say.
                pcfg.model = run_cfg.pipeline.model
                pcfg.heads = run_cfg.pipeline.heads
                pcfg.base_run = dict(run_cfg.pipeline.base_run)
                pcfg.datamanager = run_cfg.pipeline.datamanager
                if cfg.data is not None:
                    pcfg.datamanager.data = pcfg.datamanager.dataparser.data = Path(cfg.data)
                found, self._resume_key = resume_key(ckpt, run_cfg, owner.key_path)
                owner.key_path = found
                owner.message = bits_to_str(self._resume_key.message)
                owner.message_from_owner_id = False
                owner.owner_id = self._resume_key.owner_id
                pcfg.message_source = self._resume_key.message_source
            elif chosen_mark(pcfg.mark, run_cfg.pipeline.model) == "field":
                self._setup_field_mark(owner, ckpt)
                return
            else:
                pcfg.model.base_model = run_cfg.pipeline.model
                pcfg.model.base_step = runs.checkpoint_step(ckpt)
                pcfg.datamanager = copy_datamanager(run_cfg, cfg.data)
                pcfg.base_run = {
                    "method": run_cfg.method_name,
                    "model": type(run_cfg.pipeline.model).__name__,
                    "config": str(runs.run_config_path(ckpt)),
                    "checkpoint": str(ckpt.resolve()),
                    "checkpoint_sha256": file_sha256(ckpt),
                }
            self._checkpoint = ckpt
        self._key_path = self._owner_key_path(owner)
        self._identity = owner_identity() if comms.is_main_process() else None
        message = GeometryStickerPipeline.resolve_message(owner)
        source = pcfg.message_source or GeometryStickerPipeline.source_of_message(owner)
        pcfg.message_source = source
        if comms.is_main_process():
            self.save_shared_config()  # again, now with the base filled in: stock ns-viewer/ns-render rebuild from it
        super().setup(test_mode)
        message = self.pipeline.from_rank0(message)  # several ranks: rank 0's draw
        self.pipeline.set_owner(message, source, owner.owner_id, self._resume_key)
        if owner.sticker_seed is not None and not self._resume:  # a resumed sticker comes from the key
            self.pipeline.model.reseed_sticker(int(owner.sticker_seed))
        CONSOLE.print(f"\\[gsticker] {self.pipeline.describe()}; message source {source}; owner key {self._key_path}")

    def _owner_key_path(self, owner) -> Path:
        """``--pipeline.key-path``, else the keys folder's default for this run; checked before any work."""
        cfg = self.config
        path = (
            Path(owner.key_path)
            if owner.key_path is not None
            else default_key_path(cfg.experiment_name, cfg.method_name, cfg.timestamp)
        )
        check_key_path(path, self.base_dir)
        return path

    def _setup_field_mark(self, owner, ckpt: Path) -> None:
        """The field mark needs no training: check the inputs, then :meth:`train` writes the shared run."""
        pcfg = self.config.pipeline
        if pcfg.mark == "auto":
            CONSOLE.print("\\[gsticker] the message goes into the base's own density field (--pipeline.mark field)")
        if self.world_size > 1:
            raise GStickerError("the field mark is written by one process: drop --machine.num-devices")
        self._key_path = self._owner_key_path(owner)
        message = GeometryStickerPipeline.resolve_message(owner)
        self._field = {
            "checkpoint": ckpt,
            "message": message,
            "source": pcfg.message_source or GeometryStickerPipeline.source_of_message(owner),
            "owner_id": owner.owner_id,
            "pattern_seed": int(owner.pattern_seed) if owner.pattern_seed is not None else secrets.randbits(63),
            "identity": owner_identity(),
        }

    def _write_field_mark(self) -> SharedRun:
        """Mark the base's hash table, write the owner key (read back), then the shared stock run."""
        cfg, pcfg, job = self.config, self.config.pipeline, self._field
        assert job is not None
        ckpt = job["checkpoint"]
        with CONSOLE.status("[bold green]marking the base's field and measuring its renders..."):
            shared = mark_base(
                runs.run_config_path(ckpt),
                ckpt,
                job["message"],
                job["pattern_seed"],
                cfg.output_dir,
                cfg.experiment_name,
                cfg.timestamp,
                amplitude=pcfg.field_amplitude,
                levels=pcfg.field_levels,
                data=cfg.data,
                device=torch.device(cfg.machine.device_type),
            )
        check_key_path(self.key_path, shared.run_dir)
        key = OwnerKey(
            owner_id=job["owner_id"],
            message=job["message"].cpu(),
            heads_config={},
            heads_state={},
            base=shared.base,
            model_run=str(shared.run_dir),
            message_source=job["source"],
            field_mark={**shared.field_mark, "psnr_vs_base": shared.psnr_vs_base},
        )
        key.sign(job["identity"])
        write_key(key, self.key_path)  # the key first: a crash never leaves a shared run whose key is lost
        shared.write()
        (self.base_dir / "config.yml").unlink(missing_ok=True)  # the stripped geometrysticker config: nothing to load
        with contextlib.suppress(OSError):
            self.base_dir.rmdir()
            self.base_dir.parent.rmdir()
        return shared

    def setup_optimizers(self) -> Optimizers:
        """The host's optimizers; in a distributed run, ones that average the gradients over the ranks first."""
        if not self.pipeline.distributed:
            return super().setup_optimizers()
        return GradientAveragingOptimizers(
            self.config.optimizers.copy(), self.pipeline.get_param_groups(), self.pipeline.average_gradients
        )

    def _load_checkpoint(self) -> None:
        ckpt = self._checkpoint
        if ckpt is None:
            return
        state = runs.load_checkpoint_state(ckpt)
        if not self._resume:
            model_state = runs.model_state_from_pipeline_state(state["pipeline"])
            runs.check_tcnn(self.config.pipeline.model.base_model, model_state)
            runs.strict_load(
                self.pipeline.model.base, model_state, num_train_data=len(self.pipeline.datamanager.train_dataset)
            )
            self._start_step = 0
            CONSOLE.print(f"\\[gsticker] base loaded strictly from {ckpt} (frozen); starting at step 0")
            return
        self.pipeline.load_pipeline(state["pipeline"], state["step"])
        self.optimizers.load_optimizers(state["optimizers"])
        if "schedulers" in state and self.config.load_scheduler:
            self.optimizers.load_schedulers(state["schedulers"])
        key = self._resume_key if self._resume_key is not None else OwnerKey.load(self.key_path)
        assert self.pipeline.heads is not None
        self.pipeline.restore_owner(key)
        ts = key.training_state
        for group in ("heads", "sticker"):
            if f"{group}_optimizer" in ts and group in self.optimizers.optimizers:
                self.optimizers.optimizers[group].load_state_dict(ts[f"{group}_optimizer"])
            if f"{group}_scheduler" in ts and group in self.optimizers.schedulers:
                self.optimizers.schedulers[group].load_state_dict(ts[f"{group}_scheduler"])
        self._start_step = state["step"] + 1
        CONSOLE.print(f"\\[gsticker] resumed from {ckpt} (step {state['step']}) with heads from {self.key_path}")

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        """The owner key (signed, atomic, read back, the previous one kept as ``.bak``), then the shareable checkpoint
        (atomic): the folded sticker, no heads, message or sticker optimizer state. Rank 0 only."""
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        ckpt_path = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        opts = self.optimizers
        secret_groups = ("heads", "sticker")
        state = {
            "step": step,
            "pipeline": self.pipeline.shareable_state_dict(),
            "optimizers": {k: v.state_dict() for k, v in opts.optimizers.items() if k not in secret_groups},
            "schedulers": {k: v.state_dict() for k, v in opts.schedulers.items() if k not in secret_groups},
            "scalers": self.grad_scaler.state_dict(),
        }
        # (a prefix check: base fields have their own "heads", e.g. vanilla-nerf's field_coarse.field_heads)
        assert not any(k.split(".")[0] == "heads" for k in state["pipeline"]), (
            "the heads must never enter the shareable model"
        )
        training_state = {"step": step}
        for group in secret_groups:
            if group in opts.optimizers:
                training_state[f"{group}_optimizer"] = opts.optimizers[group].state_dict()
            if group in opts.schedulers:
                training_state[f"{group}_scheduler"] = opts.schedulers[group].state_dict()
        key = self.pipeline.owner_key(training_state, model_run=str(self.base_dir))
        key.sign(self._identity or owner_identity())
        # the key first, read back and checked, the previous one kept as .bak: a crash never leaves a shared
        # checkpoint whose key is lost
        write_key(key, self.key_path)
        if not self.config.save_only_latest_checkpoint:  # every kept checkpoint keeps its own key (step_key_path)
            write_key(key, step_key_path(self.key_path, step), backup=False)
        tmp = ckpt_path.with_suffix(".ckpt.tmp")
        torch.save(state, tmp)
        os.replace(tmp, ckpt_path)
        if self.config.save_only_latest_checkpoint:
            for f in self.checkpoint_dir.glob("*.ckpt"):
                if f != ckpt_path:
                    f.unlink()

    def train(self) -> None:
        if self._field is not None:
            try:
                shared = self._write_field_mark()
            except GStickerError as e:
                exit_with_error(e)
            except OSError as e:
                where = f" ({e.filename})" if e.filename else ""
                exit_with_error(GStickerError(f"{e.strerror or type(e).__name__}{where} while writing; free the disk"))
            CONSOLE.rule("\\[gsticker] done")
            CONSOLE.print(
                f"Shared run (a stock {shared.base['shared_method']} run, share this folder): {shared.run_dir}"
            )
            CONSOLE.print(f"Owner key (secret, keep it apart): {self.key_path}")
            CONSOLE.print(f"Render PSNR vs the base: {shared.psnr_vs_base:.1f} dB")
            return
        try:
            super().train()
        except GStickerError as e:  # e.g. a base whose samples the fast path cannot capture
            exit_with_error(e)
        except OSError as e:  # a disk that fills up or a folder that went away while saving
            where = f" ({e.filename})" if e.filename else ""
            exit_with_error(
                GStickerError(f"{e.strerror or type(e).__name__}{where} while training; free the disk and resume")
            )
        if not comms.is_main_process():
            return
        CONSOLE.rule("\\[gsticker] done")
        CONSOLE.print(f"Watermarked model (shareable): {self.base_dir / 'config.yml'}")
        CONSOLE.print(f"Owner key (secret, keep it apart): {self.key_path}")
