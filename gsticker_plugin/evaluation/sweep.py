"""The speed-against-accuracy sweep: one sticker variant trained and read at each checkpoint, where the variants
first meet the targets, and the chart of accuracy against training time."""

from __future__ import annotations

import contextlib
import re
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch

from gsticker_plugin import metrics, runs
from gsticker_plugin.decoders.geometric import decode_suspect
from gsticker_plugin.decoders.image import decode_posed_images
from gsticker_plugin.decoders.reference import load_base_reference
from gsticker_plugin.evaluate import psnr_nhw3, render_split
from gsticker_plugin.evaluation.held_out import HELD_OUT_VIEWS, held_out_renders, view_attack
from gsticker_plugin.evaluation.sticker_runs import run_step
from gsticker_plugin.fastpath import novel_cameras
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.machine import sticker_train_argv
from gsticker_plugin.model import geometry_reference
from gsticker_plugin.runs import load_run
from gsticker_plugin.trainer import step_key_path

_STEP = re.compile(r"step (\d+): held-out .* (\d+) s")
_POOL = re.compile(r"pool: .* (\d+) s;")
# name -> (ns-train geometrysticker overrides, dataset suffix replacement or None)
VARIANTS: Dict[str, Tuple[List[str], Optional[str]]] = {
    "default": ([], None),
    "width-16": (["--pipeline.model.sticker-hidden-dim", "16"], None),
    "width-32": (["--pipeline.model.sticker-hidden-dim", "32"], None),
    "width-128": (["--pipeline.model.sticker-hidden-dim", "128"], None),
    "bits-16": (["--pipeline.model.num-bits", "16"], None),
    "bits-32": (["--pipeline.model.num-bits", "32"], None),
    "bits-64": (["--pipeline.model.num-bits", "64", "--pipeline.model.sticker-hidden-dim", "64"], None),
    "gate-0.25": (["--pipeline.model.gate-quantile", "0.25"], None),
    "gate-0.75": (["--pipeline.model.gate-quantile", "0.75"], None),
    # the extractor and classifier in the training loop (the informed decoders do not read them): none, 8 wide,
    # the default 32 wide, the paper's VGG16 shape
    "heads-none": (
        ["--pipeline.msg-weight", "0", "--pipeline.negative-weight", "0", "--pipeline.cls-weight", "0"],
        None,
    ),
    "heads-8": (["--pipeline.heads.width", "8"], None),
    "heads-vgg16": (["--pipeline.heads.backbone", "vgg16"], None),
    # the geometrysticker-robust preset's sticker settings (its pool sizes, steps and warm-up: --pool-views 16
    # --steps 2000 --warmup-steps 50)
    "robust": (
        [
            *("--pipeline.model.sticker-amplitude", "30", "--pipeline.mark-psnr", "36", "--pipeline.target-psnr", "35"),
            *("--pipeline.condition-weight", "3", "--pipeline.condition-scale-free", "True"),
            *("--pipeline.condition-blur", "1"),
        ],
        None,
    ),
    "res-200": ([], "200"),
    "res-400": ([], "400"),
}


