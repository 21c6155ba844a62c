"""Sticker-stage speed: a geometrysticker trainer for one strategy (fast path, naive, paper-faithful), trained for a
wall-clock budget with its held-out accuracy monitored."""

from __future__ import annotations

import time
from typing import Any, Dict, List, Optional


def run_variant(cfg: Any, name: str, tcfg) -> Dict[str, object]:
    """Train ``tcfg`` (an ``ns-train geometrysticker`` config) in process for ``cfg.seconds`` of wall clock or
    ``cfg.max_steps`` steps, its pool cached at ``cfg.pool_cache``; the held-out curve every
    ``cfg.steps_per_monitor`` steps and the time to 99 % held-out bit accuracy."""
    p = tcfg.pipeline
    p.steps_per_monitor = cfg.steps_per_monitor
    p.pool_cache = cfg.pool_cache
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
