"""Blind-extractor benchmark: the routes of reading the owner's message from renders alone, with their stop rules.

    python -m gsticker_plugin.bench.blind --data ../shared/data/lego100 --doc docs/bench-blind.md

On the fast-path pool of the shared lego100 base (pool views for training, ``--heldout-views`` orbit views never
trained or whitened on), in one process:

* ``random`` (issue items 1-2): a frozen random CNN on the V channel, its output spread over clean views measured,
  whitened over distorted clean pool views; *then* the message is drawn and a per-key blind term (an MLP on
  gamma(x) under the gate; the informed sticker stays off) is trained against it. Stop rule F1: held-out bit
  accuracy < 0.75 after 300 steps with the PSNR budget at 25 dB and no distortions.
* ``linear`` (item 3): per-bit render derivatives R of the (bilinear) sticker for every view, an extractor
  pre-trained on synthetic ``I0 + alpha R s`` for random s (strength annealed to ``--work-psnr``), evaluated on
  exact renders of held-out views; the linearisation error e at the working strength (F5 > 0.3) and stop rule F6:
  message loss > 0.65 after 20k synthetic samples. After training the extractor is frozen, then a message is drawn
  and held-out views read with the bits and with the soft correlation score (item 6), beside clean renders.

Curves go to ``OUTPUT/curve-<route>.jsonl`` as they are measured; the page and its JSON are written at the end.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch
import torch.nn.functional as F
import tyro

from gsticker_plugin import metrics
from gsticker_plugin.attacks import RandomDistortion, RandomDistortionConfig
from gsticker_plugin.bench.sticker import sticker_trainer_config
from gsticker_plugin.extractor import (
    BlindExtractor,
    ExtractorConfig,
    LearnedExtractor,
    LearnedExtractorConfig,
    state_sha256,
)
from gsticker_plugin.fastpath import render_offset, render_signs, sign_jacobian
from gsticker_plugin.key import random_message
from gsticker_plugin.machine import machine_info
from gsticker_plugin.metrics import as_8_bit
from gsticker_plugin.sticker import BlindTerm


@dataclass
class BlindBenchConfig:
    """Run the blind-extractor routes on one base and write their curves, stop rules and page."""

    load_checkpoint: Path = Path(
        "../shared/checkpoints/lego100-nerfacto-small/nerfacto/base/nerfstudio_models/step-000002999.ckpt"
    )
    """Base run checkpoint."""
    data: Optional[Path] = None
    """Dataset, if the base's recorded path does not exist from here."""
    routes: Tuple[str, ...] = ("random", "linear")
    """Which routes to run (random, linear)."""
    output_dir: Path = Path("outputs/bench-blind")
    """Pool cache, Jacobians, curves and the run folder."""
    doc: Path = Path("docs/bench-blind.md")
    """Page to write (its JSON beside it)."""
    pool_train_views: int = 48
    pool_novel_views: int = 48
    heldout_views: int = 24
    every: int = 50
    """Measure the curves every this many steps."""
    seed: int = 0
    # random route
    random_steps: int = 600
    views_per_step: int = 4
    blind_lr: float = 1e-3
    loose_psnr: float = 25.0
    """PSNR budget of the first phase (no distortions)."""
    tight_psnr: float = 36.0
    loose_steps: int = 300
    ramp_steps: int = 300
    """Steps over which the budget tightens and the distortions ramp in after the loose phase."""
    hidden: int = 32
    frequencies: int = 6
    amplitude: float = 1.0
    """Blind term's largest density change, in units of the gate's sticker scale."""
    extractor: ExtractorConfig = field(default_factory=ExtractorConfig)
    whiten_distortions: int = 4
    """Distorted copies of each clean pool view in the whitening set (plus the clean view)."""
    # linear route
    linear_steps: int = 1500
    batch: int = 32
    lr: float = 1e-3
    work_psnr: float = 36.0
    """The mark's strength (PSNR of marked vs clean) the extractor is pre-trained for and evaluated at."""
    start_psnr: float = 25.0
    anneal_steps: int = 1000
    keep: bool = True
    """Keep the other routes' results already in the page's JSON (each route records its own command)."""


CHANGED = {"linear_steps": 1500, "lr": 1e-3, "every": 50, "random_steps": 600, "work_psnr": 36.0}
"""Options whose value, when changed, the recorded command spells out."""


