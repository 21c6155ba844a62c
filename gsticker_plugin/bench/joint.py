"""Joint training when compute is not the limit: the paper's setting (sticker and extractor trained together on
uniformly random messages), on a packed copy of the fast-path pool so the training step needs PyTorch alone.

    python -m gsticker_plugin.bench.joint pack     # here, with Nerfstudio: the lego100 base's pool, packed
    python -m gsticker_plugin.bench.joint train --device cuda --doc docs/bench-joint.md   # any machine with torch

The packed pool keeps, for every view, the rays where the calibrated gate opens, with their samples' density,
length and 8-bit colour and each ray's first and last sample position (the others follow: samples tile the ray);
the pack measures the largest difference to the fast path's render of a random message. Training draws a fresh
random message per image; the owner message is drawn only after training, and held-out views (never trained on) are read
with it beside their clean renders.
"""

from __future__ import annotations

import json
import math
import re
import secrets
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Dict, List, Literal, Tuple, Union

import torch
import torch.nn.functional as F
import tyro
from torch import Tensor

from gsticker_plugin import metrics
from gsticker_plugin.heads import ConvHead, HeadConfig, count_parameters
from gsticker_plugin.sticker import Sticker, composite, laplace_cdf_gate, message_to_signs, normalize_positions

PACK_VERSION = 1
CAMERAS = {
    "training": "the dataset's training cameras",
    "orbit": "orbit cameras drawn like the held-out ones",
    "both": "training and orbit cameras",
}


@dataclass
class Pack:
    """Pack the fast-path pool of a base into a file that :class:`Train` reads without Nerfstudio."""

    load_checkpoint: Path = Path(
        "../shared/checkpoints/lego100-nerfacto-small/nerfacto/base/nerfstudio_models/step-000002999.ckpt"
    )
    """Base run checkpoint."""
    data: Union[Path, None] = None
    """Dataset, if the base's recorded path does not exist from here."""
    pool_dir: Path = Path("outputs/bench-blind")
    """Where the pool is rendered (or its cache reused: ``POOL_DIR/pool.pt``)."""
    pool_train_views: int = 48
    pool_novel_views: int = 48
    heldout_views: int = 24
    train_cameras: Literal["training", "orbit", "both"] = "training"
    """Which pool views to pack for training: the dataset's training cameras, the pool's orbit cameras (drawn like the
    held-out ones), or both (twice the file)."""
    output: Path = Path("outputs/joint/pool-packed.pt")
    seed: int = 0


@dataclass
class Train:
    """Train sticker and extractor jointly on random messages from a packed pool; write curves, JSON and page."""

    pool: Path = Path("outputs/joint/pool-packed.pt")
    """Packed pool (``pack``)."""
    backbones: Tuple[str, ...] = ("vgg16", "small")
    """Extractors to train, one run each: vgg16 (the paper's shape, untrained) and small (the plugin's head)."""
    seconds: float = 200.0
    """Wall-clock budget of each run (the training loop stops at the first evaluation past it)."""
    max_steps: int = 100_000
    views_per_step: int = 16
    messages_per_view: int = 4
    """Random messages rendered per view and step (the sticker's features are computed once per view)."""
    loose_psnr: float = 25.0
    """PSNR budget (marked vs clean) of the first phase."""
    tight_psnr: float = 35.0
    """PSNR budget after the ramp."""
    loose_share: float = 0.3
    """Share of the budget spent at the loose PSNR; the budget then tightens linearly until twice this share."""
    sticker_lr: float = 1e-3
    sticker_init_scale: float = 0.5
    """Range of the sticker's last-layer init: 0.5 starts the mark near 27 dB on lego100 (the plugin's 0.1 near 40 dB,
    too faint for an untrained extractor to find)."""
    vgg16_lr: float = 1e-4
    """Adam learning rate of the vgg16 extractor (no normalisation layers)."""
    small_lr: float = 1e-3
    """Adam learning rate of the small extractor."""
    negative_weight: float = 0.5
    """Weight of the honesty loss (clean renders' logits pushed to p = 1/2)."""
    eval_every: float = 20.0
    """Seconds between evaluations."""
    device: str = "cpu"
    seed: int = 0
    output_dir: Path = Path("outputs/joint")
    """Curves (JSONL) as they are measured."""
    doc: Path = Path("docs/bench-joint.md")
    """Page to write (its JSON beside it)."""
    command: str = ""
    """The command line to record on the page (default: rebuilt from these options)."""


