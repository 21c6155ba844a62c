"""``ns-verify-owner export-key`` and ``commit``: a key's geometry reference from its run, and its commitment."""

from __future__ import annotations

import contextlib
import shutil
import sys
from pathlib import Path
from typing import Any, Dict

import torch

from gsticker_plugin.errors import GStickerError
from gsticker_plugin.key import OwnerKey, commitment
from gsticker_plugin.model import geometry_reference
from gsticker_plugin.runs import load_run
from gsticker_plugin.verify.configs import CommitConfig, ExportKeyConfig


def export_key(config: ExportKeyConfig) -> Dict[str, Any]:

    key_path = Path(config.key)
    key = OwnerKey.load(key_path, allow_legacy=config.allow_legacy)
    if key.field_mark:
        raise GStickerError(f"{key_path} is a field-mark key: it already holds everything its decoder needs")
    with contextlib.redirect_stdout(sys.stderr):
        run_cfg, pipeline, ckpt = load_run(config.load_config, data=config.data, device=torch.device("cpu"))
    model = pipeline.model
    if not hasattr(model, "sticker") or not hasattr(model, "final_wrap"):
        raise GStickerError(
            f"{config.load_config} is a {run_cfg.method_name} run without a sticker; pass the "
            "watermarked run (ns-train geometrysticker) the key was written for"
        )
    if bool(getattr(model, "folded", False)):
        raise GStickerError(
            f"{config.load_config} is a shared run (its sticker is folded, it holds no message); its "
            "owner key already carries the geometry reference: nothing to export"
        )
    if not torch.equal(model.message.cpu().long(), key.message.long()):
        raise GStickerError(
            f"the run {config.load_config} carries a different message than the key {key_path}; "
            "pass the watermarked run this key was written for"
        )
    run_sha = dict(run_cfg.pipeline.base_run).get("checkpoint_sha256")
    key_sha = (key.base or {}).get("checkpoint_sha256")
    if run_sha != key_sha:
        raise GStickerError(
            f"the run {config.load_config} was made on another base than the key {key_path} "
            "(base checkpoint sha256 differs); pass the watermarked run this key was written for"
        )
    old = key.geometry or {}
    key.geometry = {
        **geometry_reference(model),
        "null": old.get("null"),
        **({"image_null": old["image_null"]} if old.get("image_null") else {}),
    }
    key.signature = key.public_key = ""  # the commitment changed with the geometry: an older signature no longer holds
    out = Path(config.output) if config.output is not None else key_path
    backup = None
    if out.resolve() == key_path.resolve() and config.backup:
        backup = key_path.with_name(key_path.name + ".bak")
        shutil.copy2(key_path, backup)
    key.save(out)
    OwnerKey.load(out)
    return {
        "key": str(out),
        "backup": str(backup) if backup else None,
        "run": str(config.load_config),
        "checkpoint": str(ckpt),
        "fields": key.geometry["fields"],
    }


def commit(config: CommitConfig) -> Dict[str, Any]:
    key = OwnerKey.load(Path(config.key))
    return {
        "key": str(config.key),
        "commitment": commitment(key),
        "public_key": key.public_key if key.signed() else "",
        "message_source": key.message_source,
        "null_caveats": key.null_caveats(),
    }