def setup_pool(cfg: BlindBenchConfig):
    """A sticker-stage pipeline on the base with its fast-path pool rendered (or reused from the cache)."""
    tcfg = sticker_trainer_config(
        cfg.load_checkpoint,
        cfg.data,
        cfg.output_dir / "run",
        "bench-blind",
        10,
        (cfg.pool_train_views, cfg.pool_novel_views, cfg.heldout_views),
    )
    p = tcfg.pipeline
    p.seed = cfg.seed
    p.pool_cache = cfg.output_dir / "pool.pt"
    p.key_path = cfg.output_dir / "run" / "unused.gskey"
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    trainer = tcfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipe = trainer.pipeline
    if not pipe.pool:
        pipe.build_pool()
    return pipe


def quantize(img: torch.Tensor) -> torch.Tensor:
    """8-bit rounding as a saved render, straight-through for gradients."""
    return img + (as_8_bit(img) - img).detach()


def chw(images: List[torch.Tensor]) -> torch.Tensor:
    return torch.stack(images).permute(0, 3, 1, 2)


def read_views(logits: torch.Tensor, message: torch.Tensor) -> Dict[str, Any]:
    """Bits and soft score of views' logits against the message: per-view matches, soft p-values, pooled p-value."""
    matches = metrics.count_matches(metrics.decode_bits(logits), message)
    return {
        "bit_acc": float(matches.float().mean() / message.numel()),
        "mean_matches": float(matches.float().mean()),
        "max_matches": int(matches.max()),
        "views_41": int((matches >= metrics.min_matches_for_fpr(message.numel(), 1e-6)).sum()),
        "soft_pvalue_median": float(torch.tensor([metrics.soft_score_pvalue(z, message) for z in logits]).median()),
        "soft_pvalue_pooled": metrics.soft_score_pvalue(logits, message),
    }


class Curve:
    """Rows measured during a route, appended to a JSONL file as they come."""

    def __init__(self, path: Path) -> None:
        self.rows: List[Dict[str, Any]] = []
        self.file = path.open("w")

    def add(self, row: Dict[str, Any]) -> None:
        self.rows.append(row)
        self.file.write(json.dumps(row) + "\n")
        self.file.flush()
        print({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}, flush=True)


def default_init_spread(images: torch.Tensor, config: ExtractorConfig) -> Dict[str, float]:
    """The same layer shapes with PyTorch's default initialisation and no normalisation: its per-bit output spread
    across ``images`` (the trap: nearly a constant function of the image)."""
    torch.manual_seed(config.seed)
    chans = [1, config.widths[0], *config.widths]
    layers: List[torch.nn.Module] = []
    for i, (cin, cout) in enumerate(zip(chans[:-1], chans[1:])):
        layers += [torch.nn.Conv2d(cin, cout, 3, stride=1 if i == 0 else 2, padding=1), torch.nn.GELU()]
    net = torch.nn.Sequential(*layers)
    head = torch.nn.Linear(chans[-1], config.num_bits)
    with torch.no_grad():
        spread = head(net(images.amax(dim=1, keepdim=True) - 0.5).mean(dim=(-2, -1))).std(0)
    return {"min": float(spread.min()), "median": float(spread.median()), "max": float(spread.max())}