# ---------------------------------------------------------------------------------------------- packing


def along_ray(deltas: Tensor) -> Tensor:
    """Where each sample's midpoint lies between the ray's first and last midpoints (0 to 1), from the samples'
    lengths: Nerfstudio's samples tile the ray, so midpoint i is at sum(deltas[:i]) + deltas[i] / 2."""
    ends = torch.cumsum(deltas, dim=-2)
    mids = ends - deltas / 2
    span = (mids[:, -1:] - mids[:, :1]).clamp_min(1e-12)
    return (mids - mids[:, :1]) / span


@torch.no_grad()
def pack_view(view, wrap) -> Dict[str, Tensor]:
    """One fast-path pool view reduced to the rays its gate opens on; positions kept as each ray's first and last
    sample (the rest follow from the samples' lengths, :func:`along_ray`), colours in 8 bits."""
    _, open_ = wrap.open_samples(view.density)
    rays = open_.any(dim=-1)
    pos = view.positions[rays].float()
    return {
        "image": view.image.half(),
        "rays": view.active[rays].int(),
        "ends": torch.stack([pos[:, 0], pos[:, -1]], dim=1),  # [R 2 3], world units
        "density": view.density[rays].half(),
        "deltas": view.deltas[rays].half(),
        "rgb": torch.round(view.rgb[rays].float().clamp(0, 1) * 255).to(torch.uint8),
        "novel": torch.tensor(bool(view.novel)),
    }


def pack(cfg: Pack) -> Dict[str, Any]:
    # deferred: packing renders the pool through Nerfstudio, which the training machine need not have
    from gsticker_plugin.bench.blind import BlindBenchConfig, setup_pool
    from gsticker_plugin.fastpath import with_density_change

    bcfg = BlindBenchConfig(
        load_checkpoint=cfg.load_checkpoint,
        data=cfg.data,
        output_dir=cfg.pool_dir,
        pool_train_views=cfg.pool_train_views,
        pool_novel_views=cfg.pool_novel_views,
        heldout_views=cfg.heldout_views,
        seed=cfg.seed,
    )
    pipe = setup_pool(bcfg)
    wrap, bg = pipe.model.final_wrap, pipe.model.background_color()
    if bg.color is None:
        raise SystemExit("error: the packed pool needs a base with a fixed background colour (white, black, a colour)")
    wanted = {"training": (False,), "orbit": (True,), "both": (False, True)}[cfg.train_cameras]
    train_views = [v for v in pipe.pool if bool(v.novel) in wanted]
    views = {"train": train_views, "heldout": list(pipe.monitor)}
    packed = {split: [pack_view(v, wrap) for v in vs] for split, vs in views.items()}
    # The pack's error: a random message's change through the fast path and through the packed samples.
    gen = torch.Generator().manual_seed(cfg.seed)
    errs = []
    for v, p in zip(views["heldout"][:4], packed["heldout"][:4]):
        msg = torch.randint(0, 2, (wrap.sticker.num_bits,), generator=gen)
        delta, _ = wrap.delta(v.density, v.positions.float(), msg)
        exact = with_density_change(v, delta, bg.color)
        gate = (wrap.gate.mu, wrap.gate.beta, wrap.gate.scale, wrap.gate_threshold)
        mine = render_packed(p, wrap.aabb, wrap.sticker, gate, bg.color, msg)
        errs.append(float((mine - exact).abs().max().detach()))
    sizes = [int(p["density"].shape[0] * p["density"].shape[1]) for vs in packed.values() for p in vs]
    out = {
        "version": PACK_VERSION,
        "views": packed,
        "gate": {
            "mu": float(wrap.gate.mu),
            "beta": float(wrap.gate.beta),
            "scale": float(wrap.gate.scale),
            "threshold": float(wrap.gate_threshold),
        },
        "background": bg.color.float().cpu(),
        "aabb": wrap.aabb.float().cpu(),
        "num_bits": int(wrap.sticker.num_bits),
        "sticker": {"num_frequencies": wrap.sticker.num_frequencies, "hidden_dim": wrap.sticker.pos_in.out_features},
        "source": {
            "checkpoint": str(cfg.load_checkpoint),
            "train_cameras": cfg.train_cameras,
            "max_abs_error": max(errs),
        },
    }
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    torch.save(out, cfg.output)
    mib = cfg.output.stat().st_size / 2**20
    print(
        f"packed {len(views['train'])} pool + {len(views['heldout'])} held-out views, {sum(sizes):,} samples, "
        f"{mib:.1f} MiB -> {cfg.output}; largest |packed - fast path| on a random message: {max(errs):.2e}"
    )
    return out


