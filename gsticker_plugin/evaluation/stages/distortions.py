"""Evaluation stage ``distortions``."""

from __future__ import annotations

from typing import Any, Dict

from gsticker_plugin.evaluation.workspace import Workspace, describe_spec, over_seeds
from gsticker_plugin.views import progress_bar


def run(ws: Workspace) -> Dict[str, Any]:
    v = ws.views(ws.primary)
    key = ws.key(ws.primary)
    rows = []
    for r in progress_bar(ws.p.distortions, "distortions", ws.progress):
        per_seed, image_per_seed = [], []
        for seed in ws.p.seeds:
            x = ws.attacked(v["watermarked"], v["sticker_off"], r.spec, seed)
            d = ws.decode(key, x)
            d["attack_psnr"] = ws.image_metrics(x, v["watermarked"])["psnr"]
            per_seed.append({"seed": seed, **d})
            if ws.reads_images:
                image_per_seed.append({"seed": seed, **ws.image_decode(x)})
        row = {
            "label": r.label,
            "spec": r.spec,
            "paper": r.paper,
            "definition": describe_spec(r.spec),
            **over_seeds(per_seed),
            "attack_psnr": per_seed[0]["attack_psnr"],
        }
        if image_per_seed:
            row["image_decoder"] = over_seeds(image_per_seed)
        rows.append(row)
    return {"base": ws.primary, "rows": rows, "threshold": ws.threshold, "image_decoder": ws.reads_images}
