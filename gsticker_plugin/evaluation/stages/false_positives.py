"""Evaluation stage ``false_positives``."""

from __future__ import annotations

import contextlib
import json
import re
import sys
from pathlib import Path
from typing import Any, Dict, List

import torch
from torch import Tensor

from gsticker_plugin import metrics
from gsticker_plugin.evaluation.workspace import Workspace
from gsticker_plugin.runs import load_run
from gsticker_plugin.views import images_views, random_views


def run(ws: Workspace) -> Dict[str, Any]:
    key = ws.key(ws.primary)
    fp = ws.p.false_positives
    sources: List[Dict[str, Any]] = []

    def add(name: str, kind: str, images: Tensor, note: str = "") -> None:
        """The blind extractor on ``images``, and the image decoder too when they have the test views' size."""
        d = ws.decode(key, images)
        src = {
            "name": name,
            "kind": kind,
            "note": note,
            "views": d["views"],
            "passing": d["views_passing"],
            "fpr": d["views_passing"] / d["views"],
            "max_matches": max(d["matches"]),
            "bit_acc": d["bit_acc"],
            "verdict": d["verdict"],
            "matches": d["matches"],
        }
        if ws.reads_images and tuple(images.shape[1:3]) == ws.test_hw:
            e = ws.image_decode(images)
            src["image_decoder"] = {
                "views": e["views"],
                "passing": e["views_passing"],
                "max_matches": max(e["matches"]),
                "bit_acc": e["bit_acc"],
                "verdict": e["verdict"],
                "matches": e["matches"],
            }
        sources.append(src)

    for b in ws.p.bases:
        v = ws.views(b.name)
        add(f"{b.name} base run", "unwatermarked model", v["base"])
        add(f"{b.name} watermarked run, sticker off", "unwatermarked model", v["sticker_off"])
    if fp.ground_truth:
        add("ground-truth test images", "images", ws.views(ws.primary)["gt"], "photos of the same scene")
    for o in fp.other_runs:
        name, cfg = o.get("name", Path(o["config"]).parent.name), Path(o["config"])
        data = Path(o["data"]) if o.get("data") else None

        def render_other(cfg=cfg, data=data, name=name):

            with contextlib.redirect_stdout(sys.stderr):
                _, pipe, _ = load_run(cfg, data=data, device=ws.device)
            return {"rgb": ws.render(pipe, name)["rgb"]}

        add(
            name,
            "unwatermarked model",
            ws.cached(f"other-{re.sub(r'[^A-Za-z0-9_.-]', '_', name)}", render_other)["rgb"],
            str(cfg),
        )
    for folder in fp.other_images:
        vs = images_views(Path(folder), 400, 16, 10**9, progress=False)
        if vs.views:
            ims = [x.image for x in vs.views]
            same = all(i.shape == ims[0].shape for i in ims)
            if same:
                add(f"images {folder}", "images", torch.stack(ims).permute(0, 2, 3, 1))
            else:
                for i, im in enumerate(ims):
                    add(f"images {folder} #{i}", "images", im.permute(1, 2, 0)[None])
    recolor = ws.stage_path("recolor")
    if recolor.is_file():
        for row in json.loads(recolor.read_text())["rows"]:
            for s in row["null_per_seed"][:1]:
                m = s["matches"]
                sources.append(
                    {
                        "name": f"base recolored: {row['label']}",
                        "kind": "unwatermarked model",
                        "note": "from the recolor stage",
                        "views": len(m),
                        "passing": sum(x >= ws.threshold for x in m),
                        "fpr": sum(x >= ws.threshold for x in m) / len(m),
                        "max_matches": max(m),
                        "bit_acc": s["bit_acc"],
                        "verdict": s["verdict"],
                        "matches": m,
                    }
                )
    if fp.random_images > 0:
        size = int(ws.views(ws.primary)["watermarked"].shape[1])
        rv = random_views(fp.random_images, size, seed=ws.p.seeds[0])
        add(
            f"{fp.random_images} random images",
            "random images",
            torch.stack([x.image for x in rv.views]).permute(0, 2, 3, 1),
            "noise, smooth noise, flat colors, gradients",
        )
    n = sum(s["views"] for s in sources)
    x = sum(s["passing"] for s in sources)
    models = [s for s in sources if s["kind"] == "unwatermarked model"]
    return {
        "threshold": ws.threshold,
        "fpr_target": ws.p.fpr,
        "sources": sources,
        "views": n,
        "passing": x,
        "empirical_fpr": x / n if n else None,
        "fpr_upper_95": metrics.clopper_pearson_upper(x, n) if n else None,
        "models": len(models),
        "models_flagged": sum(bool(s["verdict"]) for s in models),
        "note": "views of one model are not independent; the Clopper-Pearson bound treats them as if they "
        "were and is therefore optimistic; the model-level count is the honest one",
    }