def render_packed(
    p: Dict[str, Tensor], aabb: Tensor, sticker: Sticker, gate: tuple, background: Tensor, message: Tensor
) -> Tensor:
    """A packed view rendered with the sticker of ``message`` (one view; unclamped; ``gate``: mu, beta, scale,
    threshold), for the pack's check."""
    batch = stack_views([p], aabb, torch.device("cpu"))
    return render_batch(batch, torch.tensor([0]), sticker, gate, background, message[None])[0]


# ---------------------------------------------------------------------------------------------- batched rendering


def stack_views(views: List[Dict[str, Tensor]], aabb: Tensor, device: torch.device) -> Dict[str, Tensor]:
    """Packed views padded to one ray count (padding rays have no density), stacked on ``device`` in float32, with
    every sample's position rebuilt (:func:`along_ray`) and normalized to ``aabb`` as the sticker reads it."""
    r = max(int(v["rays"].shape[0]) for v in views)

    def pad(t: Tensor) -> Tensor:
        out = torch.zeros((r, *t.shape[1:]), dtype=t.dtype)
        out[: t.shape[0]] = t
        return out

    h, w = views[0]["image"].shape[:2]
    deltas = torch.stack([pad(v["deltas"].float()) for v in views]).to(device)  # [V R S 1]
    ends = torch.stack([pad(v["ends"].float()) for v in views]).to(device)  # [V R 2 3]
    frac = along_ray(deltas.flatten(0, 1)).reshape(deltas.shape)
    return {
        "image": torch.stack([v["image"].float().reshape(h * w, 3) for v in views]).to(device),
        "rays": torch.stack([pad(v["rays"].long()) for v in views]).to(device),
        "positions": normalize_positions(ends[:, :, :1] + frac * (ends[:, :, 1:] - ends[:, :, :1]), aabb),
        "density": torch.stack([pad(v["density"].float()) for v in views]).to(device),
        "deltas": deltas,
        "rgb": torch.stack([pad(v["rgb"].float() / 255.0) for v in views]).to(device),
        "hw": torch.tensor([h, w]),
    }


