"""Evaluation stage ``seeds``."""

from __future__ import annotations

import contextlib
import json
import sys
import time
from typing import Any, Dict

import torch

from gsticker_plugin.decoders.geometric import decode_suspect
from gsticker_plugin.decoders.reference import load_base_reference
from gsticker_plugin.evaluation.workspace import Workspace
from gsticker_plugin.key import OwnerKey


def run(ws: Workspace) -> Dict[str, Any]:
    """The primary base's sticker trained again with other training seeds: each run's model-level geometric
    decode (its own owner key) and its PSNRs on the protocol's test views; mean and spread with the main run."""
    g, b = ws.p.geometry, ws.primary
    q = json.loads(ws.stage_path("quality").read_text())[b]
    main = json.loads(ws.stage_path("geometry").read_text())["bases"][b]["watermarked"]
    st = json.loads(ws.stage_path("sticker").read_text())[b]
    rows = [
        {
            "seed": 42,
            "main_run": True,
            "train_seconds": st.get("train_seconds"),
            "geometry": main,
            "psnr_wm_vs_unwm": q["wm_vs_unwm"]["psnr"],
            "psnr_wm_vs_gt": q["wm_vs_gt"]["psnr"],
        }
    ]
    for seed in ws.p.sticker.seeds:
        name = f"{b}-seed{seed}"
        ws.say(f"  [seeds] {name}")
        secs = ws.train_sticker(b, name, ["--machine.seed", str(seed)])
        wm = ws.out / "runs" / name / "geometrysticker" / "watermarked"
        key_path = wm.with_name("watermarked.gskey")
        pipe = ws.load(wm / "config.yml")
        on, off = (
            ws.render(pipe, f"{name} watermarked", sticker=True),
            ws.render(pipe, f"{name} sticker off", sticker=False),
        )
        key = OwnerKey.load(key_path)
        ref = load_base_reference(key, key_path, ws.base_config(b), ws.scene_dir, ws.device)
        t0 = time.time()
        with contextlib.redirect_stdout(sys.stderr):
            dec, _ = decode_suspect(
                key,
                ref,
                pipe.model,
                g.num_views,
                g.sampled_share,
                ws.p.seeds[0],
                sticker=True,
                progress=ws.progress,
                full_renders=False,
            )
        geo = ws.summarize(dec["matches"], dec["bit_acc"], key.num_bits)
        geo["seconds_per_view"] = round((time.time() - t0) / max(1, geo["views"]), 2)
        ws.say(f"    geometry {name}: matches {geo['matches']} -> {'OWNED' if geo['verdict'] else 'not shown'}")
        rows.append(
            {
                "seed": seed,
                "main_run": False,
                "train_seconds": secs,
                "geometry": geo,
                "psnr_wm_vs_unwm": ws.image_metrics(on["rgb"], off["rgb"])["psnr"],
                "psnr_wm_vs_gt": ws.image_metrics(on["rgb"], on["gt"])["psnr"],
            }
        )
        del pipe, ref

    def spread(vals):
        v = torch.tensor([float(x) for x in vals if isinstance(x, (int, float))], dtype=torch.float64)
        return (
            {"mean": float(v.mean()), "std": float(v.std(unbiased=False)), "min": float(v.min()), "max": float(v.max())}
            if len(v)
            else None
        )

    return {
        "base": b,
        "rows": rows,
        "bit_acc": spread(r["geometry"]["bit_acc"] for r in rows),
        "psnr_wm_vs_unwm": spread(r["psnr_wm_vs_unwm"] for r in rows),
        "psnr_wm_vs_gt": spread(r["psnr_wm_vs_gt"] for r in rows),
        "verdicts": sum(bool(r["geometry"]["verdict"]) for r in rows),
        "note": "the same protocol's sticker (steps, arguments, owner id) trained with other ns-train seeds on the "
        "same frozen base; each run decoded with its own owner key (informed geometric decoder, the "
        "geometry stage's cameras); std over runs (population)",
    }
