"""Speed against accuracy: sticker configurations trained side by side, decoded at every saved checkpoint.

    python -m gsticker_plugin.bench.sweep \\
        --load-checkpoint ../shared/checkpoints/lego100-nerfacto-small/nerfacto/base/nerfstudio_models/step-000002999.ckpt \\
        --data ../shared/data/lego100 --output docs/experiments/bench-sweep.md

For each variant (sticker width, message length, share of samples under the gate, image resolution) it runs
``ns-train geometrysticker`` on the same frozen base, keeping a checkpoint every ``--save-every`` steps, then for
every checkpoint: the informed geometric decoder's bit accuracy (``ns-verify-owner --decode geometry``, with that
checkpoint's own sticker as the reference: what the owner key would hold had training stopped there) and the PSNR
of the watermarked vs the unwatermarked render (sticker on / off, test views). Training time at a checkpoint is the
pool build plus the step time the trainer logs (``[gsticker] step N: ... S s``, printed at every checkpoint). With ``--image-views N``,
also the informed image decoder on 8-bit renders of N held-out orbit views at their true cameras, clean and under
``--image-attacks`` (:func:`image_readings`).

Writes ``--output`` (Markdown table), the same name with ``.json`` and ``.png`` (bit accuracy and PSNR against
training time, and bit accuracy against PSNR, per variant), and names the smallest variant (sticker parameters) that
reaches the targets.
The heads variants change the extractor and classifier that train beside the sticker (none, 8 wide, the paper's
VGG16 shape): what they cost per step and whether the informed decoders' numbers depend on them. The blind
extractor's own accuracy stays at chance for every configuration this CPU can train (docs/experiments/bench-sticker.md).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch
import tyro

from gsticker_plugin.evaluation.held_out import HELD_OUT_CAMERA_SEED
from gsticker_plugin.evaluation.sweep import (
    VARIANTS,
    chart,
    cost_lines,
    run_variant,
    smallest_meeting,
)
from gsticker_plugin.machine import machine_info


@dataclass
class SweepConfig:
    """Train sticker variants on one base and chart bit accuracy and PSNR against training time."""

    load_checkpoint: Path
    """The base run's checkpoint (RUN/nerfstudio_models/step-N.ckpt)."""
    data: Optional[Path] = None
    """The base's dataset folder (e.g. ../shared/data/lego100); ``res-200``/``res-400`` swap its trailing number for
    200/400 (the same scene at that resolution, e.g. ../shared/data/lego200, or ``ns-gsticker-scene --resolution 400``
    with the base's scene seed)."""
    variants: Tuple[str, ...] = (
        "default",
        "width-16",
        "width-32",
        "bits-16",
        "bits-64",
        "gate-0.25",
        "gate-0.75",
        "res-200",
    )
    """Which of: default, width-16, width-32, width-128, bits-16, bits-32, bits-64, gate-0.25, gate-0.75, heads-none,
    heads-8, heads-vgg16, robust, res-200, res-400."""
    steps: int = 150
    """Sticker training steps per variant."""
    save_every: int = 50
    """A checkpoint (and a decoded point) every this many steps."""
    warmup_steps: int = 25
    """Sticker warm-up (no content loss) before the content loss ramps in."""
    pool_views: int = 8
    """Training and novel views each in the fast-path pool."""
    num_views: int = 4
    """Cameras per geometric decode."""
    psnr_views: int = 4
    """Test views for the watermarked-vs-unwatermarked PSNR."""
    image_views: int = 0
    """Held-out orbit views (bench.unposed's cameras) that the informed image decoder reads at every checkpoint, at
    their true cameras, 8-bit, clean and under each of ``--image-attacks``; 0: none."""
    image_attacks: Tuple[str, ...] = ("clean", "noise=0.1", "jpeg=50")
    """Attack specs for ``--image-views`` (``clean``: none), drawn per view as bench.unposed draws them."""
    camera_seed: int = HELD_OUT_CAMERA_SEED
    """Seed of the held-out orbit cameras (bench.unposed's default: the same views as its pages)."""
    fpr: float = 1e-6
    """Per-view false-positive rate of the verdict threshold."""
    target_bit_acc: float = 0.99
    target_psnr: float = 35.0
    output: Path = Path("docs/experiments/bench-sweep.md")
    """Markdown table; the .json and .png beside it."""
    work_dir: Path = Path("outputs/bench-sweep")
    """Where the runs and logs go (a variant whose final checkpoint exists is not retrained)."""
    owner_id: str = "sweep-owner"
    extra: List[str] = field(default_factory=list)
    """More ns-train arguments for every variant."""


