"""Sticker-stage speed: a geometrysticker trainer for one strategy (fast path, naive, paper-faithful), trained for a
wall-clock budget with its held-out accuracy monitored."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch


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


def run_variant(cfg: Any, name: str) -> Dict[str, object]:
    tcfg = sticker_trainer_config(
        cfg.load_checkpoint,
        cfg.data,
        Path("outputs/bench-sticker"),
        name,
        cfg.max_steps,
        (cfg.pool_train_views, cfg.pool_novel_views, cfg.monitor_views),
        "cuda" if torch.cuda.is_available() else "cpu",
    )
    p = tcfg.pipeline
    p.steps_per_monitor = cfg.steps_per_monitor
    p.pool_cache = cfg.pool_cache
    for k, v in variant_overrides(name).items():
        obj = p
        *path, last = k.split(".")
        for part in path:
            obj = getattr(obj, part)
        setattr(obj, last, v)
    if cfg.pool_cache is not None:
        cfg.pool_cache.parent.mkdir(parents=True, exist_ok=True)
    trainer = tcfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipe = trainer.pipeline
    t_pool = time.time()
    if not pipe.pool and not pipe.monitor:
        pipe.build_pool()
    pool_seconds = time.time() - t_pool
    if not p.fast_path:
        p.steps_per_monitor = cfg.steps_per_monitor  # naive steps are slow: monitored explicitly below
    opt = trainer.optimizers
    t0 = time.time()
    curve: List[Dict[str, float]] = []
    step = 0
    reached: Optional[float] = None
    while step < cfg.max_steps and time.time() - t0 < cfg.seconds:
        opt.zero_grad_all()
        _, loss_dict, _ = pipe.get_train_loss_dict(step)
        sum(loss_dict.values()).backward()
        opt.optimizer_step_all()
        opt.scheduler_step_all(step)
        step += 1
        if step % cfg.steps_per_monitor == 0:
            elapsed = time.time() - t0
            m = pipe.monitor_metrics()
            curve.append({"step": step, "seconds": elapsed, **{k: float(v) for k, v in m.items()}})
            print(
                f"  [{name}] step {step} {elapsed:.0f}s held-out bit acc {curve[-1]['heldout_bit_acc']:.4f} "
                f"(clean {curve[-1]['heldout_clean_bit_acc']:.4f}) psnr {curve[-1]['heldout_psnr']:.2f}",
                flush=True,
            )
            if reached is None and curve[-1]["heldout_bit_acc"] >= 0.99:
                reached = elapsed
    seconds = time.time() - t0
    return {
        "variant": name,
        "steps": step,
        "train_seconds": seconds,
        "steps_per_second": step / max(seconds, 1e-9),
        "pool_seconds": pool_seconds,
        "seconds_to_99": reached,
        "final": curve[-1] if curve else {},
        "heads_parameters": sum(q.numel() for q in pipe.heads.parameters()),
        "curve": curve,
    }
