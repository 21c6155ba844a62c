"""Evaluation stage ``renders``."""

from __future__ import annotations

import time
from typing import Any, Dict

import torch

from gsticker_plugin.evaluation.workspace import Workspace


def run(ws: Workspace) -> Dict[str, Any]:
    res = {}
    for b in ws.p.bases:

        def wm_views(b=b):
            pipe = ws.load(ws.wm_dir(b.name) / "config.yml")
            on = ws.render(pipe, f"{b.name} watermarked", sticker=True)
            off = ws.render(pipe, f"{b.name} sticker off", sticker=False)
            return {"watermarked": on["rgb"], "sticker_off": off["rgb"], "gt": on["gt"], "indices": on["indices"]}

        def base_views(b=b):
            t0 = time.time()
            r = ws.render(ws.load(ws.base_config(b.name)), f"{b.name} base")
            return {"rgb": r["rgb"], "seconds_per_view": torch.tensor((time.time() - t0) / r["rgb"].shape[0])}

        w = ws.cached(f"{b.name}-wm", wm_views)
        base = ws.cached(f"{b.name}-base", base_views)
        res[b.name] = {
            "views": int(w["watermarked"].shape[0]),
            "size": list(w["watermarked"].shape[1:3]),
            "indices": w["indices"].tolist(),
            "base_seconds_per_view": float(base["seconds_per_view"]),
        }
    return res
