"""Blind-extractor probe: can a per-key sticker term steer a frozen, whitened random CNN on held-out views?

    python -m gsticker_plugin.bench.blind --data ../shared/data/lego100 --output-dir outputs/bench-blind

Builds the fast-path pool of the shared lego100 base, measures the frozen extractor's output spread over clean
views, whitens it over distorted clean pool views, *then* draws the message, and trains only the blind term
(the informed sticker stays off) against the frozen extractor. Logs held-out (never trained on, never whitened
on) and training-view bit accuracy, clean-render matches and PSNR every ``--every`` steps into ``curve.jsonl``
and checks the issue's stop rules F1-F4.
"""

from __future__ import annotations

import json
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch
import torch.nn.functional as F
import tyro

from gsticker_plugin import metrics
from gsticker_plugin.attacks import RandomDistortion, RandomDistortionConfig
from gsticker_plugin.extractor import BlindExtractor, ExtractorConfig, LearnedExtractor, LearnedExtractorConfig
from gsticker_plugin.fastpath import ViewCache, render_signs, sign_jacobian
from gsticker_plugin.sticker import BlindTerm, composite


@dataclass
class BlindProbeConfig:
    load_checkpoint: Path = Path(
        "../shared/checkpoints/lego100-nerfacto-small/nerfacto/base/nerfstudio_models/step-000002999.ckpt"
    )
    data: Optional[Path] = None
    output_dir: Path = Path("outputs/bench-blind")
    pool_train_views: int = 48
    pool_novel_views: int = 48
    heldout_views: int = 24
    steps: int = 600
    every: int = 50
    views_per_step: int = 4
    lr: float = 1e-3
    loose_psnr: float = 25.0
    """PSNR budget of the first phase (no distortions)."""
    tight_psnr: float = 36.0
    loose_steps: int = 300
    ramp_steps: int = 300
    """Steps over which the budget tightens and the distortions ramp in after the loose phase."""
    distortions: bool = True
    hidden: int = 32
    frequencies: int = 6
    amplitude: float = 1.0
    """Blind term's largest density change, in units of the gate's sticker scale."""
    extractor: ExtractorConfig = field(default_factory=ExtractorConfig)
    whiten_distortions: int = 4
    """Distorted copies of each clean pool view in the whitening set (plus the clean view)."""
    seed: int = 0
    message: Optional[str] = None
    route: str = "random"
    """random: train a blind term against a frozen random CNN (item 1-2); linear: pre-train an extractor on synthetic
    linearised marks of random messages (item 3), then freeze it."""
    work_psnr: float = 36.0
    """Linear route: the mark's strength (PSNR of marked vs clean) the extractor is pre-trained for."""
    start_psnr: float = 25.0
    batch: int = 32
    anneal_steps: int = 1000
    distort_after: int = 1500
    """Linear route: distortions ramp in over ``anneal_steps`` from this step."""


def setup_pool(cfg: BlindProbeConfig):
    # deferred: an ns-train entry point module, not a library
    from method_configs.geometrysticker import geometrysticker_config

    tcfg = geometrysticker_config(10)
    tcfg.load_checkpoint = cfg.load_checkpoint
    tcfg.data = cfg.data
    tcfg.machine.device_type = "cpu"
    tcfg.output_dir = cfg.output_dir / "run"
    tcfg.experiment_name = "blind-probe"
    tcfg.set_timestamp()
    p = tcfg.pipeline
    p.pool_train_views, p.pool_novel_views, p.monitor_views = (
        cfg.pool_train_views,
        cfg.pool_novel_views,
        cfg.heldout_views,
    )
    p.pool_cache = cfg.output_dir / "pool.pt"
    p.message = "0" * 48  # placeholder for the informed sticker, which stays off here
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    trainer = tcfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipe = trainer.pipeline
    if not pipe.pool:
        pipe.build_pool()
    return pipe


