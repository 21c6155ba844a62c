"""What the informed decoders cost per suspect: whole renders against renders of the read rays only.

    python -m gsticker_plugin.bench.decode \\
        --key RUN.gskey --load-config RUN/config.yml --data ../shared/data/lego100 --output outputs/bench-decode.md

The owner's base is rebuilt from the key and its reference views rendered once (as ``ns-gsticker-eval`` keeps
them); then the suspect is decoded ``--repeats`` times each way (geometric decoder, sticker on and off), with
``full_renders=True`` (``ns-verify-owner``: whole views, for its figure) and ``full_renders=False`` (the protocol,
``calibrate``, the sweep: the suspect rendered only at the rays the fit reads). Writes a Markdown table (seconds per
suspect and per view, rays read, how many bits the suspect left undetermined, whether the decoded bits are
identical) and a JSON beside it.
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
from typing import Any, Dict, List, Optional

import torch
import tyro

from gsticker_plugin import compat
from gsticker_plugin.decoders.geometric import decode_suspect
from gsticker_plugin.decoders.reference import load_base_reference
from gsticker_plugin.errors import GStickerError, run_command
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.runs import load_run


@dataclass
class BenchDecodeConfig:
    """Time the geometric decoder on one suspect with whole renders and with the read rays only."""

    key: Path
    """The owner key (version 2: it carries the geometry reference)."""
    load_config: Path
    """The suspect run's config.yml (e.g. the watermarked run)."""
    data: Optional[Path] = None
    """Dataset folder when the runs' recorded one does not exist here."""
    num_views: int = 8
    """Cameras per decode (as the protocol's geometry.num_views)."""
    sampled_share: float = 0.25
    """Share of sampled orbit poses among them."""
    repeats: int = 1
    """Decodes per setting (the fastest is reported)."""
    output: Path = Path("outputs/bench-decode.md")
    """Markdown table; the JSON goes beside it."""


def main(cfg: BenchDecodeConfig) -> Dict[str, Any]:

    compat.apply()  # the plugin's host fixes (offline LPIPS, checkpoint types)
    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
    if cfg.repeats < 1 or cfg.num_views < 1:
        raise GStickerError("--repeats and --num-views must be at least 1")
    device = torch.device("cpu")
    key = OwnerKey.load(cfg.key)
    with contextlib.redirect_stdout(sys.stderr):
        ref = load_base_reference(key, cfg.key, None, cfg.data, device)
        _, pipe, _ = load_run(cfg.load_config, data=cfg.data, device=device)
    cache: Dict[Any, Any] = {}
    t0 = time.time()
    decode_suspect(
        key, ref, pipe.model, cfg.num_views, cfg.sampled_share, 0, ref_cache=cache, relinearize=0, full_renders=False
    )
    reference_s = time.time() - t0
    rows: List[Dict[str, Any]] = []
    for sticker in (True, False):
        decoded = {}
        for full in (True, False):
            best = float("inf")
            for _ in range(cfg.repeats):
                t0 = time.time()
                dec, _ = decode_suspect(
                    key,
                    ref,
                    pipe.model,
                    cfg.num_views,
                    cfg.sampled_share,
                    0,
                    ref_cache=cache,
                    sticker=sticker,
                    full_renders=full,
                )
                best = min(best, time.time() - t0)
            decoded[full] = dec
            rows.append(
                {
                    "sticker": "on" if sticker else "off",
                    "renders": "whole views" if full else "read rays only",
                    "seconds": round(best, 2),
                    "seconds_per_view": round(best / cfg.num_views, 2),
                    "rays_read_mean": sum(d["rays"] for d in dec["geometry"]) / len(dec["geometry"]),
                    "matches": [int(m) for m in dec["matches"].tolist()],
                    "undetermined": [int(d["undetermined"]) for d in dec["geometry"]],
                }
            )
        same = bool(torch.equal(decoded[True]["bits"], decoded[False]["bits"]))
        rows[-1]["bits_identical_to_whole"] = rows[-2]["bits_identical_to_whole"] = same
    cam0 = ref.pipeline.datamanager.train_dataset.cameras[0:1]
    h, w = int(cam0.height.item()), int(cam0.width.item())
    res = {
        "command": "python -m gsticker_plugin.bench.decode " + " ".join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "cpu": platform.processor() or platform.machine(),
        "threads": torch.get_num_threads(),
        "suspect": str(cfg.load_config),
        "pixels_per_view": int(h * w),
        "num_views": cfg.num_views,
        "reference_views_seconds": round(reference_s, 2),
        "rows": rows,
    }
    lines = [
        "# Decoding cost: whole renders vs read rays only",
        "",
        f"`{res['command']}` ({res['date']}, {res['threads']} threads). Suspect `{cfg.load_config}`, "
        f"{cfg.num_views} views of {res['pixels_per_view']} pixels; the base's reference views rendered once "
        f"before ({reference_s:.1f} s, as the protocol caches them).",
        "",
        "| sticker | suspect renders | s per suspect | s per view | rays read per view | matches | undetermined bits "
        "| bits identical |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['sticker']} | {r['renders']} | {r['seconds']:.2f} | {r['seconds_per_view']:.2f} | "
            f"{r['rays_read_mean']:.0f} | {' '.join(map(str, r['matches']))} | "
            f"{' '.join(map(str, r['undetermined']))} | {'yes' if r['bits_identical_to_whole'] else 'NO'} |"
        )
    lines += [
        "",
        "Undetermined bits (zero residual: the suspect's geometry equals the base's there) are marked "
        "undetermined in both modes (and count as mismatches), so they agree by construction; only the fitted "
        "bits test the two modes.",
    ]
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    cfg.output.write_text("\n".join(lines) + "\n")
    cfg.output.with_suffix(".json").write_text(json.dumps(res, indent=2))
    print("\n".join(lines))
    return res


def entrypoint() -> None:
    cfg = tyro.cli(BenchDecodeConfig)
    raise SystemExit(run_command(lambda: [main(cfg), 0][1]))


if __name__ == "__main__":
    entrypoint()