def random_route(cfg: BlindBenchConfig, pipe) -> Dict[str, Any]:
    wrap, bg = pipe.model.final_wrap, pipe.model.background_color()
    pool, held = pipe.pool, pipe.monitor
    k = pipe.config.model.num_bits
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    distort = RandomDistortion(RandomDistortionConfig())
    ext = BlindExtractor(cfg.extractor)
    clean_pool = chw([v.image for v in pool])
    spread = ext.cnn(clean_pool).std(0)
    wstats = ext.fit_whitening(
        [clean_pool] + [distort(clean_pool, generator=gen) for _ in range(cfg.whiten_distortions)]
    )
    res: Dict[str, Any] = {
        "extractor_sha256": ext.sha256(),
        "raw_spread_across_clean_views": {
            k_: float(f(spread)) for k_, f in (("min", torch.min), ("median", torch.median), ("max", torch.max))
        },
        "whitening": wstats,
        "default_init_spread": default_init_spread(clean_pool, cfg.extractor),
    }
    message = random_message(k)  # after the extractor and its whitening are fixed
    heldc = quantize(chw([v.image for v in held]))
    term = BlindTerm(cfg.frequencies, cfg.hidden, cfg.amplitude)
    opt = torch.optim.Adam(term.parameters(), lr=cfg.blind_lr)
    curve = Curve(cfg.output_dir / "curve-random.jsonl")
    t0 = time.time()

    def renders(views):
        return chw([render_offset(v, wrap, term, bg) for v in views])

    for step in range(cfg.random_steps + 1):
        if step % cfg.every == 0:
            with torch.no_grad():
                imgs = renders(held)
                z = ext(quantize(imgs))
                train = ext(quantize(renders(pool[: len(held)])))
                psnr = metrics.psnr(imgs, heldc)
            curve.add(
                {
                    "step": step,
                    "seconds": time.time() - t0,
                    "heldout_bit_acc": read_views(z, message)["bit_acc"],
                    "train_bit_acc": read_views(train, message)["bit_acc"],
                    "heldout_psnr": float(psnr.mean()),
                }
            )
        if step == cfg.random_steps:
            break
        frac = min(1.0, max(0.0, (step - cfg.loose_steps) / max(1, cfg.ramp_steps)))
        budget = 10.0 ** (-(cfg.loose_psnr + frac * (cfg.tight_psnr - cfg.loose_psnr)) / 10.0)
        idx = torch.randint(0, len(pool), (cfg.views_per_step,), generator=gen).tolist()
        marked, clean = renders([pool[i] for i in idx]), chw([pool[i].image for i in idx])
        content = 10.0 * F.relu(F.mse_loss(marked, clean) / budget - 1.0)
        x = quantize(marked)
        if frac > 0 and float(torch.rand(1, generator=gen)) < frac:
            x = distort(x, cover=clean, generator=gen)
        z = ext(x)
        loss = F.binary_cross_entropy_with_logits(z, message.float()[None].expand_as(z)) + content
        opt.zero_grad()
        loss.backward()
        opt.step()
    at300 = next((r for r in curve.rows if r["step"] >= 300), curve.rows[-1])
    res["curve"] = curve.rows
    res["F1"] = {
        "step": at300["step"],
        "heldout_bit_acc": at300["heldout_bit_acc"],
        "heldout_psnr": at300["heldout_psnr"],
        "fired": at300["heldout_bit_acc"] < 0.75,
    }
    with torch.no_grad():
        res["final"] = {
            "marked": read_views(ext(quantize(renders(held))), message),
            "clean": read_views(ext(heldc), message),
        }
    return res


