"""The null of several images-alone pages together: their unmarked images, each image counted once.

    python -m gsticker_plugin.bench.null_pool --pages docs/experiments/bench-unposed-evened.json docs/experiments/bench-unposed-evened-b.json \\
        --output docs/experiments/bench-null-pool.md

Reads the per-image rows that :mod:`gsticker_plugin.bench.unposed` wrote into each page's JSON. An unmarked image
(a row of :data:`~gsticker_plugin.evaluation.unposed_page.NULL_IMAGES`) is named by its row and index, the same image on
every page of one command's seeds; the first page that decoded it counts, the later readings are listed apart. The
other keys (one page's: every page draws the same 64 messages with the same seed) are a row of their own, never part
of the null: they check the messages' randomness on marked images, not the decoder on unmarked ones. Writes the Markdown page, its JSON and the null chart beside it.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Tuple

import tyro

from gsticker_plugin.bench import command_lines
from gsticker_plugin.evaluation.unposed_page import is_null_row, null_chart, null_summary, read_nothing, row_key


@dataclass
class NullPoolConfig:
    """Pool the null of images-alone pages (their JSON) into one page."""

    pages: Tuple[Path, ...]
    """The pages' JSON files (``bench.unposed``'s), the first one's other keys and readings first."""
    output: Path = Path("docs/experiments/bench-null-pool.md")
    """The page; its JSON and chart go beside it."""


def pool_null(pages: List[Dict[str, Any]], names: List[str]) -> Dict[str, Any]:
    """Every page's unmarked images, each ``(row, index)`` once (the first page's reading), and the first other keys
    found; the images read again on a later page listed with each page's matches."""
    thresholds = {p["threshold"] for p in pages}
    if len(thresholds) != 1:
        raise ValueError(f"the pages pass at different thresholds {sorted(thresholds)}: pool pages of one key size")
    first: Dict[Tuple[str, int], Dict[str, Any]] = {}
    again: Dict[Tuple[str, int], List[Tuple[str, int]]] = {}
    counted: Dict[str, int] = {}
    for page, name in zip(pages, names):
        counted[name] = 0
        for r in page["per_image"]:
            if not is_null_row(r["row"]):
                continue
            image = (row_key(r["row"]), int(r["view"]))
            if image in first:
                again.setdefault(image, [(first[image]["page"], first[image]["matches"])]).append((name, r["matches"]))
                continue
            first[image] = {**r, "page": name}
            counted[name] += 1
    others_from = next((n for p, n in zip(pages, names) if p.get("other_keys")), None)
    others = pages[names.index(others_from)]["other_keys"] if others_from is not None else None
    rows = list(first.values())
    num_bits = next((len(r["bits"]) for r in rows if "bits" in r), 48)
    null = null_summary(rows, pages[0]["threshold"], num_bits)
    if null is None:
        raise ValueError("the pages hold no unmarked image read: nothing to pool")
    by_row: Dict[str, List[int]] = {}
    for r in rows:
        if not read_nothing(r):
            by_row.setdefault(row_key(r["row"]), []).append(int(r["matches"]))
    return {
        "null": null,
        "other_keys": others,
        "other_keys_from": others_from,
        "images_per_page": counted,
        "rows": {k: {"images": len(v), "mean": sum(v) / len(v), "max": max(v)} for k, v in by_row.items()},
        "read_again": [
            {"row": k[0], "view": k[1], "readings": [{"page": n, "matches": m} for n, m in v]} for k, v in again.items()
        ],
        "threshold": pages[0]["threshold"],
    }


def main(cfg: NullPoolConfig) -> Dict[str, Any]:
    missing = [str(p) for p in cfg.pages if not p.is_file()]
    if missing:
        raise SystemExit(
            f"error: no page JSON at {', '.join(missing)}: write it with python -m gsticker_plugin.bench.unposed"
        )
    pages = [json.loads(p.read_text()) for p in cfg.pages]
    names = [p.with_suffix(".md").name for p in cfg.pages]
    try:
        res = pool_null(pages, names)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    res["command"] = "python -m gsticker_plugin.bench.null_pool " + " ".join(sys.argv[1:])
    res["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    res["pages"] = [
        {
            "page": n,
            "model": p["command"].split("--load-config ")[-1].split(" ")[0],
            "psnr_marked_vs_clean_db": p.get("psnr_marked_vs_clean_db"),
            "decoded": p.get("decoded", p.get("date")),
            "key_sha256": p.get("key_sha256"),
        }
        for p, n in zip(pages, names)
    ]
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    cfg.output.with_suffix(".json").write_text(json.dumps(res, indent=1))
    null, t = res["null"], res["threshold"]
    num_bits = len(null["histogram"]) - 1
    chart = cfg.output.with_name(cfg.output.stem + ".png")
    null_chart(null, [], [], chart, num_bits, t)
    lines = [
        *command_lines(
            "The images-alone null, pooled over pages",
            res["date"],
            cfg.output.with_suffix(".json").name,
            res["command"],
        ),
        "| page | model | owner key sha256 | PSNR marked vs clean (dB) | decoded | unmarked images counted |",
        "|---|---|---|---:|---|---:|",
    ]
    for p in res["pages"]:
        psnr = p["psnr_marked_vs_clean_db"] or {}
        lines.append(
            f"| [{p['page']}]({p['page']}) | `{p['model']}` | {(p['key_sha256'] or 'not recorded')[:16]} | "
            f"{psnr.get('mean', float('nan')):.2f} | {p['decoded']} | "
            f"{res['images_per_page'][p['page']]} |"
        )
    lines += ["", "| unmarked images | read | mean matches | max |", "|---|---:|---:|---:|"]
    for row, s in res["rows"].items():
        lines.append(f"| {row} | {s['images']} | {s['mean']:.1f} | {s['max']} |")
    if res["other_keys_from"]:
        ok = res["other_keys"]
        lines.append(
            f"| other keys ({res['other_keys_from']}'s marked images, one check a key; not in the null) | "
            f"{ok['checks']} | {ok['matches_mean']:.1f} | {ok['matches_max']} |"
        )
    lines += [
        "",
        f"**The null: {null['images']} distinct unmarked images, each counted once: mean {null['matches_mean']:.1f}, "
        f"max {null['matches_max']}, {null['passing']} at or above {t}/{num_bits}** (empirical false-positive rate "
        f"{null['fpr']:.3f}, 95 % upper bound {null['fpr_upper_95']:.3f}); {null['nothing_read']} more images had "
        "nothing to read (every bit undetermined at the camera found) and are not counted. The other keys' checks are "
        "not null images: they are reported in their row and left out of this count.",
        "",
        f"![null]({chart.name})",
    ]
    if res["read_again"]:
        lines += ["", "Images decoded on more than one page (counted once, on the first):", ""]
        for a in res["read_again"]:
            readings = ", ".join(f"{r['page']} {r['matches']}" for r in a["readings"])
            lines.append(f"- {a['row']} {a['view']}: {readings}")
    cfg.output.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main(tyro.cli(NullPoolConfig))
