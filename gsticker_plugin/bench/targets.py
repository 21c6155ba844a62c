"""The sticker's targets, measured on every test view: bit accuracy, PSNR against the clean render and the ground truth.

    python -m gsticker_plugin.bench.targets \\
        --load-checkpoint ../shared/checkpoints/lego100-nerfacto-small/nerfacto/base/nerfstudio_models/step-000002999.ckpt \\
        --data ../shared/data/lego100 --output-dir outputs/bench-targets

1. ``ns-train geometrysticker`` for ``--steps`` steps on the base (timed; skipped when the run exists);
2. every view of the test split (``--max-views`` to stop early): the watermarked render decoded with the informed
   geometric decoder and the owner key, compared with the owner's unwatermarked base at the same camera (the
   decoder's reference render, the same pixels as the run with its sticker off) and with the ground truth. Per-view
   rows are appended to ``views.jsonl`` as they finish, so an interrupted run resumes.

Writes the page ``--output`` (default ``docs/experiments/bench-targets.md``: the targets of the sticker issue, 48 bits, >= 99.5 %
bit accuracy over all test views, >= 35 dB watermarked vs unwatermarked, test PSNR within 0.3 dB of the base, <= 15
min of training, each with the measured number and met / not met), beside it a JSON of the same stem holding every
number the page prints, and a PNG chart; ``results.json`` in ``--output-dir`` keeps the training record for resuming.
"""

from __future__ import annotations

import contextlib
import json
import platform
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional

import torch
import tyro

from gsticker_plugin import compat
from gsticker_plugin.decoders.geometric import decode_suspect
from gsticker_plugin.decoders.reference import load_base_reference
from gsticker_plugin.evaluate import psnr_nhw3
from gsticker_plugin.evaluation.sticker_runs import StickerRunConfig, train_sticker
from gsticker_plugin.evaluation.targets import chart, report, summarize
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.runs import load_run
from gsticker_plugin.views import progress_bar


@dataclass
class BenchTargetsConfig(StickerRunConfig):
    """Train a sticker on a base and measure the issue's targets on every test view."""

    output_dir: Path = Path("outputs/bench-targets")
    """Where the run, the per-view rows and the training record are written."""
    output: Path = Path("docs/experiments/bench-targets.md")
    """The page; the JSON with every number it prints (same stem, ``.json``) and the chart (``.png``) go beside it."""
    steps: int = 300
    """Sticker training steps."""
    max_views: Optional[int] = None
    """Stop after this many test views (default: all of them)."""
    chunk: int = 10
    """Views decoded between two appends to views.jsonl."""
    seed: int = 0
    """Seed of the decoder's tie-breaking coin flips."""
    progress: bool = True
    """tqdm progress bars on stderr."""


