"""Evaluation stage ``bases``."""

from __future__ import annotations

import time
from typing import Any, Dict

from gsticker_plugin.errors import GStickerError
from gsticker_plugin.evaluation.workspace import Workspace
from gsticker_plugin.machine import console_script


def run(ws: Workspace) -> Dict[str, Any]:
    res = {}
    for b in ws.p.bases:
        cfg = ws.base_config(b.name)
        if b.config is None and ws.latest_ckpt(cfg.parent) is None:
            t0 = time.time()
            ws.run_cmd(
                [
                    console_script("ns-train"),
                    b.preset,
                    "--machine.device-type",
                    ws.p.device,
                    "--vis",
                    "tensorboard",
                    "--output-dir",
                    str(ws.out / "runs"),
                    "--experiment-name",
                    b.name,
                    "--timestamp",
                    "base",
                    "--max-num-iterations",
                    str(b.steps),
                    "--steps-per-save",
                    str(b.steps),
                    *[str(a) for a in b.args],
                    "--data",
                    str(ws.scene_dir),
                ],
                f"base-{b.name}",
            )
            res[b.name] = {
                "config": str(cfg),
                "trained_here": True,
                "steps": b.steps,
                "train_seconds": round(time.time() - t0, 1),
            }
        else:
            res[b.name] = {"config": str(cfg), "trained_here": b.config is None}
        if ws.latest_ckpt(cfg.parent) is None:
            raise GStickerError(f"base {b.name}: no checkpoint in {cfg.parent / 'nerfstudio_models'}")
        res[b.name]["checkpoint"] = str(ws.latest_ckpt(cfg.parent))
    return res