def linear_route(cfg: BlindBenchConfig, pipe) -> Dict[str, Any]:
    wrap, bg = pipe.model.final_wrap, pipe.model.background_color()
    pool, held = pipe.pool, pipe.monitor
    k = pipe.config.model.num_bits
    t0 = time.time()
    jac_path = cfg.output_dir / "jacobians.pt"
    jac_id = f"{state_sha256(wrap.sticker)}-{len(pool)}-{len(held)}-{cfg.seed}"
    saved = torch.load(jac_path, weights_only=True) if jac_path.is_file() else {}
    if saved.get("id") == jac_id:
        r_pool, r_held = saved["pool"], saved["held"]
    else:
        r_pool = [sign_jacobian(v, wrap, k, bg).half() for v in pool]
        r_held = [sign_jacobian(v, wrap, k, bg).half() for v in held]
        torch.save({"id": jac_id, "pool": r_pool, "held": r_held}, jac_path)
    jac_seconds = time.time() - t0
    gen = torch.Generator().manual_seed(cfg.seed + 2)

    def synth(view, r, signs, alpha):
        return (view.image + alpha * torch.einsum("k,khwc->hwc", signs, r.float())).clamp(0, 1)

    power = []
    for r in r_pool[:16]:
        s = torch.randint(0, 2, (8, k), generator=gen).float() * 2 - 1
        power.append((torch.einsum("bk,khwc->bhwc", s, r.float()) ** 2).mean())
    mse1 = float(torch.stack(power).mean())

    def alpha_for(psnr: float) -> float:
        return (10.0 ** (-psnr / 10.0) / mse1) ** 0.5

    a_work = alpha_for(cfg.work_psnr)
    egen = torch.Generator().manual_seed(cfg.seed + 3)
    eval_msgs = torch.randint(0, 2, (len(held), k), generator=egen)
    eval_signs = eval_msgs.float() * 2 - 1
    exact, lin_err = [], []
    with torch.no_grad():
        for v, r, sg in zip(held, r_held, eval_signs):
            img = render_signs(v, wrap, sg, bg, gain=a_work, clamp=False)
            lin = v.image + a_work * torch.einsum("k,khwc->hwc", sg, r.float())
            lin_err.append(float((img - lin).norm() / (img - v.image).norm().clamp_min(1e-12)))
            exact.append(img.clamp(0, 1))
        sets = {
            "heldout_exact": quantize(chw(exact)),
            "heldout_synthetic": quantize(chw([synth(v, r, sg, a_work) for v, r, sg in zip(held, r_held, eval_signs)])),
            "pool_exact": quantize(
                chw([render_signs(v, wrap, sg, bg, gain=a_work) for v, sg in zip(pool, eval_signs)])
            ),
            "pool_synthetic": quantize(chw([synth(v, r, sg, a_work) for v, r, sg in zip(pool, r_pool, eval_signs)])),
        }
    heldc = quantize(chw([v.image for v in held]))
    exact_psnr = metrics.psnr(sets["heldout_exact"], heldc)
    res: Dict[str, Any] = {
        "jacobian_seconds": jac_seconds,
        "mse_at_unit_strength": mse1,
        "alpha_work": a_work,
        "heldout_exact_psnr": float(exact_psnr.mean()),
        "heldout_exact_psnr_min": float(exact_psnr.min()),
        "F5": {"linearisation_error_mean": sum(lin_err) / len(lin_err), "max": max(lin_err)},
    }
    res["F5"]["fired"] = res["F5"]["linearisation_error_mean"] > 0.3
    ext = LearnedExtractor(LearnedExtractorConfig(seed=cfg.seed, num_bits=k))
    opt = torch.optim.Adam(ext.parameters(), lr=cfg.lr)
    curve = Curve(cfg.output_dir / "curve-linear.jsonl")
    loss_avg = float("nan")
    t0 = time.time()
    for step in range(cfg.linear_steps + 1):
        if step % cfg.every == 0:
            ext.eval()
            with torch.no_grad():
                accs = {
                    n: float(metrics.bit_accuracy(metrics.decode_bits(ext(x)), eval_msgs).mean())
                    for n, x in sets.items()
                }
            ext.train()
            curve.add(
                {
                    "step": step,
                    "samples": step * cfg.batch,
                    "seconds": time.time() - t0,
                    "message_loss": loss_avg,
                    **accs,
                }
            )
        if step == cfg.linear_steps:
            break
        frac = min(1.0, step / max(1, cfg.anneal_steps))
        a = alpha_for(cfg.start_psnr + frac * (cfg.work_psnr - cfg.start_psnr))
        idx = torch.randint(0, len(pool), (cfg.batch,), generator=gen).tolist()
        s = torch.randint(0, 2, (cfg.batch, k), generator=gen)
        x = quantize(chw([synth(pool[i], r_pool[i], sg, a) for i, sg in zip(idx, s.float() * 2 - 1)]))
        loss = F.binary_cross_entropy_with_logits(ext(x), s.float())
        loss_avg = float(loss) if loss_avg != loss_avg else 0.9 * loss_avg + 0.1 * float(loss)
        opt.zero_grad()
        loss.backward()
        opt.step()
    ext.eval()
    at20k = next((r for r in curve.rows if r["samples"] >= 20000), curve.rows[-1])
    res["curve"] = curve.rows
    res["F6"] = {
        "samples": at20k["samples"],
        "message_loss": at20k["message_loss"],
        "fired": at20k["message_loss"] > 0.65,
    }
    # frozen here and whitened over clean (and distorted) pool renders; the owner's message is drawn below
    white = BlindExtractor(
        ExtractorConfig(num_bits=k, pca_eps=cfg.extractor.pca_eps), network=ext.requires_grad_(False)
    )
    dgen = torch.Generator().manual_seed(cfg.seed + 4)
    distort = RandomDistortion(RandomDistortionConfig())
    clean_pool = chw([v.image for v in pool])
    with torch.no_grad():
        res["whitening"] = white.fit_whitening(
            [clean_pool] + [distort(clean_pool, generator=dgen) for _ in range(cfg.whiten_distortions)]
        )
    res["extractor_sha256"] = white.sha256()
    torch.save({"state": white.state_dict(), "sha256": res["extractor_sha256"]}, cfg.output_dir / "extractor-linear.pt")
    message = random_message(k)
    with torch.no_grad():
        marked = quantize(chw([render_signs(v, wrap, message.float() * 2 - 1, bg, gain=a_work) for v in held]))
        res["final"] = {
            "marked": read_views(ext(marked), message),
            "clean": read_views(ext(heldc), message),
            "marked_whitened": read_views(white(marked), message),
            "clean_whitened": read_views(white(heldc), message),
            "marked_psnr": float(metrics.psnr(marked, heldc).mean()),
        }
    return res


