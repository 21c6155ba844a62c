"""Sticker-stage speed benchmark: fast path vs naive re-rendering vs a paper-faithful configuration.

    python -m gsticker_plugin.bench.sticker \
        --load-checkpoint ../shared/checkpoints/lego100-nerfacto-small/nerfacto/base/nerfstudio_models/step-000002999.ckpt \
        --output docs/experiments/bench-sticker.md

Runs, in one process on the same base and the same held-out views, each configuration for a wall-clock
budget, and prints steps/s and the time to >= 99% held-out bit accuracy (owner message, no attack).
(a) fast: cached base samples, small extractor (the default);
(b) naive: the base re-rendered every step (random 64x64 ray patches), small extractor;
(c) paper: cached samples, VGG16-shaped extractor and classifier (randomly initialised: no weights offline).
Optional (d) owner: the fast path trained on the owner's fixed message only, as the authors' released code did;
its "clean" column (the same extractor on unwatermarked renders of the held-out views) shows whether it reads the
mark or prints a constant.
"""

from __future__ import annotations

import json
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch
import tyro

from gsticker_plugin.evaluation.sticker_speed import run_variant


@dataclass
class StickerBenchConfig:
    """Compare training strategies of the sticker stage on one base."""

    load_checkpoint: Path
    """Base run checkpoint."""
    data: Optional[Path] = None
    """Dataset, if the base's recorded path does not exist from here."""
    variants: Tuple[str, ...] = ("fast", "naive", "paper")
    """Which configurations to run."""
    seconds: float = 300.0
    """Wall-clock training budget per configuration (pool rendering excluded and reported apart)."""
    max_steps: int = 3000
    """Step cap per configuration."""
    steps_per_monitor: int = 50
    """Held-out bit accuracy is measured every this many steps."""
    pool_train_views: int = 24
    pool_novel_views: int = 24
    monitor_views: int = 8
    pool_cache: Optional[Path] = Path("outputs/bench-sticker/pool.pt")
    """Rendered pool kept here so every variant (and reruns) use the same views."""
    output: Path = Path("docs/experiments/bench-sticker.md")
    """Markdown report (a JSON file is written beside it)."""
    append: bool = False
    """Keep the variants already in the JSON beside --output and add (or replace) these."""


def write_report(cfg: StickerBenchConfig, results: List[Dict[str, object]]) -> None:
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    dev = (
        torch.cuda.get_device_name(0)
        if torch.cuda.is_available()
        else f"CPU ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"
    )
    lines = [
        "# Sticker-stage speed: fast path vs naive vs paper-faithful",
        "",
        f"Command: `python -m gsticker_plugin.bench.sticker --load-checkpoint {cfg.load_checkpoint} --seconds {cfg.seconds:g} "
        f"{'--data ' + str(cfg.data) + ' ' if cfg.data else ''}--variants {' '.join(cfg.variants)} "
        f"{'--append ' if cfg.append else ''}--output {cfg.output}`",
        f"Device: {dev}; torch {torch.__version__}; date {time.strftime('%Y-%m-%d')}.",
        f"Budget {cfg.seconds:g} s of training per variant (the last run; `--append` keeps earlier rows, whose own budget is "
        f"the 'train s' column); held-out bit accuracy on {cfg.monitor_views} novel views, owner message, no attack.",
        "",
        "| variant | heads params | train s | steps/s | steps | time to >= 99% bits | final held-out bit acc | same, clean renders (chance = 0.5) | final PSNR marked vs clean | pool render (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        fin = r["final"] or {}
        t99 = f"{r['seconds_to_99']:.0f} s" if r["seconds_to_99"] is not None else "not reached"
        lines.append(
            f"| {r['variant']} | {r['heads_parameters']:,} | {r['train_seconds']:.0f} | {r['steps_per_second']:.2f} | {r['steps']} | {t99} | "
            f"{fin.get('heldout_bit_acc', float('nan')):.4f} | {fin.get('heldout_clean_bit_acc', float('nan')):.4f} | "
            f"{fin.get('heldout_psnr', float('nan')):.2f} dB | {r['pool_seconds']:.0f} |"
        )
    cfg.output.write_text("\n".join(lines) + "\n")
    cfg.output.with_suffix(".json").write_text(json.dumps(results, indent=2))
    print("\n".join(lines))


def trainer_config(cfg: StickerBenchConfig, name: str):
    """The variant's trainer config: the shared settings, then the variant's overrides."""
    tcfg = sticker_trainer_config(
        cfg.load_checkpoint,
        cfg.data,
        Path("outputs/bench-sticker"),
        name,
        cfg.max_steps,
        (cfg.pool_train_views, cfg.pool_novel_views, cfg.monitor_views),
        "cuda" if torch.cuda.is_available() else "cpu",
    )
    for k, v in variant_overrides(name).items():
        obj = tcfg.pipeline
        *path, last = k.split(".")
        for part in path:
            obj = getattr(obj, part)
        setattr(obj, last, v)
    return tcfg


def main(cfg: StickerBenchConfig) -> None:
    results: List[Dict[str, object]] = []
    js = cfg.output.with_suffix(".json")
    if cfg.append and js.is_file():
        results = [r for r in json.loads(js.read_text()) if r["variant"] not in cfg.variants]
    for name in cfg.variants:
        print(f"== {name}", flush=True)
        results.append(run_variant(cfg, name, trainer_config(cfg, name)))
        write_report(cfg, results)


if __name__ == "__main__":
    main(tyro.cli(StickerBenchConfig))


def variant_overrides(name: str) -> Dict[str, object]:
    if name == "fast":
        return {"fast_path": True}
    if name == "naive":
        return {"fast_path": False}
    if name == "paper":
        return {"fast_path": True, "heads.backbone": "vgg16"}
    if name == "owner":  # the authors' released code: one fixed message (an honesty check, not a recommendation)
        return {"fast_path": True, "owner_message_prob": 1.0}
    raise ValueError(f"unknown variant {name!r}; use fast, naive, paper or owner")


def sticker_trainer_config(
    load_checkpoint: Path,
    data: Optional[Path],
    output_dir: Path,
    experiment: str,
    steps: int,
    pool_views: Tuple[int, int, int],
    device: str = "cpu",
):
    """An ``ns-train geometrysticker`` config for an in-process benchmark: base, data, output folder, steps and the
    pool's (training, novel, held-out) view counts."""
    # deferred: an ns-train entry point module, not a library
    from method_configs.geometrysticker import geometrysticker_config

    tcfg = geometrysticker_config(steps)
    tcfg.load_checkpoint = load_checkpoint
    tcfg.data = data
    tcfg.machine.device_type = device
    tcfg.output_dir = output_dir
    tcfg.experiment_name = experiment
    tcfg.set_timestamp()
    p = tcfg.pipeline
    p.pool_train_views, p.pool_novel_views, p.monitor_views = pool_views
    p.train_heads = True  # the held-out bit accuracy is the extractor's
    return tcfg
