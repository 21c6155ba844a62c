"""Evaluation stage ``speed``."""

from __future__ import annotations

import json
from typing import Any, Dict

from gsticker_plugin.evaluation.workspace import Workspace


def run(ws: Workspace) -> Dict[str, Any]:
    st = json.loads(ws.stage_path("sticker").read_text())
    q = json.loads(ws.stage_path("quality").read_text()) if ws.stage_path("quality").is_file() else {}
    res = {}
    for b in ws.p.bases:
        mon = st.get(b.name, {}).get("monitor", [])
        res[b.name] = {
            "train_seconds": st.get(b.name, {}).get("train_seconds"),
            "steps": st.get(b.name, {}).get("steps"),
            "monitor": mon,
            "final_bit_acc": q.get(b.name, {}).get("decode_watermarked", {}).get("bit_acc"),
            "final_psnr_wm_vs_unwm": q.get(b.name, {}).get("wm_vs_unwm", {}).get("psnr"),
        }
    usable = any(r["monitor"] for r in res.values())
    res["note"] = (
        (
            "held-out history: the '[gsticker] step N: held-out bit acc ...' lines ns-train geometrysticker prints "
            "every --pipeline.steps-per-monitor steps (fast-path renders of held-out novel views, owner message, "
            "no attack); final = real renders of the test views"
        )
        if usable
        else (
            "no held-out history in the sticker logs (the monitor did not run: fewer steps than "
            "--pipeline.steps-per-monitor, or the run was trained elsewhere); only the final point is plotted"
        )
    )
    return res