def render_batch(
    batch: Dict[str, Tensor], idx: Tensor, sticker: Sticker, gate: tuple, background: Tensor, messages: Tensor
) -> Tensor:
    """Images [V*M H W 3] (unclamped) of views ``idx`` [V], each under ``messages`` [V*M K] (M per view, in order)."""
    mu, beta, scale, threshold = gate
    pos, dens = batch["positions"][idx], batch["density"][idx]  # [V R S 3], [V R S 1]
    v, r, s = dens.shape[:3]
    m = messages.shape[0] // v
    psi = laplace_cdf_gate(dens, torch.as_tensor(mu).to(dens), torch.as_tensor(beta).to(dens))
    open_ = (psi > threshold).float()
    feats = sticker.features(pos.reshape(-1, 3)).reshape(v, r * s, -1)  # [V RS K]
    signs = message_to_signs(messages).reshape(v, m, -1)  # [V M K]
    mix = torch.tanh(torch.einsum("vnk,vmk->vmn", feats, signs) / math.sqrt(feats.shape[-1]))  # [V M RS]
    delta = (psi * open_ * scale).reshape(v, 1, r * s) * mix
    marked = torch.relu(dens.reshape(v, 1, r * s) + delta).reshape(v * m * r, s, 1)
    dl, rgb = batch["deltas"][idx].reshape(v * r, s, 1), batch["rgb"][idx].reshape(v * r, s, 3)
    clean, _ = composite(dens.reshape(v * r, s, 1), rgb, dl, background)  # once per view, not per message
    per_message = lambda t: t.reshape(v, 1, r, s, -1).expand(-1, m, -1, -1, -1).reshape(v * m * r, s, -1)  # noqa: E731
    marked, _ = composite(marked, per_message(rgb), per_message(dl), background)
    change = marked.reshape(v, m, r, 3) - clean.reshape(v, 1, r, 3)
    h, w = int(batch["hw"][0]), int(batch["hw"][1])
    image = batch["image"][idx].repeat_interleave(m, 0)
    rays = batch["rays"][idx].repeat_interleave(m, 0)
    return image.scatter_add(1, rays[..., None].expand(-1, -1, 3), change.reshape(v * m, r, 3)).reshape(v * m, h, w, 3)


def quantize(img: Tensor) -> Tensor:
    """8-bit rounding as a saved render, straight-through for gradients."""
    clamped = img.clamp(0.0, 1.0)
    return clamped + (metrics.as_8_bit(clamped) - clamped).detach()


def chw(images: Tensor) -> Tensor:
    return images.permute(0, 3, 1, 2)


# ---------------------------------------------------------------------------------------------- training


def psnr_budget(cfg: Train, frac: float) -> float:
    """The PSNR budget at ``frac`` of the time budget: loose, then a linear ramp to tight."""
    if frac <= cfg.loose_share:
        return cfg.loose_psnr
    t = min(1.0, (frac - cfg.loose_share) / max(cfg.loose_share, 1e-9))
    return cfg.loose_psnr + t * (cfg.tight_psnr - cfg.loose_psnr)


@torch.no_grad()
def evaluate(batch, n: int, sticker, gate, bg, extractor, messages: Tensor) -> Dict[str, float]:
    """Bit accuracy of ``n`` views read under ``messages`` [n K] (8-bit renders), the clean renders' accuracy
    against the same messages, and the mean PSNR marked vs clean."""
    accs, clean_accs, psnrs = [], [], []
    for i in range(0, n, 8):
        idx = torch.arange(i, min(n, i + 8), device=messages.device)
        marked = quantize(render_batch(batch, idx, sticker, gate, bg, messages[idx]))
        clean = quantize(batch["image"][idx].reshape(marked.shape))
        bits = metrics.decode_bits(extractor(chw(torch.cat([marked, clean]))))
        accs.append(metrics.bit_accuracy(bits[: len(idx)], messages[idx]))
        clean_accs.append(metrics.bit_accuracy(bits[len(idx) :], messages[idx]))
        psnrs.append(metrics.psnr(chw(marked), chw(clean)))
    return {
        "bit_acc": float(torch.cat(accs).mean()),
        "clean_bit_acc": float(torch.cat(clean_accs).mean()),
        "psnr": float(torch.cat(psnrs).mean()),
    }