def train_seconds(log: Path) -> Tuple[Optional[float], Dict[int, float]]:
    """(pool build seconds, {step: seconds since training began}) from an ns-train geometrysticker log."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", log.read_text(errors="replace")) if log.is_file() else ""
    pool = _POOL.search(text)
    return (float(pool.group(1)) if pool else None), {int(m.group(1)): float(m.group(2)) for m in _STEP.finditer(text)}


def image_readings(pipeline, key, ref, cameras, attacks: Sequence[str], threshold: int) -> Dict[str, Any]:
    """The informed image decoder at ``cameras`` (their true poses) on 8-bit renders of the loaded state, clean and
    under each attack spec of ``attacks`` (``clean``: none; view i's draw seeded with i, as bench.unposed's), and the
    PSNR of those renders marked vs unmarked."""
    marked, clean = held_out_renders(pipeline, cameras)
    n = marked.shape[0]
    names = [(f"view{i}", cameras[i : i + 1]) for i in range(n)]
    cache: Dict[Any, Any] = {}  # the base's reference views, shared by the attacks
    out: Dict[str, Any] = {
        "image_psnr_db": float(metrics.psnr(marked.permute(0, 3, 1, 2), clean.permute(0, 3, 1, 2)).mean()),
        "image": {},
    }
    t0 = time.time()
    for spec in attacks:
        images = [view_attack(marked[i], "" if spec == "clean" else spec, i, clean[i])[0] for i in range(n)]
        with contextlib.redirect_stdout(sys.stderr):
            d = decode_posed_images(key, ref, images, names, 0, ref_cache=cache)
        m = d["matches"]
        out["image"][spec] = {
            "bit_acc": float(d["bit_acc"].float().mean()),
            "matches": [int(x) for x in m],
            "views_passing": int((m >= threshold).sum()),
        }
    out["image_decode_seconds_per_view"] = round((time.time() - t0) / max(n * len(attacks), 1), 2)
    return out


def decode_checkpoint(
    pipeline,
    key,
    base_config: Path,
    data: Optional[Path],
    num_views: int,
    psnr_views: int,
    threshold: int,
    image_cameras=None,
    image_attacks: Sequence[str] = (),
) -> Dict[str, Any]:
    """Geometric bit accuracy (the checkpoint's own sticker as the reference) and PSNR on/off, at the loaded state;
    with ``image_cameras``, the informed image decoder's readings there too (:func:`image_readings`)."""
    model = pipeline.model
    ref_key = SimpleNamespace(
        geometry=geometry_reference(model), message=key.message, base=key.base, num_bits=key.num_bits
    )
    ref = load_base_reference(ref_key, "(checkpoint)", base_config, data, model.device)
    t0 = time.time()
    with contextlib.redirect_stdout(sys.stderr):
        dec, _ = decode_suspect(ref_key, ref, model, num_views, 0.25, 0, sticker=True, full_renders=False)
    per_view = (time.time() - t0) / num_views
    on = render_split(pipeline, "test", psnr_views, sticker=True, progress=False)
    off = render_split(pipeline, "test", psnr_views, sticker=False, progress=False)
    m = dec["matches"]
    out = {
        "bit_acc": float(dec["bit_acc"].float().mean()),
        "matches": [int(x) for x in m],
        "views_passing": int((m >= threshold).sum()),
        "psnr_vs_unwm": float(psnr_nhw3(on["rgb"], off["rgb"]).mean()),
        "psnr_vs_gt": float(psnr_nhw3(on["rgb"], on["gt"]).mean()),
        "decode_seconds_per_view": round(per_view, 2),
    }
    if image_cameras is not None:
        out.update(image_readings(pipeline, ref_key, ref, image_cameras, image_attacks, threshold))
    return out


def run_variant(cfg: Any, name: str) -> Dict[str, Any]:
    overrides, res = VARIANTS[name]
    data = cfg.data
    if res is not None:
        if data is None or not re.search(r"\d+$", str(data).rstrip("/")):
            raise SystemExit(f"variant {name} needs --data ending in a resolution (e.g. ../shared/data/lego100)")
        data = Path(re.sub(r"\d+$", res, str(data).rstrip("/")))
        if not data.is_dir():
            raise SystemExit(f"variant {name}: {data} does not exist; drop it from --variants")
    out = cfg.work_dir.resolve()
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    run = out / name / "geometrysticker" / "watermarked"
    key_path = run.with_name("watermarked.gskey")
    log = logs / f"{name}.log"
    final = run / "nerfstudio_models" / f"step-{cfg.steps - 1:09d}.ckpt"
    wall = None
    if not (key_path.is_file() and final.is_file()):
        t0 = time.time()
        run_step(
            sticker_train_argv(
                out,
                name,
                cfg.steps,
                cfg.owner_id,
                key_path,
                "--steps-per-save",
                str(cfg.save_every),
                "--save-only-latest-checkpoint",
                "False",
                "--pipeline.train-heads",
                "True",
                "--pipeline.pool-train-views",
                str(cfg.pool_views),
                "--pipeline.pool-novel-views",
                str(cfg.pool_views),
                "--pipeline.monitor-views",
                "2",
                "--pipeline.steps-per-monitor",
                str(cfg.save_every),
                "--pipeline.warmup-steps",
                str(cfg.warmup_steps),
                *overrides,
                *cfg.extra,
                "--load-checkpoint",
                str(Path(cfg.load_checkpoint).resolve()),
                *(["--data", str(Path(data).resolve())] if data is not None else []),
            ),
            log,
        )
        wall = round(time.time() - t0, 1)
    pool_s, step_s = train_seconds(log)
    key = OwnerKey.load(key_path)
    threshold = metrics.min_matches_for_fpr(key.num_bits, cfg.fpr)
    base_config = Path(cfg.load_checkpoint).resolve().parent.parent / "config.yml"
    with contextlib.redirect_stdout(sys.stderr):
        _, pipeline, _ = load_run(run / "config.yml", data=data)
    params = sum(p.numel() for p in pipeline.model.sticker.parameters())
    # heads trained beside the sticker (none when their three loss weights are 0)
    heads_params = (
        sum(t.numel() for t in key.heads_state.values() if t.is_floating_point()) if pipeline.trains_heads else 0
    )
    # drawn as bench.unposed draws its views (its count at least), so view i is its page's view i
    image_cameras = (
        novel_cameras(
            pipeline.datamanager.train_dataset.cameras,
            max(cfg.image_views, HELD_OUT_VIEWS),
            torch.Generator().manual_seed(cfg.camera_seed),
        )[: cfg.image_views]
        if cfg.image_views > 0
        else None
    )
    points = []
    for ckpt in sorted((run / "nerfstudio_models").glob("step-*.ckpt")):
        n = int(ckpt.stem.split("-")[1])
        step = n if n % cfg.save_every == 0 else n + 1  # the final checkpoint is saved at step max - 1
        state = runs.load_checkpoint_state(ckpt)
        pipeline.model.load_state_dict(runs.model_state_from_pipeline_state(state["pipeline"]), strict=True)
        step_key = OwnerKey.load(step_key_path(key_path, n))  # the sticker as it was at this checkpoint
        pipeline.restore_owner(step_key, heads=False)
        pipeline.model.eval()
        pt = decode_checkpoint(
            pipeline,
            step_key,
            base_config,
            data,
            cfg.num_views,
            cfg.psnr_views,
            threshold,
            image_cameras,
            cfg.image_attacks,
        )
        secs = step_s.get(step, step_s.get(n + 1))
        pt.update(step=step, train_seconds=None if secs is None or pool_s is None else pool_s + secs)
        print(
            f"    {name} step {step}: bit acc {pt['bit_acc']:.3f} ({pt['views_passing']}/{cfg.num_views} views), "
            f"PSNR vs unwm {pt['psnr_vs_unwm']:.2f} dB, t {pt['train_seconds']} s"
            + "".join(f", image {a}: {v['matches']}" for a, v in pt.get("image", {}).items()),
            flush=True,
        )
        points.append(pt)
    h, w = (
        int(pipeline.datamanager.train_dataset.cameras.height[0]),
        int(pipeline.datamanager.train_dataset.cameras.width[0]),
    )
    return {
        "name": name,
        "overrides": overrides,
        "data": str(data) if data is not None else None,
        "size": [h, w],
        "num_bits": key.num_bits,
        "threshold": threshold,
        "sticker_params": params,
        "heads_params": heads_params,
        "pool_seconds": pool_s,
        "wall_seconds": wall,
        "points": points,
    }


def smallest_meeting(rows: List[Dict[str, Any]], bit_acc: float, psnr: float) -> Optional[Dict[str, Any]]:
    ok = [
        r
        for r in rows
        if r["points"]
        and r["points"][-1]["bit_acc"] >= bit_acc
        and r["points"][-1]["psnr_vs_unwm"] >= psnr
        and r["num_bits"] == 48
        and r["size"][0] == min(x["size"][0] for x in rows)
    ]
    return (
        min(ok, key=lambda r: (r["sticker_params"] + r.get("heads_params", 0), r["points"][-1]["train_seconds"] or 0))
        if ok
        else None
    )


def first_meeting(row: Dict[str, Any], bit_acc: float, psnr: float) -> Optional[Dict[str, Any]]:
    """The first checkpoint of ``row`` at or above both targets (None if none is)."""
    return next((p for p in row["points"] if p["bit_acc"] >= bit_acc and p["psnr_vs_unwm"] >= psnr), None)


def cost_lines(rows: List[Dict[str, Any]], bit_acc: float, psnr: float) -> List[str]:
    """How the cost of reaching the targets grows with image size and message length: a table row per variant."""
    lines = [
        f"Cost to reach the targets (first checkpoint at >= {100 * bit_acc:g} % and >= {psnr:g} dB; "
        "'not reached' within the run's steps):",
        "",
        "| variant | image | bits | step | train s | decode s/view | pool s | s/step |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: (r["size"][0], r["num_bits"], r["sticker_params"])):
        p = first_meeting(r, bit_acc, psnr)
        decode = sum(x["decode_seconds_per_view"] for x in r["points"]) / max(len(r["points"]), 1)
        pool, per_step = step_cost(r)
        lines.append(
            f"| {r['name']} | {r['size'][0]} px | {r['num_bits']} | "
            + (
                f"{p['step']} | {p['train_seconds'] if p['train_seconds'] is not None else '-'}"
                if p
                else "not reached | -"
            )
            + f" | {decode:.2f} | {'-' if pool is None else f'{pool:g}'} | "
            f"{'-' if per_step is None else f'{per_step:.2f}'} |"
        )
    return lines


def step_cost(row: Dict[str, Any]) -> Tuple[Optional[float], Optional[float]]:
    """(pool build seconds, training seconds per step after it) of a variant, from its last checkpoint."""
    pool = row.get("pool_seconds")
    last = row["points"][-1] if row["points"] else None
    if pool is None or last is None or last.get("train_seconds") is None or not last.get("step"):
        return pool, None
    return pool, (last["train_seconds"] - pool) / last["step"]


def chart(rows: List[Dict[str, Any]], path: Path) -> None:
    """Bit accuracy and PSNR against training time, and bit accuracy against PSNR: solid the geometric decoder (test
    views' PSNR), dashed the image decoder per attack (held-out renders' PSNR) where the points have its readings."""
    # deferred: only charts need it, slow to import
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(14, 3.9))
    marks = "sv^Dx+"
    for r in rows:
        pts = [p for p in r["points"] if p["train_seconds"] is not None]
        if not pts:
            continue
        t = [p["train_seconds"] / 60 for p in pts]
        acc = [100 * p["bit_acc"] for p in pts]
        (line,) = a1.plot(t, acc, "o-", label=f"{r['name']} geometric")
        c = line.get_color()
        a2.plot(t, [p["psnr_vs_unwm"] for p in pts], "o-", color=c, label=f"{r['name']} test views")
        a3.plot([p["psnr_vs_unwm"] for p in pts], acc, "o-", color=c, label=f"{r['name']} geometric")
        img = [p for p in pts if "image" in p]
        if img:
            ti = [p["train_seconds"] / 60 for p in img]
            a2.plot(ti, [p["image_psnr_db"] for p in img], "--", color=c, label=f"{r['name']} held-out 8-bit")
            for k, a in enumerate(dict.fromkeys(x for p in img for x in p["image"])):
                have = [p for p in img if a in p["image"]]
                ya = [100 * p["image"][a]["bit_acc"] for p in have]
                style = dict(color=c, ls="--", marker=marks[k % len(marks)], label=f"{r['name']} image {a}")
                a1.plot([p["train_seconds"] / 60 for p in have], ya, **style)
                a3.plot([p["image_psnr_db"] for p in have], ya, **style)
    low = min([y for ax in (a1, a3) for ln in ax.get_lines() for y in ln.get_ydata()] or [40.0])
    for ax in (a1, a3):
        ax.axhline(99, color="gray", ls=":", lw=0.8)
        ax.axhline(50, color="red", ls=":", lw=0.8)
        ax.set_ylabel("bit accuracy %")
        ax.set_ylim(max(40.0, low - 5), 101)  # chance (50 %) drawn when a curve comes near it
    a2.axhline(35, color="gray", ls=":", lw=0.8)
    a3.axvline(35, color="gray", ls=":", lw=0.8)
    a1.set_xlabel("training time (min)")
    a2.set_xlabel("training time (min)")
    a3.set_xlabel("PSNR watermarked vs unwatermarked (dB)")
    a2.set_ylabel("PSNR watermarked vs unwatermarked (dB)")
    a1.legend(fontsize=6)
    a2.legend(fontsize=6)
    fig.suptitle("sticker variants: accuracy and invisibility against training time (dotted: targets)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
