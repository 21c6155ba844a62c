"""The shared run of ``ns-train geometrysticker`` read back (``python -m gsticker_plugin.bench.shared``).

1. ``ns-train geometrysticker`` on the base (message and pattern seed drawn from ``--seed``; timed): the field-marked
   stock run and its owner key.
2. The recolors of that run (``ns-recolor``; every spec in ``--recolors``).
3. Every ``--every``-th test view: the field-mark decoder on the shared run, with render PSNR vs the ground truth;
   every ``--null-every``-th on the unmarked base and each ``--null`` (independently trained bases), every
   ``--recolor-every``-th on each recolor. The verdict of each suspect follows ``ns-verify-owner``'s rule (per-view FPR 1e-6, half the views).

Rows go to ``WORK/rows.jsonl`` as they are measured (a rerun continues); writes a Markdown page and its JSON.
"""

from __future__ import annotations

import contextlib
import json
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Tuple

import torch

from gsticker_plugin.bench import bench_main, command_lines, provenance, suspect_summary
from gsticker_plugin.machine import config_under, console_script, recolor_into, run_logged

RECOLORS: Tuple[str, ...] = (
    *(
        f"palette:--set 0={c}"
        for c in ("green", "yellow", "orange", "red", "pink", "magenta", "purple", "blue", "dodgerblue", "cyan")
    ),
    "hue:--shift 0.25",
    "hue:--shift 0.5",
    "hue:--shift -0.25",
    "finetune:--set 0=blue --steps 50",
    "finetune:--hue-shift 0.5 --steps 50",
)
"""Fifteen recolors fixed before any was read: palette entry 0 to each of ten colours, three model-level hue turns,
two 50-step colour fine-tunes (toward a blue palette edit and toward a half-turn of hue)."""


@dataclass
class Args:
    base: Path
    """The base run's config.yml (nerfacto with the torch implementation, or TensoRF vector-matrix)."""
    data: Path
    """Its dataset folder."""
    work_dir: Path = Path("outputs/bench-shared")
    seed: int = 20261207
    """Message and pattern seed (drawn before the run; a user's are drawn with `secrets`)."""
    every: int = 1
    """Read every this-many-th test view on the shared run."""
    null_every: int = 8
    """... every this-many-th on the unmarked base and each --null."""
    recolor_every: int = 8
    """... and every this-many-th on each recolor."""
    null: Tuple[Path, ...] = ()
    """Independently trained bases of the same scene (config.yml)."""
    recolors: Tuple[str, ...] = RECOLORS
    """ns-recolor edits of the shared run: each `SUBCOMMAND:ARG ARG`."""
    mark: str = "auto"
    """--pipeline.mark of the shared run (auto: the field mark, where the base hosts it)."""
    output: Path = Path("docs/experiments/bench-shared.md")
    page_only: bool = False
    """Rewrite the page from OUTPUT's JSON (no measuring)."""


def train_shared(args: Args) -> Tuple[Path, Path, Dict[str, Any]]:
    """``ns-train geometrysticker`` on the base (skipped when its run exists); returns (run config, key, record)."""
    from gsticker_plugin.runs import latest_checkpoint

    work = args.work_dir
    key, record = work / "owner.gskey", work / "train.json"
    g = torch.Generator().manual_seed(args.seed)
    bits = "".join(str(int(b)) for b in torch.randint(0, 2, (48,), generator=g))
    if not record.is_file():
        ckpt = latest_checkpoint(args.base.parent / "nerfstudio_models")
        cmd = [console_script("ns-train"), "geometrysticker", "--load-checkpoint", str(ckpt), "--data", str(args.data)]
        cmd += ["--machine.device-type", "cpu", "--vis", "tensorboard", "--output-dir", str(work / "runs")]
        cmd += ["--experiment-name", "lego", "--timestamp", "shared", "--pipeline.key-path", str(key)]
        cmd += ["--pipeline.message", bits, "--pipeline.pattern-seed", str(args.seed), "--pipeline.mark", args.mark]
        t0 = time.time()
        run_logged(cmd, work / "train.log", what="ns-train geometrysticker")
        record.write_text(json.dumps({"seconds": time.time() - t0}))
    return config_under(work / "runs"), key, json.loads(record.read_text())


def ground_truth(dataset, i: int) -> torch.Tensor:
    """Test image ``i`` [3 H W] composited on white (the Blender recipe's background)."""
    img = dataset.get_image_float32(i)
    if img.shape[-1] == 4:
        img = img[..., :3] * img[..., 3:] + (1.0 - img[..., 3:])
    return img.permute(2, 0, 1)


