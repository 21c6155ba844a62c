"""Edit fidelity of the training-free palette recolor, measured on a real run (``python -m gsticker_plugin.recolor.bench``).

For one palette entry moved to a target color, on the run's training views:

* *region*: the pixels whose original render is hard-assigned to the edited entry (nearest entry in the
  palette metric) and covered by the object (accumulation > 0.5);
* *moved*: share of region pixels whose hue after the edit lies within 30 degrees (LCh hue) of the target's;
  *hue error*: median LCh hue distance of region pixels to the target (degrees);
* *PSNR outside*: PSNR of the edited render vs the original over all pixels outside the region (what must stay);
* *PSNR outside, object only*: the same over object pixels outside the region (the background is never touched).

Model-level (per sample, before compositing) is compared with the same edit applied to the rendered image.
Writes a markdown table to stdout (and ``--out``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import torch
import tyro
from torch import Tensor

from gsticker_plugin import compat
from gsticker_plugin.recolor import palette as P
from gsticker_plugin.recolor import runs
from gsticker_plugin.recolor.model import ColorWrap, require_color_fields, unwrap


def lch_hue_deg(rgb: Tensor) -> Tensor:
    lab = P.rgb_to_lab(rgb)
    return torch.rad2deg(torch.atan2(lab[..., 2], lab[..., 1])) % 360.0


def hue_distance_deg(a: Tensor, b: Tensor | float) -> Tensor:
    d = (a - b).abs() % 360.0
    return torch.minimum(d, 360.0 - d)


def psnr_masked(a: Tensor, b: Tensor, mask: Tensor) -> float:
    if int(mask.sum()) == 0:
        return float("nan")
    mse = float(((a - b) ** 2)[mask].mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def edit_region(rgb: Tensor, acc: Tensor, palette_lab: Tensor, index: int) -> Tensor:
    """[..., H, W] bool: object pixels whose color is nearest (palette metric) to entry ``index``."""
    w = P.palette_weights(P.rgb_to_lab(rgb), palette_lab, 1.0)  # softness 1: argmax of the nearest entry
    return (w.argmax(-1) == index) & (acc[..., 0] > 0.5)


def fidelity(
    original: Tensor, edited: Tensor, region: Tensor, acc: Tensor, target_rgb: Sequence[float]
) -> Dict[str, float]:
    """Metrics of one edit over [N, H, W, 3] renders."""
    target_hue = float(lch_hue_deg(torch.tensor([list(target_rgb)], dtype=torch.float32))[0])
    hue = lch_hue_deg(edited[region])
    dist = hue_distance_deg(hue, target_hue)
    outside = ~region
    obj_out = outside & (acc[..., 0] > 0.5)
    hue0 = lch_hue_deg(original[region])
    return {
        "region_share": float(region.float().mean()),
        "moved": float((dist < 30.0).float().mean()) if dist.numel() else float("nan"),
        "hue_error_deg": float(dist.median()) if dist.numel() else float("nan"),
        "hue_error_before_deg": float(hue_distance_deg(hue0, target_hue).median()) if hue0.numel() else float("nan"),
        "psnr_outside": psnr_masked(original, edited, outside),
        "psnr_outside_object": psnr_masked(original, edited, obj_out),
        "psnr_region": psnr_masked(original, edited, region),
    }


@torch.no_grad()
def measure(
    config: Path,
    data: Optional[Path],
    edits: Sequence[tuple],
    softness: Sequence[float],
    views: int,
    k: Optional[int] = None,
    seed: int = 0,
) -> List[Dict[str, object]]:
    loaded = runs.load_run(config, data)
    model = loaded.pipeline.model
    dataset = loaded.pipeline.datamanager.train_dataset
    n = min(views, len(dataset))
    t0 = time.time()
    pal = P.extract_palette(runs.foreground_pixels(runs.training_images(dataset)), k=k, seed=seed)
    t_pal = time.time() - t0
    base = runs.render_views(model, dataset.cameras, range(n), desc="original", outputs=("rgb", "accumulation"))
    orig = torch.stack(base["rgb"])
    acc = torch.stack(base["accumulation"])
    rows: List[Dict[str, object]] = []
    for index, color in edits:
        target = P.parse_color(color)
        region = edit_region(orig, acc, pal.lab, index)
        src = pal.lab
        tgt = pal.lab.clone()
        tgt[index] = P.rgb_to_lab(torch.tensor([target]))[0]
        for soft in softness:
            fields = require_color_fields(unwrap(model))
            wraps = [ColorWrap(f, lambda rgb, s=soft: P.recolor(rgb, src.to(rgb), tgt.to(rgb), s)) for _, f in fields]
            t0 = time.time()
            try:
                edited = torch.stack(
                    runs.render_views(model, dataset.cameras, range(n), desc=f"edit {index} soft {soft}")["rgb"]
                )
            finally:
                for w in reversed(wraps):
                    w.remove()
            t_render = (time.time() - t0) / n
            image_level = P.recolor(orig, src, tgt, soft)
            row = {
                "entry": f"{index}: {P.to_hex(pal.rgb[index])} -> {color}",
                "softness": soft,
                "level": "model",
                "s_per_view": t_render,
                **fidelity(orig, edited, region, acc, target),
            }
            rows.append(row)
            rows.append(
                {
                    "entry": row["entry"],
                    "softness": soft,
                    "level": "image",
                    "s_per_view": float("nan"),
                    **fidelity(orig, image_level, region, acc, target),
                }
            )
    rows.insert(0, {"palette": pal.describe(), "k": pal.k, "palette_seconds": t_pal, "views": n})
    return rows


def to_markdown(rows: List[Dict[str, object]]) -> str:
    head = rows[0]
    lines = [
        f"Palette (K = {head['k']}, {head['palette_seconds']:.1f} s): " + "; ".join(head["palette"]),
        "",
        f"{head['views']} training views.",
        "",
        "| edit | softness | level | region % | moved | hue err (deg, before) | PSNR outside | PSNR outside (object) | s/view |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows[1:]:
        lines.append(
            f"| {r['entry']} | {r['softness']:g} | {r['level']} | {100 * r['region_share']:.1f} | "
            f"{100 * r['moved']:.0f} % | {r['hue_error_deg']:.0f} ({r['hue_error_before_deg']:.0f}) | "
            f"{r['psnr_outside']:.1f} | {r['psnr_outside_object']:.1f} | "
            f"{'' if math.isnan(r['s_per_view']) else format(r['s_per_view'], '.2f')} |"
        )
    return "\n".join(lines)


@dataclass
class BenchArgs:
    load_config: Path = Path("../shared/checkpoints/lego100-nerfacto-small/nerfacto/base/config.yml")
    data: Optional[Path] = Path("../shared/data/lego100")
    edits: tuple = ("0=dodgerblue", "1=magenta")
    softness: tuple = (5.0, 10.0, 20.0)
    views: int = 8
    k: Optional[int] = None
    out: Optional[Path] = None


def main() -> None:

    compat.apply()  # the plugin's host fixes (offline LPIPS, checkpoint types)

    args = tyro.cli(BenchArgs)
    edits = [(int(e.split("=")[0]), e.split("=", 1)[1]) for e in args.edits]
    rows = measure(args.load_config, args.data, edits, args.softness, args.views, args.k)
    md = to_markdown(rows)
    print(md)
    if args.out is not None:
        Path(args.out).write_text(md + "\n")


if __name__ == "__main__":
    main()