def fmt_p(p: float) -> str:
    return f"{p:.1e}" if p < 0.01 else f"{p:.2f}"


def write_doc(cfg: BlindBenchConfig, res: Dict[str, Any]) -> None:
    cfg.doc.parent.mkdir(parents=True, exist_ok=True)
    cfg.doc.with_suffix(".json").write_text(json.dumps(res, indent=1))
    routes = [name for name in ("random", "linear") if name in res]
    lines = [
        "# Reading the message from images alone: the blind routes",
        "",
        f"Commands (every number here is in [{cfg.doc.with_suffix('.json').name}]({cfg.doc.with_suffix('.json').name}), "
        "written by them; each route's date and machine are recorded there):",
        "",
        "```bash",
        *sorted({res[name]["command"] for name in routes}),
        "```",
        "",
        f"Pool: {cfg.pool_train_views} training + {cfg.pool_novel_views} orbit views of the lego100 nerfacto-small base; "
        f"{cfg.heldout_views} held-out orbit views (never trained or whitened on), 8-bit renders. Chance: 24 of 48.",
        "",
    ]
    r = res.get("random")
    if r:
        rc = r["config"]
        sp = r["raw_spread_across_clean_views"]
        f1 = r["F1"]
        fin = r["final"]
        lines += [
            "## Route 1-2: a frozen random CNN, a per-key blind term trained against it",
            "",
            f"Extractor (V channel, Kaiming/GELU init, per-stage scale normalisation, seed {rc['extractor']['seed']}, sha256 "
            f"`{r['extractor_sha256'][:16]}…`): raw output spread across clean views {sp['min']:.3g} to {sp['max']:.3g} "
            f"(median {sp['median']:.3g}) per bit: not degenerate (the same layers with PyTorch's default init and no "
            f"normalisation: {r['default_init_spread']['min']:.2g} to {r['default_init_spread']['max']:.2g}). Whitened over "
            f"{r['whitening']['samples']} clean and distorted pool renders (eigenvalues {r['whitening']['eig_min']:.2g} to "
            f"{r['whitening']['eig_max']:.2g}, epsilon {r['whitening']['eps']:.2g} = {rc['extractor']['pca_eps']:g} x mean).",
            "",
            f"**F1 {'fired' if f1['fired'] else 'passed'}**: held-out bit accuracy {f1['heldout_bit_acc']:.3f} after "
            f"{f1['step']} steps (PSNR {f1['heldout_psnr']:.1f} dB, budget {rc['loose_psnr']:g} dB, no distortions; the rule "
            f"asks >= 0.75). End of the run ({rc['random_steps']} steps): marked held-out {fin['marked']['bit_acc']:.3f} "
            f"(soft-score p pooled over views {fmt_p(fin['marked']['soft_pvalue_pooled'])}), clean "
            f"{fin['clean']['bit_acc']:.3f} (p {fmt_p(fin['clean']['soft_pvalue_pooled'])}).",
            "",
            "| step | held-out bit acc | training views bit acc | PSNR marked vs clean |",
            "|---|---|---|---|",
        ]
        lines += [
            f"| {c['step']} | {c['heldout_bit_acc']:.3f} | {c['train_bit_acc']:.3f} | {c['heldout_psnr']:.1f} dB |"
            for c in r["curve"]
        ]
        lines.append("")
    li = res.get("linear")
    if li:
        lc = li["config"]
        f5, f6, fin = li["F5"], li["F6"], li["final"]
        lines += [
            "## Route 3: an extractor pre-trained on linearised marks of random messages",
            "",
            f"Per-bit render derivatives of the sticker for {lc['pool_train_views'] + lc['pool_novel_views'] + lc['heldout_views']} "
            f"views ({li['jacobian_seconds']:.0f} s here, a reuse of the cache file in the output folder when it matches); synthetic `I0 + alpha R s` for random s, strength annealed from "
            f"{lc['start_psnr']:g} to {lc['work_psnr']:g} dB over {lc['anneal_steps']} steps, batch {lc['batch']}, Adam {lc['lr']:g}. "
            f"Held-out exact renders at the working strength: {li['heldout_exact_psnr']:.1f} dB (worst view "
            f"{li['heldout_exact_psnr_min']:.1f} dB).",
            "",
            f"**F5 {'fired' if f5['fired'] else 'passed'}**: linearisation error e = {f5['linearisation_error_mean']:.2f} "
            f"(max {f5['max']:.2f}) at the working strength (rule: > 0.3 -> synthetic samples for the loose phase only).",
            f"**F6 {'fired' if f6['fired'] else 'passed'}**: message loss {f6['message_loss']:.3f} after {f6['samples']:,} "
            f"synthetic samples (rule: > 0.65 -> abandon).",
            "",
            f"Frozen extractor (sha256 `{li['extractor_sha256'][:16]}…`), then a fresh random message: held-out marked views "
            f"{fin['marked']['bit_acc']:.3f} bit accuracy ({fin['marked']['views_41']} of {lc['heldout_views']} views >= 41/48; "
            f"soft-score p median per view {fmt_p(fin['marked']['soft_pvalue_median'])}, pooled over the views "
            f"{fmt_p(fin['marked']['soft_pvalue_pooled'])}) at {fin['marked_psnr']:.1f} dB; the same views clean: "
            f"{fin['clean']['bit_acc']:.3f} (pooled p {fmt_p(fin['clean']['soft_pvalue_pooled'])}).",
            "",
        ]
        if "marked_whitened" in fin:
            mw, cw = fin["marked_whitened"], fin["clean_whitened"]
            lines += [
                f"Whitened (mean + PCA over {li['whitening']['samples']} clean and distorted pool renders, before the message "
                f"was drawn; the mean removes the extractor's per-bit bias on this scene): marked {mw['bit_acc']:.3f} "
                f"({mw['views_41']} views >= 41/48; soft-score p median per view {fmt_p(mw['soft_pvalue_median'])}, pooled "
                f"{fmt_p(mw['soft_pvalue_pooled'])}); clean {cw['bit_acc']:.3f} (pooled p {fmt_p(cw['soft_pvalue_pooled'])}).",
                "",
            ]
        lines += [
            "| samples | message loss | held-out exact | held-out synthetic | pool exact | pool synthetic |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {c['samples']:,} | {c['message_loss']:.3f} | {c['heldout_exact']:.3f} | {c['heldout_synthetic']:.3f} | "
            f"{c['pool_exact']:.3f} | {c['pool_synthetic']:.3f} |"
            for c in li["curve"]
        ]
        lines.append("")
    cfg.doc.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(cfg: BlindBenchConfig) -> Dict[str, Any]:
    bad = [r for r in cfg.routes if r not in ("random", "linear")]
    if bad:
        raise SystemExit(f"unknown route(s) {bad}; use random and/or linear")
    torch.manual_seed(cfg.seed)
    pipe = setup_pool(cfg)
    js = cfg.doc.with_suffix(".json")
    res: Dict[str, Any] = json.loads(js.read_text()) if cfg.keep and js.is_file() else {}
    command = "python -m gsticker_plugin.bench.blind " + " ".join(
        [f"--load-checkpoint {cfg.load_checkpoint}"]
        + ([f"--data {cfg.data}"] if cfg.data else [])
        + [f"--routes {' '.join(cfg.routes)} --doc {cfg.doc}"]
        + [f"--{k.replace('_', '-')} {v}" for k, v in vars(cfg).items() if k in CHANGED and v != CHANGED[k]]
    )
    for route in cfg.routes:
        print(f"== route {route}", flush=True)
        res[route] = random_route(cfg, pipe) if route == "random" else linear_route(cfg, pipe)
        res[route].update(
            command=command,
            date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            machine=machine_info(),
            config=json.loads(json.dumps(vars(cfg), default=lambda o: vars(o) if hasattr(o, "__dict__") else str(o))),
        )
        write_doc(cfg, res)
    return res


if __name__ == "__main__":
    main(tyro.cli(BlindBenchConfig))