def measure(args: Args) -> Dict[str, Any]:
    from gsticker_plugin import metrics
    from gsticker_plugin.decoders.fieldmark import decode_suspect, load_field_reference
    from gsticker_plugin.key import OwnerKey
    from gsticker_plugin.runs import load_run

    args.work_dir.mkdir(parents=True, exist_ok=True)
    shared_cfg, key_path, trained = train_shared(args)
    recolored = []
    for i, edit in enumerate(args.recolors):
        sub, _, rest = edit.partition(":")
        dest = args.work_dir / "recolor" / str(i)
        recolor_into([sub, *rest.split()], shared_cfg, dest, args.work_dir / f"recolor{i}.log", what=edit)
        recolored.append((f"recolor: {sub} {rest}", config_under(dest), args.recolor_every))
    dev = torch.device("cpu")
    key = OwnerKey.load(key_path)
    ref = load_field_reference(key, key_path, None, args.data, dev)
    suspects = [("shared run", shared_cfg, args.every), ("unmarked base", args.base, args.null_every)]
    suspects += [(f"independent base {n.parent.parent.parent.name}", n, args.null_every) for n in args.null]
    suspects += recolored
    models = {}
    for label, cfg, _ in suspects:
        with contextlib.redirect_stdout(sys.stderr):
            models[label] = load_run(cfg, data=args.data, device=dev)[1].model
    dataset = ref.pipeline.datamanager.eval_dataset
    rows_path = args.work_dir / "rows.jsonl"
    done = (
        {(r["suspect"], r["view"]) for r in map(json.loads, rows_path.read_text().splitlines())}
        if (rows_path.is_file())
        else set()
    )
    for vi in range(len(dataset.cameras)):
        cam, cache = [(f"test/{vi:03d}", dataset.cameras[vi : vi + 1])], {}
        for label, _, every in suspects:
            if vi % every or (label, vi) in done:
                continue
            t0 = time.time()
            dec, views = decode_suspect(key, ref, models[label], 1, 0.0, args.seed, cameras=cam, cache=cache)
            img = views[0].image[None]
            row = {
                "suspect": label,
                "view": vi,
                "matches": int(dec["matches"][0]),
                "explained": dec["geometry"][0]["explained"],
                "psnr_vs_truth": float(metrics.psnr(img, ground_truth(dataset, vi)[None])),
                "seconds": time.time() - t0,
            }
            with rows_path.open("a") as f:
                f.write(json.dumps(row) + "\n")
        print(f"test view {vi} done", file=sys.stderr, flush=True)
    rows = [json.loads(line) for line in rows_path.read_text().splitlines()]
    return {
        "train": trained,
        "method": ref.method,
        "psnr_vs_base_train_views": key.field_mark["psnr_vs_base"],
        "shared_run": str(shared_cfg),
        "suspects": [s[0] for s in suspects],
        "rows": rows,
        "threshold": metrics.min_matches_for_fpr(key.num_bits, 1e-6),
        **provenance("gsticker_plugin.bench.shared"),
    }


def summary(res: Dict[str, Any], label: str) -> Dict[str, Any]:
    rows = [r for r in res["rows"] if r["suspect"] == label]
    return {
        **suspect_summary(rows, res["threshold"]),
        "psnr_vs_truth": statistics.mean(r["psnr_vs_truth"] for r in rows),
    }


def page(res: Dict[str, Any]) -> str:
    lines = command_lines(
        f"The shared run: a stock {res.get('method', 'nerfacto')} with the mark in its field, read back",
        f"{res['date']}, {res['machine']['cpu']}",
        res["json"],
        res["command"],
    )
    lines += [
        f"`ns-train geometrysticker` wrote the shared run in {res['train']['seconds']:.0f} s (wall, everything: loading "
        f"the base, marking its {'planes' if res.get('method') == 'tensorf' else 'hash table'}, measuring {res['psnr_vs_base_train_views']:.1f} dB render PSNR vs the base "
        "on 4 training views, writing the key and the run). Each suspect below is loaded like any suspect and read "
        f"by the field-mark decoder; a view passes at >= {res['threshold']}/48 (per-view FPR 1e-6), a suspect is "
        "OWNED when half its views pass.",
        "",
        "| suspect | test views | passing | bit accuracy | matches min / median / max | verdict | PSNR vs truth (dB) |",
        "|---|---|---|---|---|---|---|",
    ]
    for label in res["suspects"]:
        s = summary(res, label)
        lines.append(
            f"| {label} | {s['views']} | {s['passing']} | {100 * s['bit_acc']:.2f} % | {s['min']} / {s['median']:g} / "
            f"{s['max']} | {s['verdict']} | {s['psnr_vs_truth']:.2f} |"
        )
    both = {r["view"] for r in res["rows"] if r["suspect"] == "unmarked base"}
    psnr = {
        label: statistics.mean(r["psnr_vs_truth"] for r in res["rows"] if r["suspect"] == label and r["view"] in both)
        for label in ("shared run", "unmarked base")
    }
    lines += [
        "",
        f"Render PSNR vs the ground truth on the {len(both)} test views read on both: shared run "
        f"{psnr['shared run']:.3f} dB, unmarked base {psnr['unmarked base']:.3f} dB "
        f"(difference {psnr['shared run'] - psnr['unmarked base']:+.3f} dB).",
        "",
        "Each row's seconds (the decoder on one suspect: its render and the fit; the base's view is computed once per "
        "camera and counted on the first suspect) are in the JSON; this page quotes none: time a suspect with the "
        "machine alone.",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    bench_main(Args, measure, page)


if __name__ == "__main__":
    main()