def render_blind(view: ViewCache, wrap, term: BlindTerm, background: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    h, w = view.hw
    density = view.density
    psi, open_ = wrap.open_samples(density)
    delta = torch.zeros_like(density)
    if open_.any():
        pos = wrap.normalize(view.positions.float()[open_])
        delta[open_] = psi[open_] * wrap.gate.scale * term(pos)
    rgb = view.rgb.float()
    marked, _ = composite(torch.relu(density + delta), rgb, view.deltas, background)
    clean, _ = composite(density, rgb, view.deltas, background)
    flat = view.image.reshape(-1, 3)
    change = torch.zeros_like(flat).index_add(0, view.active, marked - clean)
    return (flat + change).clamp(0.0, 1.0).reshape(h, w, 3).permute(2, 0, 1), psi


def quantize(img: torch.Tensor) -> torch.Tensor:
    """8-bit rounding (straight-through), as a saved render."""
    return img + ((img * 255).round() / 255 - img).detach()


def main(cfg: BlindProbeConfig) -> None:
    torch.manual_seed(cfg.seed)
    pipe = setup_pool(cfg)
    if cfg.route == "linear":
        return linear_route(cfg, pipe)
    wrap = pipe.model.final_wrap
    bg = pipe.model.background_color()
    pool, held = pipe.pool, pipe.monitor
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    distort = RandomDistortion(RandomDistortionConfig())
    out = cfg.output_dir
    log = (out / "curve.jsonl").open("w")

    # 1. the extractor, its spread over clean views, its whitening: all before the message exists
    ext = BlindExtractor(cfg.extractor)
    clean_pool = torch.stack([v.image.permute(2, 0, 1) for v in pool])
    raw = ext.cnn(clean_pool)
    spread = raw.std(0)
    batches = [clean_pool] + [distort(clean_pool, generator=gen) for _ in range(cfg.whiten_distortions)]
    wstats = ext.fit_whitening(batches)
    info: Dict[str, object] = {
        "extractor_sha256": ext.sha256(),
        "raw_spread_across_clean_views": {
            "min": float(spread.min()),
            "median": float(spread.median()),
            "max": float(spread.max()),
        },
        "whitening": wstats,
    }
    # 2. the message, drawn after the extractor is fixed
    message = (
        metrics.message_to_bits(cfg.message, 48)
        if cfg.message
        else torch.tensor([int(b) for b in format(secrets.randbits(48), "048b")])
    )
    heldc = torch.stack([v.image.permute(2, 0, 1) for v in held])
    with torch.no_grad():
        z_clean = ext(quantize(heldc))
    clean_matches = metrics.count_matches(metrics.decode_bits(z_clean), message)
    info["heldout_clean_matches"] = clean_matches.tolist()
    print(json.dumps(info, indent=1), flush=True)
    (out / "extractor.json").write_text(json.dumps(info, indent=1))

    term = BlindTerm(cfg.frequencies, cfg.hidden, cfg.amplitude)
    opt = torch.optim.Adam(term.parameters(), lr=cfg.lr)
    target = message.float()[None]
    t0 = time.time()
    curve: List[Dict[str, float]] = []
    for step in range(cfg.steps + 1):
        if step % cfg.every == 0:
            with torch.no_grad():
                imgs = torch.stack([render_blind(v, wrap, term, bg)[0] for v in held])
                z = ext(quantize(imgs))
                acc = metrics.bit_accuracy(metrics.decode_bits(z), message)
                psnr = metrics.psnr(imgs, heldc)
                tr = pool[: len(held)]
                timgs = torch.stack([render_blind(v, wrap, term, bg)[0] for v in tr])
                tacc = metrics.bit_accuracy(metrics.decode_bits(ext(quantize(timgs))), message)
            row = {
                "step": step,
                "seconds": time.time() - t0,
                "heldout_bit_acc": float(acc.mean()),
                "heldout_views_41": int((metrics.count_matches(metrics.decode_bits(z), message) >= 41).sum()),
                "train_bit_acc": float(tacc.mean()),
                "heldout_psnr": float(psnr.mean()),
                "heldout_psnr_min": float(psnr.min()),
                "z_abs_mean": float(z.abs().mean()),
            }
            curve.append(row)
            log.write(json.dumps(row) + "\n")
            log.flush()
            print(row, flush=True)
        if step == cfg.steps:
            break
        frac = min(1.0, max(0.0, (step - cfg.loose_steps) / max(1, cfg.ramp_steps)))
        psnr_budget = cfg.loose_psnr + frac * (cfg.tight_psnr - cfg.loose_psnr)
        idx = torch.randint(0, len(pool), (cfg.views_per_step,), generator=gen)
        marked, clean, psis = [], [], []
        for i in idx.tolist():
            img, psi = render_blind(pool[i], wrap, term, bg)
            marked.append(img)
            clean.append(pool[i].image.permute(2, 0, 1))
            psis.append(psi.reshape(-1))
        marked_t, clean_t = torch.stack(marked), torch.stack(clean)
        mse = F.mse_loss(marked_t, clean_t)
        budget = 10.0 ** (-psnr_budget / 10.0)
        content = 10.0 * F.relu(mse / budget - 1.0)
        x = quantize(marked_t)
        if cfg.distortions and frac > 0 and float(torch.rand(1, generator=gen)) < frac:
            x = distort(x, cover=clean_t, generator=gen)
        z = ext(x)
        msg_loss = F.binary_cross_entropy_with_logits(z, target.expand_as(z))
        loss = msg_loss + content
        opt.zero_grad()
        loss.backward()
        opt.step()
    info["curve"] = curve
    info["config"] = json.loads(json.dumps(vars(cfg), default=str))
    (out / "result.json").write_text(json.dumps(info, indent=1))


def linear_route(cfg: BlindProbeConfig, pipe) -> None:
    """Item 3: per-bit render derivatives R of every pool view, synthetic I0 + alpha R s for random s, an extractor
    trained on them (strength annealed), held-out views read from exact renders."""
    wrap = pipe.model.final_wrap
    bg = pipe.model.background_color()
    pool, held = pipe.pool, pipe.monitor
    k = pipe.config.model.num_bits
    out = cfg.output_dir
    log = (out / "curve-linear.jsonl").open("w")
    t0 = time.time()
    jac_path = out / "jacobians.pt"
    if jac_path.is_file():
        saved = torch.load(jac_path, weights_only=True)
        r_pool, r_held = saved["pool"], saved["held"]
    else:
        r_pool = [sign_jacobian(v, wrap, k, bg).half() for v in pool]
        r_held = [sign_jacobian(v, wrap, k, bg).half() for v in held]
        torch.save({"pool": r_pool, "held": r_held}, jac_path)
    print(f"jacobians: {time.time() - t0:.0f} s", flush=True)
    i0_pool = torch.stack([v.image for v in pool])  # [N H W 3]
    gen = torch.Generator().manual_seed(cfg.seed + 2)
    # strength: alpha for a PSNR, from the mean power of R s over pool views and random s
    power = []
    for r in r_pool[:16]:
        s = torch.randint(0, 2, (8, k), generator=gen).float() * 2 - 1
        power.append((torch.einsum("bk,khwc->bhwc", s, r.float()) ** 2).mean())
    mse1 = float(torch.stack(power).mean())

    def alpha_for(psnr: float) -> float:
        return (10.0 ** (-psnr / 10.0) / mse1) ** 0.5

    a_work = alpha_for(cfg.work_psnr)
    print(f"mse of R s: {mse1:.3e}; alpha at {cfg.work_psnr} dB: {a_work:.3f}", flush=True)
    # held-out evaluation set: exact renders at the working strength, fixed random messages
    egen = torch.Generator().manual_seed(cfg.seed + 3)
    eval_msgs = torch.randint(0, 2, (len(held), k), generator=egen)
    exact, lin_err = [], []
    with torch.no_grad():
        for v, r, msg in zip(held, r_held, eval_msgs):
            signs = msg.float() * 2 - 1
            img = render_signs(v, wrap, signs, bg, gain=a_work, clamp=False)
            lin = v.image + a_work * torch.einsum("k,khwc->hwc", signs, r.float())
            lin_err.append(float((img - lin).norm() / (img - v.image).norm().clamp_min(1e-12)))
            exact.append(img.clamp(0, 1))
    exact_t = quantize(torch.stack(exact).permute(0, 3, 1, 2))
    clean_t = quantize(torch.stack([v.image for v in held]).permute(0, 3, 1, 2))
    exact_psnr = metrics.psnr(exact_t, clean_t)
    print(
        f"held-out exact renders: PSNR {float(exact_psnr.mean()):.2f} dB (min {float(exact_psnr.min()):.2f}); "
        f"linearisation error e = {sum(lin_err) / len(lin_err):.3f} (max {max(lin_err):.3f})",
        flush=True,
    )
    ext = LearnedExtractor(LearnedExtractorConfig(seed=cfg.seed))
    opt = torch.optim.Adam(ext.parameters(), lr=cfg.lr)
    distort = RandomDistortion(RandomDistortionConfig())
    info: Dict[str, object] = {
        "mse_unit": mse1,
        "alpha_work": a_work,
        "heldout_exact_psnr": float(exact_psnr.mean()),
        "linearisation_error_mean": sum(lin_err) / len(lin_err),
        "linearisation_error_max": max(lin_err),
        "curve": [],
    }
    t0 = time.time()
    for step in range(cfg.steps + 1):
        if step % cfg.every == 0:
            ext.eval()
            with torch.no_grad():
                acc = metrics.bit_accuracy(metrics.decode_bits(ext(exact_t)), eval_msgs)
                cm = metrics.count_matches(metrics.decode_bits(ext(clean_t)), eval_msgs)
                m = metrics.count_matches(metrics.decode_bits(ext(exact_t)), eval_msgs)
            ext.train()
            row = {
                "step": step,
                "seconds": time.time() - t0,
                "samples": step * cfg.batch,
                "heldout_bit_acc": float(acc.mean()),
                "heldout_views_41": int((m >= 41).sum()),
                "clean_mean_matches": float(cm.float().mean()),
                "clean_max_matches": int(cm.max()),
            }
            info["curve"].append(row)
            log.write(json.dumps(row) + "\n")
            log.flush()
            print(row, flush=True)
        if step == cfg.steps:
            break
        frac = min(1.0, step / max(1, cfg.anneal_steps))
        psnr_t = cfg.start_psnr + frac * (cfg.work_psnr - cfg.start_psnr)
        a = alpha_for(psnr_t)
        idx = torch.randint(0, len(pool), (cfg.batch,), generator=gen)
        s = torch.randint(0, 2, (cfg.batch, k), generator=gen)
        signs = s.float() * 2 - 1
        x = torch.stack(
            [i0_pool[i] + a * torch.einsum("k,khwc->hwc", sg, r_pool[i].float()) for i, sg in zip(idx.tolist(), signs)]
        )
        x = quantize(x.clamp(0, 1).permute(0, 3, 1, 2))
        dfrac = min(1.0, max(0.0, (step - cfg.distort_after) / max(1, cfg.anneal_steps)))
        if cfg.distortions and dfrac > 0 and float(torch.rand(1, generator=gen)) < dfrac:
            x = distort(x, generator=gen)
        loss = F.binary_cross_entropy_with_logits(ext(x), s.float())
        opt.zero_grad()
        loss.backward()
        opt.step()
    info["extractor_sha256"] = ext.sha256()
    torch.save(ext.state_dict(), out / "extractor-linear.pt")
    info["config"] = json.loads(json.dumps(vars(cfg), default=str))
    (out / "result-linear.json").write_text(json.dumps(info, indent=1))


if __name__ == "__main__":
    main(tyro.cli(BlindProbeConfig))