@torch.no_grad()
def owner_read(batch, n: int, sticker, gate, bg, extractor, message: Tensor) -> Dict[str, Any]:
    """The owner's message (drawn after training) on ``n`` views: per-view matches, marked and clean."""
    num_bits = message.numel()
    thr = metrics.min_matches_for_fpr(num_bits, 1e-6)
    marked_m, clean_m, psnrs = [], [], []
    for i in range(0, n, 8):
        idx = torch.arange(i, min(n, i + 8), device=message.device)
        msgs = message[None].expand(len(idx), -1)
        marked = quantize(render_batch(batch, idx, sticker, gate, bg, msgs))
        clean = quantize(batch["image"][idx].reshape(marked.shape))
        marked_m.append(metrics.count_matches(metrics.decode_bits(extractor(chw(marked))), message))
        clean_m.append(metrics.count_matches(metrics.decode_bits(extractor(chw(clean))), message))
        psnrs.append(metrics.psnr(chw(marked), chw(clean)))
    mm, cm = torch.cat(marked_m), torch.cat(clean_m)
    return {
        "views": n,
        "bit_acc": float(mm.float().mean() / num_bits),
        "views_at_41": int((mm >= thr).sum()),
        "clean_mean_matches": float(cm.float().mean()),
        "clean_max_matches": int(cm.max()),
        "psnr": float(torch.cat(psnrs).mean()),
        "min_psnr": float(torch.cat(psnrs).min()),
    }


def train_one(cfg: Train, data: Dict[str, Any], backbone: str, lr: float, device: torch.device) -> Dict[str, Any]:
    torch.manual_seed(cfg.seed)
    gen = torch.Generator(device=device).manual_seed(cfg.seed)
    nbits = int(data["num_bits"])
    train = stack_views(data["views"]["train"], data["aabb"], device)
    held = stack_views(data["views"]["heldout"], data["aabb"], device)
    n_train, n_held = train["rays"].shape[0], held["rays"].shape[0]
    g = data["gate"]
    gate = (g["mu"], g["beta"], g["scale"], g["threshold"])
    bg = data["background"].to(device)
    sticker = Sticker(num_bits=nbits, init_scale=cfg.sticker_init_scale, **data["sticker"]).to(device)
    extractor = ConvHead(HeadConfig(backbone=backbone), nbits).to(device)  # type: ignore[arg-type]
    opt = torch.optim.Adam(
        [{"params": sticker.parameters(), "lr": cfg.sticker_lr}, {"params": extractor.parameters(), "lr": lr}]
    )
    eval_train_msgs = torch.randint(0, 2, (n_train, nbits), generator=gen, device=device)
    eval_held_msgs = torch.randint(0, 2, (n_held, nbits), generator=gen, device=device)
    curve_path = cfg.output_dir / f"curve-{backbone}.jsonl"
    curve_path.parent.mkdir(parents=True, exist_ok=True)
    rows: List[Dict[str, Any]] = []
    t0, last_eval, step, images = time.time(), -1e9, 0, 0
    with curve_path.open("w") as curve:
        while True:
            elapsed = time.time() - t0
            if elapsed - last_eval >= cfg.eval_every or step >= cfg.max_steps or elapsed >= cfg.seconds:
                if device.type == "cuda":
                    torch.cuda.synchronize()
                sticker.eval()
                extractor.eval()
                row = {
                    "step": step,
                    "seconds": round(time.time() - t0, 1),
                    "images": images,
                    "budget_psnr": psnr_budget(cfg, elapsed / max(cfg.seconds, 1e-9)),
                    "heldout": evaluate(held, n_held, sticker, gate, bg, extractor, eval_held_msgs),
                    "train": evaluate(train, min(n_train, 24), sticker, gate, bg, extractor, eval_train_msgs),
                }
                rows.append(row)
                curve.write(json.dumps(row) + "\n")
                curve.flush()
                print(f"[joint {backbone}] {json.dumps(row)}", flush=True)
                sticker.train()
                extractor.train()
                last_eval = time.time() - t0
                if step >= cfg.max_steps or elapsed >= cfg.seconds:
                    break
            idx = torch.randint(0, n_train, (cfg.views_per_step,), generator=gen, device=device)
            msgs = torch.randint(
                0, 2, (cfg.views_per_step * cfg.messages_per_view, nbits), generator=gen, device=device
            )
            marked = quantize(render_batch(train, idx, sticker, gate, bg, msgs))
            clean = quantize(train["image"][idx].reshape(-1, *marked.shape[1:]))
            mse = F.mse_loss(marked, clean.repeat_interleave(cfg.messages_per_view, 0))
            budget = 10.0 ** (-psnr_budget(cfg, elapsed / max(cfg.seconds, 1e-9)) / 10.0)
            content = 10.0 * F.relu(mse / budget - 1.0)  # free below the budget: the mark may grow to it
            logits = extractor(chw(marked))
            neg = extractor(chw(clean))
            loss = (
                F.binary_cross_entropy_with_logits(logits, msgs.float())
                + cfg.negative_weight * F.binary_cross_entropy_with_logits(neg, torch.full_like(neg, 0.5))
                + content
            )
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            images += marked.shape[0]
    # The owner message exists only now: the extractor and sticker were trained on random messages alone.
    owner = torch.tensor([int(b) for b in f"{secrets.randbits(nbits):0{nbits}b}"], device=device)
    sticker.eval()
    extractor.eval()
    return {
        "backbone": backbone,
        "extractor_lr": lr,
        "extractor_params": count_parameters(extractor),
        "sticker_params": count_parameters(sticker),
        "steps": step,
        "images": images,
        "seconds": round(time.time() - t0, 1),
        "curve": rows,
        "owner_heldout": owner_read(held, n_held, sticker, gate, bg, extractor, owner),
        "owner_train": owner_read(train, min(n_train, 24), sticker, gate, bg, extractor, owner),
    }


