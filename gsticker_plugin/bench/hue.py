"""The informed image decoder under hue shifts: V-channel mode against the RGB fit, beside the unmarked null.

    python -m gsticker_plugin.bench.hue --load-config RUN/config.yml --key RUN.gskey --data ../shared/data/lego100

Renders ``--num-views`` test views of a watermarked run (sticker on) and of its base (sticker off), hue-shifts them
(kornia HSV, turns), rounds them to 8 bits and decodes them at their cameras with the informed image decoder, once
with the V-channel mode on (the default of ``ns-verify-owner --images --cameras``) and once with RGB fits only.
Writes a Markdown table and a JSON beside it.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch
import tyro

from gsticker_plugin import compat, metrics
from gsticker_plugin.attacks import hue_shift
from gsticker_plugin.bench import command_lines
from gsticker_plugin.decoders.image import decode_posed_images
from gsticker_plugin.decoders.reference import load_base_reference
from gsticker_plugin.evaluate import render_split
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.machine import machine_info
from gsticker_plugin.metrics import as_8_bit
from gsticker_plugin.runs import load_run


@dataclass
class BenchHueConfig:
    """Decode hue-shifted renders of a watermarked run at their cameras, with and without the V-channel mode."""

    load_config: Path
    """The watermarked run's config.yml."""
    key: Path
    """Its owner key."""
    data: Optional[Path] = None
    """The dataset, when the recorded path does not exist from here."""
    base_config: Optional[Path] = None
    """The owner's base config.yml, when the key's recorded one does not exist from here."""
    num_views: int = 16
    """First test views decoded."""
    shifts: Tuple[float, ...] = (0.0, 0.1, 0.25, -0.25, 0.5)
    """Hue shifts in turns (0.5 = 180 degrees)."""
    seed: int = 0
    output: Path = Path("docs/experiments/bench-hue.md")
    """The page; its JSON goes beside it."""


def main(cfg: BenchHueConfig) -> Dict[str, Any]:
    compat.apply()
    warnings.filterwarnings("ignore")  # nerfstudio 1.1.5's camera indexing warns on every render with this torch
    device = torch.device("cpu")
    key = OwnerKey.load(cfg.key)
    with contextlib.redirect_stdout(sys.stderr):
        _, pipe, _ = load_run(cfg.load_config, data=cfg.data, device=device)
        ref = load_base_reference(key, cfg.key, cfg.base_config, cfg.data, device)
    dataset = pipe.datamanager.eval_dataset
    n = min(cfg.num_views, len(dataset))
    marked = render_split(pipe, "test", n, sticker=True, progress=False)["rgb"]
    clean = render_split(pipe, "test", n, sticker=False, progress=False)["rgb"]
    cams = [(f"test/{i:03d}", dataset.cameras[i : i + 1]) for i in range(n)]
    cache: Dict[Any, Any] = {}
    threshold = metrics.min_matches_for_fpr(key.num_bits, 1e-6)
    rows: List[Dict[str, Any]] = []
    for shift in cfg.shifts:
        for name, images, modes in (("marked", marked, (True, False)), ("unmarked", clean, (True,))):
            x = (
                as_8_bit(hue_shift(images.permute(0, 3, 1, 2), shift).permute(0, 2, 3, 1))
                if shift
                else as_8_bit(images)
            )
            for value_mode in modes:
                t0 = time.time()
                dec = decode_posed_images(key, ref, list(x), cams, cfg.seed, ref_cache=cache, value_mode=value_mode)
                m = dec["matches"]
                row = {
                    "shift": shift,
                    "images": name,
                    "value_mode": value_mode,
                    "bit_acc": float(dec["bit_acc"].mean()),
                    "views_passing": int((m >= threshold).sum()),
                    "views": n,
                    "matches_min": int(m.min()),
                    "matches_max": int(m.max()),
                    "read_by_value": sum(d["signals"] == ["value"] for d in dec["image"]),
                    "seconds_per_view": (time.time() - t0) / n,
                }
                rows.append(row)
                print(row, flush=True)
    res = {
        "command": "python -m gsticker_plugin.bench.hue " + " ".join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_info(),
        "threshold": threshold,
        "rows": rows,
    }
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    cfg.output.with_suffix(".json").write_text(json.dumps(res, indent=1))
    lines = [
        *command_lines(
            "The informed image decoder under hue shifts",
            res["date"],
            cfg.output.with_suffix(".json").name,
            res["command"],
        ),
        f"The first {n} test views of the watermarked run (sticker on) and of its base (sticker off), hue-shifted with "
        f"kornia's HSV rotation, rounded to 8 bits, decoded at their cameras. A view passes at >= {threshold}/48 "
        "(per-view false-positive rate 1e-6). *V mode on*: the default (an image whose V matches the base render's "
        "far better than its RGB is read by V = max(R, G, B), which the hue shift leaves as it is); *RGB only*: the "
        "fit before it.",
        "",
        "| hue shift (turns) | images | V mode | bit accuracy | views passing | matches min-max | read by V |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['shift']:g} | {r['images']} | {'on' if r['value_mode'] else 'RGB only'} | {100 * r['bit_acc']:.2f} % | "
            f"{r['views_passing']}/{r['views']} | {r['matches_min']}-{r['matches_max']} | {r['read_by_value']} |"
        )
    cfg.output.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main(tyro.cli(BenchHueConfig))
