"""The torch hash encoding, stock against :mod:`gsticker_plugin.hashgrid`, on a real base
(``python -m gsticker_plugin.bench.hashgrid --base RUN/config.yml``).

Times, in one process with the thread count given: the base's hash encoding alone on ``--samples`` random points, and
whole renders of ``--views`` training cameras, each stock then sped up (alternating, ``--repeats`` times; the median
is kept), and checks that both give the same bits. Writes a Markdown page and its JSON.
"""

from __future__ import annotations

import contextlib
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Optional

import torch

from gsticker_plugin.bench import bench_main, command_lines, provenance


@dataclass
class Args:
    base: Path
    """A nerfacto run (torch implementation) config.yml."""
    data: Optional[Path] = None
    """Its dataset folder, when the recorded one does not exist from here."""
    samples: int = 200_000
    views: int = 2
    repeats: int = 3
    threads: int = 1
    output: Path = Path("docs/experiments/bench-hashgrid.md")
    page_only: bool = False
    """Rewrite the page from OUTPUT's JSON (no measuring)."""


def median_seconds(fn: Callable[[], Any], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def measure(args: Args) -> Dict[str, Any]:
    from nerfstudio.field_components.encodings import HashEncoding

    from gsticker_plugin import hashgrid, runs

    torch.set_num_threads(args.threads)
    with contextlib.redirect_stdout(sys.stderr):
        _, pipeline, _ = runs.load_run(args.base, data=args.data, device=torch.device("cpu"))
    model = pipeline.model
    encoders = [m for m in model.modules() if isinstance(m, HashEncoding)]
    for enc in encoders:  # load_run sped them up: start from the stock class's forward
        vars(enc).pop("pytorch_fwd", None)
    x = torch.rand(args.samples, 3, generator=torch.Generator().manual_seed(0))
    enc = encoders[0]
    with torch.no_grad():
        same_encoding = bool(torch.equal(enc.pytorch_fwd(x), hashgrid.encode(enc, x)))
        encode_stock = median_seconds(lambda: enc.pytorch_fwd(x), args.repeats)
        encode_fast = median_seconds(lambda: hashgrid.encode(enc, x), args.repeats)
    cams = pipeline.datamanager.train_dataset.cameras

    def render_all() -> list:
        with torch.no_grad():
            return [model.get_outputs_for_camera(cams[i : i + 1])["rgb"] for i in range(args.views)]

    stock_images = render_all()
    render_stock = median_seconds(render_all, args.repeats)
    hashgrid.speed_up(model)
    same_renders = all(torch.equal(a, b) for a, b in zip(stock_images, render_all()))
    render_fast = median_seconds(render_all, args.repeats)
    return {
        "base": str(args.base),
        "model": type(model).__name__,
        "hash_encodings": len(encoders),
        "levels": int(enc.num_levels),
        "table_size": int(enc.hash_table_size),
        "samples": args.samples,
        "views": args.views,
        "image": [int(cams.height[0]), int(cams.width[0])],
        "threads": args.threads,
        "repeats": args.repeats,
        "encode_seconds": {"stock": encode_stock, "hashgrid": encode_fast},
        "render_seconds": {"stock": render_stock, "hashgrid": render_fast},
        "same_encoding": same_encoding,
        "same_renders": same_renders,
        **provenance("gsticker_plugin.bench.hashgrid"),
    }


def page(res: Dict[str, Any]) -> str:
    e, r = res["encode_seconds"], res["render_seconds"]
    h, w = res["image"]
    lines = command_lines(
        "The torch hash encoding: stock against hashgrid",
        res["date"],
        res["json"],
        res["command"],
    )
    m = res["machine"]
    lines += [
        f"Machine: {m['cpu']}, {m['nproc']} cores, torch {m['torch']}, nerfstudio {m['nerfstudio']}; nothing else "
        "running.",
        "",
        f"Base: `{res['base']}` ({res['model']}, {res['hash_encodings']} hash encodings; the field's: {res['levels']} "
        f"levels, table {res['table_size']} rows). {res['threads']} thread(s), median of {res['repeats']} runs each.",
        "",
        "| what | stock (s) | hashgrid (s) | speed-up | same bits |",
        "|---|---|---|---|---|",
        f"| the field's encoding, {res['samples']:,} points | {e['stock']:.3f} | {e['hashgrid']:.3f} | "
        f"{e['stock'] / e['hashgrid']:.2f}x | {'yes' if res['same_encoding'] else 'NO'} |",
        f"| {res['views']} renders at {h}x{w} px | {r['stock']:.2f} | {r['hashgrid']:.2f} | "
        f"{r['stock'] / r['hashgrid']:.2f}x | {'yes' if res['same_renders'] else 'NO'} |",
        "",
        "`hashgrid` is what gsticker's own renders use (the models it loads, the sticker stage's base); training a "
        "table and stock `ns-train`/`ns-render` run the stock code.",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    bench_main(Args, measure, page)


if __name__ == "__main__":
    main()