def main(cfg: BenchTargetsConfig) -> Dict[str, Any]:

    compat.apply()  # the plugin's host fixes (offline LPIPS, checkpoint types)
    out, logs, data, base_ckpt, base_config = cfg.layout()
    wm = out / "bench" / "geometrysticker" / "watermarked"
    key_path = wm.with_name("watermarked.gskey")
    res_path = out / "results.json"
    results: Dict[str, Any] = json.loads(res_path.read_text()) if res_path.is_file() else {}
    results["config"] = {k: str(v) for k, v in vars(cfg).items()}

    print("[1/2] ns-train geometrysticker", flush=True)
    trained = train_sticker(cfg, out, base_ckpt, data, logs)
    if trained is not None:
        results["train"] = trained
    res_path.write_text(json.dumps(results, indent=2))

    print("[2/2] every test view: geometric decode, PSNR", flush=True)
    device = torch.device("cpu")
    warnings.filterwarnings("ignore")  # nerfstudio 1.1.5's camera indexing warns on every render with this torch
    key = OwnerKey.load(key_path)
    data_path = Path(cfg.data) if cfg.data is not None else None
    ref = load_base_reference(key, key_path, base_config, data_path, device)
    with contextlib.redirect_stdout(sys.stderr):
        _, pipe, _ = load_run(wm / "config.yml", data=data_path, device=device)
    dataset = pipe.datamanager.eval_dataset  # load_run builds the run in test mode: the test split
    n = len(dataset) if cfg.max_views is None else min(cfg.max_views, len(dataset))
    rows_path = out / "views.jsonl"
    done = {}
    if rows_path.is_file():
        for line in rows_path.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                done[r["index"]] = r
    todo = [i for i in range(n) if i not in done]
    ref_cache: Dict[Any, Any] = {}
    for start in progress_bar(range(0, len(todo), cfg.chunk), "test views (chunks)", cfg.progress):
        idx = todo[start : start + cfg.chunk]
        t0 = time.time()
        cams = [(f"test/{i:03d}", dataset.cameras[i : i + 1]) for i in idx]
        dec, views = decode_suspect(
            key,
            ref,
            pipe.model,
            len(cams),
            0.0,
            cfg.seed,
            sticker=True,
            progress=False,
            ref_cache=ref_cache,
            cameras=cams,
        )
        # the unwatermarked render: the owner's base at the same camera, rendered once by the decoder (its reference)
        base_images = {name: v.image for (name, _), v in ref_cache.items()}
        ref_cache.clear()  # every camera is decoded once
        decode_s = time.time() - t0
        rows = []
        for j, i in enumerate(idx):
            clean = base_images[cams[j][0]].permute(1, 2, 0).float().clamp(0, 1)
            marked = views[j].image.permute(1, 2, 0)
            gt = dataset.get_image_float32(i)
            if gt.shape[-1] == 4:
                gt = gt[..., :3] * gt[..., 3:] + (1.0 - gt[..., 3:])  # Blender scenes: white background
            gt = gt[..., :3].float()
            p = [float(psnr_nhw3(a[None], b[None])[0]) for a, b in ((marked, clean), (marked, gt), (clean, gt))]
            rows.append(
                {
                    "index": i,
                    "matches": int(dec["matches"][j]),
                    "bit_acc": float(dec["bit_acc"][j]),
                    "pvalue": float(dec["pvalues"][j]),
                    "psnr_vs_clean_db": p[0],
                    "psnr_marked_vs_gt_db": p[1],
                    "psnr_clean_vs_gt_db": p[2],
                    "decode_s": decode_s / len(idx),
                }
            )
        with open(rows_path, "a") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")
                done[r["index"]] = r
    rows = [done[i] for i in sorted(done) if i < n]
    results["views"] = summarize(rows, key.num_bits, results.get("train"), len(dataset))
    results["run"] = {
        "command": "python -m gsticker_plugin.bench.targets " + " ".join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "cpu": platform.processor() or platform.machine(),
        "threads": torch.get_num_threads(),
        "steps": cfg.steps,
        "pool_views": cfg.pool_views,
        "warmup_steps": cfg.warmup_steps,
        "owner_id": cfg.owner_id,
        # a benchmark's message is not a secret: `--message BITS` reproduces this page
        "message": "".join(str(int(b)) for b in key.message.tolist()),
        "base_checkpoint": str(cfg.load_checkpoint),
        "views_jsonl": str(rows_path),
    }
    res_path.write_text(json.dumps(results, indent=2))
    page_path = cfg.output.resolve()
    page_path.parent.mkdir(parents=True, exist_ok=True)
    png = chart(rows, key.num_bits, results["views"]["threshold"], page_path.with_suffix(".png"))
    md = page(results, page_path.with_suffix(".json").name, png.name if png is not None else None)
    page_path.with_suffix(".json").write_text(
        json.dumps({"run": results["run"], "train": results.get("train"), "views": results["views"]}, indent=2)
    )
    page_path.write_text(md)
    print(md)
    return results


def page(results: Dict[str, Any], json_name: str, png_name: Optional[str]) -> str:
    """The whole Markdown page: the command, what it did, :func:`report`'s table, the chart and the limits."""
    r, v = results["run"], results["views"]
    trained = results.get("train") is not None
    what = (
        f"It trained a {r['steps']}-step sticker on the base (`ns-train geometrysticker`, {r['pool_views']} + "
        f"{r['pool_views']} pool views, warm-up {r['warmup_steps']} steps, owner id `{r['owner_id']}`"
        + (f", message `{r['message']}`: `--message` with these bits reproduces the page)" if r.get("message") else ")")
        if trained
        else "It used the watermarked run already in the output folder (training not timed here)"
    )
    lines = [
        "# The sticker's targets on every test view",
        "",
        f"Command ({r['date']}, {r['cpu']}, {r['threads']} threads; every number on this page is in "
        f"[{json_name}]({json_name}), written by it):",
        "",
        "```bash",
        r["command"],
        "```",
        "",
        f"{what}, then decoded {v['views']} of the {v['split_views']} test views of the watermarked run with the informed "
        "geometric decoder (`ns-verify-owner --decode geometry`'s decoder: the owner key and the owner's base run), and "
        "compared each view with the unwatermarked render (the owner's base at the same camera, which the decoder "
        "renders anyway) and with the ground truth (on white). Per-view rows: `views.jsonl` in the output folder (an "
        "interrupted run resumes).",
        "",
        report(v).rstrip("\n"),
        "",
    ]
    if png_name:
        lines += [f"![per-view matched bits and PSNR]({png_name})", ""]
    lines += [
        "What this does *not* show: the blind extractor (reading bits from images without the base); these "
        "targets hold for the informed, model-level decoder on this base. Robustness to recoloring and the null "
        "(unwatermarked models at chance) are in [results.md](results.md)."
    ]
    return "\n".join(lines) + "\n"


def entrypoint() -> None:
    main(tyro.cli(BenchTargetsConfig))


if __name__ == "__main__":
    entrypoint()