def train(cfg: Train) -> Dict[str, Any]:
    device = torch.device(cfg.device)
    torch.backends.cudnn.benchmark = True
    data = torch.load(cfg.pool, map_location="cpu", weights_only=False)  # a file this benchmark wrote
    if data.get("version") != PACK_VERSION:
        raise SystemExit(f"error: {cfg.pool} is not a version-{PACK_VERSION} packed pool; run `pack` again")
    runs = [train_one(cfg, data, b, cfg.vgg16_lr if b == "vgg16" else cfg.small_lr, device) for b in cfg.backbones]
    machine: Dict[str, Any] = {"device": cfg.device, "torch": torch.__version__}
    if device.type == "cuda":
        machine["gpu"] = torch.cuda.get_device_name(device)
    res = {
        "command": cfg.command or command_line(cfg),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine,
        "pool": {
            "train_views": len(data["views"]["train"]),
            "heldout_views": len(data["views"]["heldout"]),
            "size": list(data["views"]["train"][0]["image"].shape[:2]),
            **data["source"],
        },
        "config": {
            k: (list(v) if isinstance(v, tuple) else v)
            for k, v in vars(cfg).items()
            if k not in ("pool", "output_dir", "doc", "command", "device")
        },
        "runs": runs,
    }
    cfg.doc.parent.mkdir(parents=True, exist_ok=True)
    cfg.doc.with_suffix(".json").write_text(json.dumps(res, indent=2))
    cfg.doc.write_text(page(res, cfg.doc.with_suffix(".json").name))
    print(f"wrote {cfg.doc} and {cfg.doc.with_suffix('.json')}")
    return res


def command_line(cfg: Train) -> str:
    default = Train()
    opts = [
        f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, tuple) else v}"
        for k, v in vars(cfg).items()
        if k != "command" and v != getattr(default, k)
    ]
    return " ".join(["python -m gsticker_plugin.bench.joint train", *opts])


