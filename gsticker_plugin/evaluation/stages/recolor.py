"""Evaluation stage ``recolor``."""

from __future__ import annotations

import contextlib
import json
import shutil
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import torch
from torch import Tensor

from gsticker_plugin.attacks import hue_shift
from gsticker_plugin.evaluation.workspace import Workspace, over_seeds
from gsticker_plugin.recolor.configs import FinetuneArgs, HueArgs, PaletteArgs, PaletteEdit
from gsticker_plugin.recolor.edits import apply_edit, extract_palette_of
from gsticker_plugin.recolor.palette import parse_color, rgb_to_lab
from gsticker_plugin.views import progress_bar


def run(ws: Workspace) -> Dict[str, Any]:
    key = ws.key(ws.primary)
    v = ws.views(ws.primary)
    rows = []
    jitter = ws.p.recolor.image_hue_jitter
    if jitter is not None:
        per_seed, null_seed, quality, image_seed, image_null = [], [], [], [], []
        for seed in ws.p.seeds:
            g = torch.Generator().manual_seed(seed)
            shifts = (torch.rand(v["watermarked"].shape[0], generator=g) * 2 - 1) * abs(float(jitter))

            def jit(x):  # as ns-recolor hue --image-level: per-image shift, written as 8-bit PNG
                y = hue_shift(x.permute(0, 3, 1, 2).float(), shifts).permute(0, 2, 3, 1)
                return (y * 255).round() / 255

            a, b = jit(v["watermarked"]), jit(v["base"])
            per_seed.append(ws.decode(key, a))
            null_seed.append(ws.decode(key, b))
            quality.append(ws.image_metrics(a, b))
            if ws.reads_images:
                image_seed.append({"seed": seed, **ws.image_decode(a)})
                image_null.append({"seed": seed, **ws.image_decode(b)})
        row = _recolor_row(
            {
                "name": "image-hue-jitter",
                "kind": "image_hue",
                "label": f"image-level hue jitter U(-{abs(jitter):g}, {abs(jitter):g})",
            },
            per_seed,
            null_seed,
            quality,
            paper=99.33,
        )
        if image_seed:
            row["image_decoder"], row["image_decoder_null"] = over_seeds(image_seed), over_seeds(image_null)
        rows.append(row)
    with_color = ws.p.geometry is not None and ws.p.geometry.color_baseline and ws.color_run() is not None
    source = palette_source(ws) if ws.p.recolor.colors else None
    for var in progress_bar(recolor_variants(ws), "recolor", ws.progress):
        wm, base = recolored(ws, var, "wm"), recolored(ws, var, "base")
        a, b = wm["rgb"], base["rgb"]
        paper = 99.40 if var["kind"] == "palette" else None
        row = _recolor_row(var, [ws.decode(key, a)], [ws.decode(key, b)], [ws.image_metrics(a, b)], paper)
        row["geometry"] = ws._from_tensors(wm, "geo", key.num_bits)
        row["geometry_null"] = ws._from_tensors(base, "geo", key.num_bits)
        if with_color:
            row["color_baseline"] = ws._from_tensors(recolored(ws, var, "color"), "color", key.num_bits)
        if var["kind"] == "finetune":
            row["steps"] = var["steps"]
        if var["kind"] == "palette" and source is not None:
            row["delta_e"] = palette_distance(source, var["color"])
        rows.append(row)
    return {
        "base": ws.primary,
        "rows": rows,
        "palette_entry": ws.p.recolor.palette_entry,
        "palette_source": source,
        "note": "bit accuracy of the watermarked run after the edit; 'null' = the same edit of the unwatermarked base "
        "decoded with the owner key; PSNR/SSIM = watermarked-recolored vs unwatermarked-recolored render; "
        "bit_acc/null_* = the blind extractor on the renders; 'geometry' = the informed geometric decoder on "
        "the edited model (geometry_null: on the edited base); 'color_baseline' = the color-branch "
        "baseline after the same edit, read by the informed color decoder",
    }


def recolor_variants(ws: Workspace) -> List[Dict[str, Any]]:
    rc = ws.p.recolor
    out = []
    for c in rc.colors:
        out.append(
            {
                "name": f"palette-{c.replace(' ', '')}",
                "kind": "palette",
                "color": c,
                "label": f"palette {rc.palette_entry} -> {c}",
                "edit": (PaletteArgs, {"set_": (f"{rc.palette_entry}={c}",)}),
            }
        )
    for h in rc.model_hue:
        out.append(
            {
                "name": f"hue-{h:+g}",
                "kind": "model_hue",
                "label": f"model-level hue {h:+g}",
                "edit": (HueArgs, {"shift": float(h)}),
            }
        )
    ft = rc.finetune
    if ft is not None:
        tgt = {"set_": (f"{rc.palette_entry}={ft.color}",)} if ft.color is not None else {"hue_shift": ft.hue_shift}
        what = f"palette {rc.palette_entry} -> {ft.color}" if ft.color is not None else f"hue {ft.hue_shift:+g}"
        # one fine-tune per model to the longest step count; the shorter ones are its snapshots (--save-at)
        counts = sorted({ft.steps, *ft.steps_curve})
        views = {} if ft.max_views is None else {"max_views": int(ft.max_views)}
        fields = {
            **tgt,
            **views,
            "steps": int(counts[-1]),
            "rays_per_step": int(ft.rays_per_step),
            "save_at": tuple(int(n) for n in counts[:-1]),
        }
        for n in counts:
            out.append(
                {
                    "name": "finetune" if n == ft.steps else f"finetune-{n}steps",
                    "kind": "finetune",
                    "steps": n,
                    "label": f"attacker's color fine-tune ({what}, {n} steps)",
                    "edit": (FinetuneArgs, fields),
                    "snapshot": n != counts[-1],
                }
            )
    return out