def markdown(cfg: SweepConfig, rows: List[Dict[str, Any]], when: str, machine: str) -> str:
    lines = [
        "# Speed against accuracy: sticker variants on one base",
        "",
        f"Command: `python -m gsticker_plugin.bench.sweep --load-checkpoint {cfg.load_checkpoint}"
        + (f" --data {cfg.data}" if cfg.data else "")
        + f" --variants {' '.join(cfg.variants)} --steps {cfg.steps} "
        f"--save-every {cfg.save_every} --warmup-steps {cfg.warmup_steps} --pool-views {cfg.pool_views} "
        f"--work-dir {cfg.work_dir}"
        + (
            f" --image-views {cfg.image_views} --image-attacks {' '.join(cfg.image_attacks)}"
            + ("" if cfg.camera_seed == HELD_OUT_CAMERA_SEED else f" --camera-seed {cfg.camera_seed}")
            if cfg.image_views
            else ""
        )
        + f" --output {cfg.output}`",
        f"Machine: {machine}. Date: {when}.",
        "",
        f"Each variant: `ns-train geometrysticker` for {cfg.steps} steps ({cfg.pool_views}+{cfg.pool_views} pool views, "
        f"warm-up {cfg.warmup_steps}); at every {cfg.save_every}-step checkpoint the informed geometric decoder on "
        f"{cfg.num_views} cameras (the checkpoint's own sticker as the reference) and PSNR of watermarked vs "
        f"unwatermarked renders on {cfg.psnr_views} test views. Time = pool build + training seconds logged at that "
        "step (setup and checkpoint writing excluded).",
        "",
        "| variant | image | bits | sticker params | trained heads params | step | train s | geometric bit acc | "
        "views passing | PSNR wm vs unwm | PSNR wm vs GT | decode s/view |",
        "|" + "---|" * 12,
    ]
    for r in rows:
        heads = f"{r['heads_params']:,}" if "heads_params" in r else "-"
        for p in r["points"]:
            lines.append(
                f"| {r['name']} | {r['size'][0]} px | {r['num_bits']} | {r['sticker_params']:,} | {heads} | {p['step']} | "
                f"{p['train_seconds'] if p['train_seconds'] is not None else '-'} | {100 * p['bit_acc']:.1f} | "
                f"{p['views_passing']}/{len(p['matches'])} | {p['psnr_vs_unwm']:.2f} | {p['psnr_vs_gt']:.2f} | "
                f"{p['decode_seconds_per_view']} |"
            )
    lines += image_lines(rows, cfg)
    best = smallest_meeting(rows, cfg.target_bit_acc, cfg.target_psnr)
    lines += [
        "",
        f"Smallest 48-bit variant at the lowest resolution reaching >= {100 * cfg.target_bit_acc:g} % and >= "
        f"{cfg.target_psnr:g} dB at its last checkpoint: "
        + (
            f"**{best['name']}** ({best['sticker_params']:,} sticker parameters, {best.get('heads_params', 0):,} trained "
            f"heads parameters, {best['points'][-1]['train_seconds']} s)."
            if best
            else "none of the variants."
        ),
        "",
        *cost_lines(rows, cfg.target_bit_acc, cfg.target_psnr),
        "",
        f"Chart: `{cfg.output.with_suffix('.png').name}`.",
        "",
    ]
    return "\n".join(lines)


def image_lines(rows: List[Dict[str, Any]], cfg: SweepConfig) -> List[str]:
    """The image decoder's table (a row per checkpoint that has its readings), or nothing when no point has them."""
    attacks = list(dict.fromkeys(a for r in rows for p in r["points"] for a in p.get("image", {})))
    if not attacks:
        return []
    lines = [
        "",
        "From images: the informed image decoder at every checkpoint, on 8-bit renders of held-out orbit views "
        f"(bench.unposed's cameras, seed {cfg.camera_seed}: never used in training) read at their true cameras; "
        "cells give bit accuracy % and views at or above the verdict threshold. PSNR: those renders, watermarked vs "
        "unwatermarked. Images alone (no camera) add the camera search to this reading: the final model's numbers "
        "are on the images-alone pages.",
        "",
        "| variant | step | train s | held-out PSNR (dB) | "
        + " | ".join(f"image {a}" for a in attacks)
        + " | image decode s/view |",
        "|---|---|---|---|" + "---|" * len(attacks) + "---|",
    ]
    for r in rows:
        for p in r["points"]:
            if "image" not in p:
                continue
            cells = [
                f"{100 * p['image'][a]['bit_acc']:.1f} ({p['image'][a]['views_passing']}/{len(p['image'][a]['matches'])})"
                if a in p["image"]
                else "-"
                for a in attacks
            ]
            lines.append(
                f"| {r['name']} | {p['step']} | {p['train_seconds'] if p['train_seconds'] is not None else '-'} | "
                f"{p['image_psnr_db']:.2f} | " + " | ".join(cells) + f" | {p['image_decode_seconds_per_view']} |"
            )
    return lines


def main(cfg: SweepConfig) -> List[Dict[str, Any]]:
    unknown = [v for v in cfg.variants if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variant(s) {unknown}; use some of {', '.join(VARIANTS)}")
    rows = []
    for i, name in enumerate(cfg.variants):
        print(f"[{i + 1}/{len(cfg.variants)}] {name}", flush=True)
        rows.append(run_variant(cfg, name))
        cfg.output.parent.mkdir(parents=True, exist_ok=True)
        cfg.output.with_suffix(".json").write_text(json.dumps(rows, indent=1))  # partial results survive a crash
    m = machine_info()
    md = markdown(
        cfg,
        rows,
        time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        f"{m['cpu']}, {m['cores']} cores, torch threads {m['torch_threads']}, CUDA {'yes' if m['cuda'] else 'no'}",
    )
    cfg.output.write_text(md)
    chart(rows, cfg.output.with_suffix(".png"))
    print(md)
    return rows


def entrypoint() -> None:
    torch.set_grad_enabled(True)
    main(tyro.cli(SweepConfig))


if __name__ == "__main__":
    entrypoint()