def page(res: Dict[str, Any], json_name: str) -> str:
    """The Markdown page of a ``train`` result whose JSON is ``json_name`` beside it."""
    pool = res["pool"]
    cameras = pool.get("train_cameras") or ("both" if pool.get("novel_in_training") else "training")
    pack_cmd = "python -m gsticker_plugin.bench.joint pack"
    if cameras != "training":
        pack_cmd += f" --train-cameras {cameras}"
    found = re.search(r"--pool (\S+)", res["command"])
    if found:
        pack_cmd += f" --output {found.group(1)}"
    lines = [
        "# Joint training when compute is not the limit (the paper's setting, honestly)",
        "",
        f"Commands (every number here is in [{json_name}]({json_name}), written by the second):",
        "",
        "```bash",
        pack_cmd + "   # the fast-path pool of the lego100 nerfacto-small base, packed",
        res["command"],
        "```",
        "",
        f"Machine: {res['machine'].get('gpu', res['machine']['device'])}, torch {res['machine']['torch']}; "
        f"{res['date']}. Pool: {pool['train_views']} training views "
        f"({CAMERAS[cameras]}), "
        f"{pool['heldout_views']} held-out orbit views never trained on, {pool['size'][0]} px, 8-bit renders; "
        f"packed renders differ from the fast path's by at most {pool['max_abs_error']:.1e} (a random message).",
        "",
        "Sticker (bilinear, random init) and extractor trained together from scratch; every training image carries "
        "a fresh uniformly random message (no owner message exists during training), BCE on the message, the "
        "honesty loss on clean renders, and a content hinge at a PSNR budget (free below it) that is loose "
        f"({res['config']['loose_psnr']:g} dB) for the first {res['config']['loose_share']:.0%} of the time, then "
        f"tightens to {res['config']['tight_psnr']:g} dB; no distortions. After training a secret message is drawn "
        "and the held-out views are read with it, beside their clean renders. Chance: 24 of 48.",
        "",
    ]
    for run in res["runs"]:
        oh, ot = run["owner_heldout"], run["owner_train"]
        lines += [
            f"## Extractor `{run['backbone']}` ({run['extractor_params']:,} parameters, lr {run['extractor_lr']:g})",
            "",
            f"{run['steps']:,} steps, {run['images']:,} marked training images in {run['seconds']:.0f} s.",
            "",
            f"Owner message (drawn after training), held-out views: bit accuracy {oh['bit_acc']:.3f}, "
            f"{oh['views_at_41']} of {oh['views']} views at >= 41/48, PSNR {oh['psnr']:.1f} dB (worst "
            f"{oh['min_psnr']:.1f}); clean renders: mean {oh['clean_mean_matches']:.1f} matches, max "
            f"{oh['clean_max_matches']}. Training views: {ot['bit_acc']:.3f}, {ot['views_at_41']} of {ot['views']} "
            f"at >= 41/48, {ot['psnr']:.1f} dB.",
            "",
            "| step | seconds | images | PSNR budget | held-out bit acc | held-out clean | held-out PSNR "
            "| training bit acc |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in run["curve"]:
            h, t = r["heldout"], r["train"]
            lines.append(
                f"| {r['step']:,} | {r['seconds']:.0f} | {r['images']:,} | {r['budget_psnr']:.1f} dB "
                f"| {h['bit_acc']:.3f} | {h['clean_bit_acc']:.3f} | {h['psnr']:.1f} dB | {t['bit_acc']:.3f} |"
            )
        lines.append("")
    return "\n".join(lines) + "\n"


@dataclass
class Page:
    """Write the Markdown page of a ``train`` result again from its JSON (the page goes beside it, same stem)."""

    json: Path = Path("docs/bench-joint.json")


Command = Union[
    Annotated[Pack, tyro.conf.subcommand("pack", description="Pack the fast-path pool of a base (needs Nerfstudio).")],
    Annotated[Train, tyro.conf.subcommand("train", description="Joint training from a packed pool (PyTorch alone).")],
    Annotated[Page, tyro.conf.subcommand("page", description="Write a result's page again from its JSON.")],
]


def main(cmd: Union[Pack, Train, Page]) -> Dict[str, Any]:
    if isinstance(cmd, Page):
        res = json.loads(cmd.json.read_text())
        cmd.json.with_suffix(".md").write_text(page(res, cmd.json.name))
        return res
    return pack(cmd) if isinstance(cmd, Pack) else train(cmd)


if __name__ == "__main__":
    main(tyro.cli(Command))  # type: ignore[arg-type]