def palette_source(ws: Workspace) -> Optional[List[float]]:
    """The color of the palette entry the palette edits replace, extracted as ``ns-recolor palette`` does
    (training images' foreground, k-means with its default k and seed 0)."""
    pipe = ws.load(ws.base_config(ws.primary))
    pal = extract_palette_of(PaletteEdit(), pipe.model, pipe.datamanager.train_dataset, seed=0)
    e = ws.p.recolor.palette_entry
    return [float(x) for x in pal.rgb[e].tolist()] if e < pal.k else None


def recolored(ws: Workspace, variant: Dict[str, Any], which: str) -> Dict[str, Tensor]:
    """One ns-recolor edit of the watermarked run (``wm``), the base run (``base``) or the color-branch baseline
    (``color``): its renders and, with ``geometry`` on, its model-level decodes (geometric; color for ``color``)."""

    def make():
        src = {"wm": ws.wm_dir(ws.primary) / "config.yml", "base": ws.base_config(ws.primary), "color": ws.color_run()}[
            which
        ]
        base_dir = ws.out / "recolored" / ws.primary
        if variant["kind"] == "finetune":  # the curve's variants share one ns-recolor run: OUT, OUT-stepN
            out_dir = base_dir / "finetune" / which
            dest = out_dir.with_name(f"{which}-step{variant['steps']}") if variant["snapshot"] else out_dir
        else:
            out_dir = dest = base_dir / variant["name"] / which
        if not list(dest.glob("*/*/*/config.yml")):
            for old in [out_dir, *out_dir.parent.glob(f"{which}-step*")]:
                if old.exists():
                    shutil.rmtree(old)
            kind, fields = variant["edit"]
            args = kind(load_config=Path(src), output_dir=out_dir, data=ws.scene_dir, **fields)
            ws.say(f"  recolor ({variant['label']}): {src} -> {out_dir}")
            with contextlib.redirect_stdout(sys.stderr):
                apply_edit(args)
        (cfg,) = list(dest.glob("*/*/*/config.yml"))
        pipe = ws.load(cfg)
        label = f"{variant['name']} ({which})"
        out = {}
        if which != "color":  # the baseline is only decoded (its renders enter no table)
            out["rgb"] = ws.render(pipe, label)["rgb"]
        g = ws.p.geometry
        if g is not None and (which == "wm" or (which == "base" and g.recolor_null)):
            out.update(ws._as_tensors(ws.geo_decode(ws.primary, pipe.model, desc=label), "geo"))
        if g is not None and which == "color":
            amp = json.loads(ws.stage_path("geometry").read_text())["color_baseline"]["amplitude"]
            out.update(ws._as_tensors(ws.color_decode(pipe.model, amp, desc=label), "color"))
        if not ws.p.recolor.keep_runs:
            shutil.rmtree(dest)
        return out

    return ws.cached(f"recolor-{ws.primary}-{variant['name']}-{which}", make)


def _recolor_row(var, per_seed, null_seed, quality, paper) -> Dict[str, Any]:
    def mean(xs, k):
        vals = [x[k] for x in xs if isinstance(x[k], (int, float))]
        return float(sum(vals) / len(vals)) if vals else (xs[0][k] if xs else None)

    return {
        "name": var["name"],
        "kind": var["kind"],
        "label": var["label"],
        "paper": paper,
        "bit_acc": mean(per_seed, "bit_acc"),
        "share_passing": mean(per_seed, "share_passing"),
        "verdict_rate": sum(float(s["verdict"]) for s in per_seed) / len(per_seed),
        "null_bit_acc": mean(null_seed, "bit_acc"),
        "null_share_passing": mean(null_seed, "share_passing"),
        "psnr": mean(quality, "psnr"),
        "ssim": mean(quality, "ssim"),
        "per_seed": per_seed,
        "null_per_seed": null_seed,
    }


def palette_distance(source_rgb: Sequence[float], color: str) -> float:
    """CIE76 distance (Lab Delta E) between a palette entry and the color an edit gives it."""
    lab = rgb_to_lab(torch.tensor([list(source_rgb), list(parse_color(color))], dtype=torch.float32))
    return float((lab[0] - lab[1]).norm())
