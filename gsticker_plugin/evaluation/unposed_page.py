"""The images-alone bench's bookkeeping and page: rows and their counts, per-row summaries, the null (unmarked
images and other keys), the threat-model curves, and the Markdown page with its JSON and charts."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Protocol, Sequence, Tuple

import torch

from gsticker_plugin import metrics
from gsticker_plugin.decoders.unposed import MAP_SEARCH_SHARE
from gsticker_plugin.machine import machine_info


class PageConfig(Protocol):
    """What the page reads of the bench's config (:class:`gsticker_plugin.bench.unposed.BenchUnposedConfig`)."""

    key: Path
    rows: Tuple[str, ...]
    num_views: int
    camera_seed: int
    random_images: int
    other_keys: int
    development_views: int
    output: Path
    work_dir: Path
    page_only: bool
    purify_lr: float
    purify_rays_per_step: int


def read_nothing(row: Dict[str, Any]) -> bool:
    """Whether an image's every bit is undetermined: the camera found showed no ray the gate reads."""
    return "bits" in row and not any(c in "01" for c in row["bits"])


def unread(summary: Dict[str, Any]) -> str:
    """The table's note on a row's images with nothing to read (none: empty)."""
    n = summary.get("nothing_read", 0)
    return f"; {n} with nothing to read" if n else ""


def summarize(rows: List[Dict[str, Any]], threshold: int, num_bits: int, null: bool = False) -> Dict[str, Any]:
    """A row's images: their matches (a ``null`` row's over the images with bits read, those with nothing to read
    counted apart; a marked image with nothing to read counts its 0 matches), the routes they were read through, the
    camera error and the seconds."""
    read = ([r for r in rows if not read_nothing(r)] if null else rows) or rows
    m = torch.tensor([r["matches"] for r in read], dtype=torch.float64)
    out = {
        "images": len(rows),
        "nothing_read": sum(map(read_nothing, rows)),
        "bit_acc": float(m.mean() / num_bits),
        "matches_mean": float(m.mean()),
        "matches_min": int(m.min()),
        "matches_max": int(m.max()),
        "passing": int((m >= threshold).sum()),
        "read_by_value": sum(r["signals"] == ["value"] for r in rows),
        "read_through_map": sum(bool(r.get("color_map")) for r in rows),
        "searched_through_map": sum((r.get("map_share_at_search") or 0.0) >= MAP_SEARCH_SHARE for r in rows),
        "read_through_blur": sum(r.get("degradation", "none").startswith("blur") for r in rows),
        "read_as_turned": sum(r.get("degradation", "none").startswith("rotate") for r in rows),
        "read_through_jpeg": sum(r.get("degradation", "none").startswith("jpeg") for r in rows),
        "read_around_cover": sum((r.get("covered_share") or 0.0) > 0 for r in rows),
        "seconds_per_image": float(sum(r["seconds"] for r in rows) / len(rows)),
    }
    rot = [r["rotation_error_deg"] for r in rows if "rotation_error_deg" in r]
    if rot:
        out["rotation_error_deg_median"] = float(torch.tensor(rot).median())
        out["rotation_error_deg_max"] = float(max(rot))
    return out


def other_keys(rows: List[Dict[str, Any]], count: int, threshold: int) -> Optional[Dict[str, Any]]:
    """The marked images' decoded bits checked against ``count`` other owners' keys (messages drawn uniformly at
    random, seed 99): a check of the messages' randomness, reported in its own row and never pooled with the null of
    unmarked images. Each key is one check, against one marked image (the images in turn); ``matches_max_pairs`` and ``passing_pairs`` cover
    every image with every key (those pairs share images, so they are not independent). None without rows or keys."""
    rows = [r for r in rows if "bits" in r]
    if not rows or count <= 0:
        return None
    n = len(rows[0]["bits"])
    msgs = torch.randint(0, 2, (count, n), generator=torch.Generator().manual_seed(99))
    bits = torch.tensor([[int(c) if c in "01" else -1 for c in r["bits"]] for r in rows])
    m = (bits[:, None, :] == msgs[None]).sum(-1)  # [images, keys]
    one = m[torch.arange(count) % len(rows), torch.arange(count)].double()  # key j against image j mod images
    return {
        "keys": count,
        "images": len(rows),
        "checks": count,
        "matches_mean": float(one.mean()),
        "matches_max": int(one.max()),
        "passing": int((one >= threshold).sum()),
        "histogram": match_histogram(one.long().tolist(), n),
        "pairs": int(m.numel()),
        "matches_max_pairs": int(m.max()),
        "passing_pairs": int((m >= threshold).sum()),
    }


def match_histogram(matches: List[int], num_bits: int) -> List[int]:
    """How many checks matched 0, 1, ..., ``num_bits`` bits."""
    return torch.bincount(torch.tensor(matches, dtype=torch.long), minlength=num_bits + 1).tolist()


NULL_IMAGES = ("clean", "foreign", "random", "scene")
"""Rows of images that never held the owner's message."""


def is_null_row(row: str) -> bool:
    """Whether a row's images never held the owner's message (its images are one of :data:`NULL_IMAGES`)."""
    return row.partition(":")[0].partition("=")[0] in NULL_IMAGES


REMOVAL_ATTACKS = ("pgd", "purify", "leak")
"""Rows of the threat model: the recipient removing the mark (they may read like the null where they break it)."""


def is_removal_row(row: str) -> bool:
    """Whether a row's images are a removal attack's (:data:`REMOVAL_ATTACKS`)."""
    return row.partition(":")[0].partition("=")[0] in REMOVAL_ATTACKS


def null_chart(
    null: Dict[str, Any], marked: List[int], removed: List[int], path: Path, num_bits: int, threshold: int
) -> None:
    """Histogram of the null's matches beside Binomial(``num_bits``, 1/2) scaled to its images, the marked images'
    matches and the removal attacks' (log count axis), with the pass line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = list(range(num_bits + 1))
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    ax.bar(x, null["histogram"], 0.8, color="tab:gray", label=f"null: {null['images']} unmarked images")
    expected = [null["images"] * math.comb(num_bits, k) / 2**num_bits for k in x]
    ax.plot(x, expected, "k-", lw=1, label=f"Binomial({num_bits}, 1/2) x images")
    for values, color, label in (
        (marked, "tab:green", "marked model's images (attacked, recoloured)"),
        (removed, "tab:red", "removal attacks (pgd, purify)"),
    ):
        if values:
            ax.bar(x, match_histogram(values, num_bits), 0.8, color=color, alpha=0.8, label=f"{label}: {len(values)}")
    ax.axvline(threshold - 0.5, color="tab:blue", ls=":", label=f"pass line ({threshold}/{num_bits})")
    ax.set_yscale("log")
    ax.set_ylim(0.5, max(max(null["histogram"]), len(marked), len(removed), 1) * 3)
    ax.set_xlabel(f"matching bits (of {num_bits})")
    ax.set_ylabel("images")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def null_summary(rows: List[Dict[str, Any]], threshold: int, num_bits: int = 48) -> Optional[Dict[str, Any]]:
    """The null: the distinct unmarked images (``rows`` of :data:`NULL_IMAGES`, each decoded once; those with nothing
    to read counted apart), their matches' histogram, mean and maximum, and the empirical false-positive rate at
    ``threshold`` with its 95 % upper bound. Other keys' checks of marked images are not null images: see
    :func:`other_keys`."""
    m = [int(r["matches"]) for r in rows if not read_nothing(r)]
    if not m:
        return None
    passing = int(sum(v >= threshold for v in m))
    return {
        "histogram": match_histogram(m, num_bits),
        "images": len(m),
        "nothing_read": sum(map(read_nothing, rows)),
        "matches_mean": sum(m) / len(m),
        "matches_max": max(m),
        "passing": passing,
        "fpr": passing / len(m),
        "fpr_upper_95": metrics.clopper_pearson_upper(passing, len(m)),
    }


def drawn(rows: List[Dict[str, Any]]) -> str:
    """The strengths drawn per view for a row's ``~`` attack (each image's recorded ``attack``), in view order."""
    values = []
    for r in sorted(rows, key=lambda r: r["view"]):
        for part in str(r.get("attack", "")).split(","):
            name, _, value = part.partition("=")
            with contextlib.suppress(ValueError):
                values.append(f"{name} {float(value):+.3g}")
    return ", ".join(values)


def row_key(row: str) -> str:
    """A row's images and attack (``IMAGES:ATTACK``): rows that differ in their ``@N`` share decoded images."""
    return row.partition("@")[0]


def row_count(cfg: PageConfig, row: str) -> int:
    """Images a row asks for: ``@N`` (default ``--num-views``), at most ``--num-views`` for rows at the held-out
    cameras; random images need no camera (as many as asked)."""
    count = row.partition("@")[2]
    n = int(count) if count else cfg.num_views
    return n if row.startswith("random") else min(n, cfg.num_views)


def wanted(cfg: PageConfig) -> Dict[str, int]:
    """Images per row key (:func:`row_count`), in the order of ``--rows`` (the largest of rows sharing a key), random
    images last."""
    out: Dict[str, int] = {}
    for row in cfg.rows:
        out[row_key(row)] = max(out.get(row_key(row), 0), row_count(cfg, row))
    if cfg.random_images > 0:
        out["random:"] = max(out.get("random:", 0), cfg.random_images)
    return out


def not_reached(cfg: PageConfig, done: Dict[Any, Dict[str, Any]]) -> Dict[str, int]:
    """Images each row asks for that have not been decoded (``--page-only`` pages)."""
    out = {}
    for key, want in wanted(cfg).items():
        have = sum(1 for k, v in done if k == key and v < want)
        if have < want:
            out[key] = want - have
    return out


def file_sha256(path: Path) -> Optional[str]:
    """The sha256 of a file's bytes (the owner key a page was decoded with names the model); None without the file."""
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None


def recorded_page(page_json: Path) -> Dict[str, Any]:
    """What a page's JSON recorded (its PSNR, machine and date: a page rewritten from its rows keeps them); empty
    without one."""
    return json.loads(page_json.read_text()) if page_json.exists() else {}


def write_page(
    cfg: PageConfig, num_bits: int, done: Dict[Any, Dict[str, Any]], threshold: int, psnr: Dict[str, float]
) -> Dict[str, Any]:
    """The page and its JSON from the images decoded (``done``); ``psnr``: marked vs clean, mean and min (dB)."""
    want = wanted(cfg)
    table = {
        row: summarize([r for (k, v), r in done.items() if k == row and v < n], threshold, num_bits, is_null_row(row))
        for row, n in want.items()
        if any(k == row and v < n for k, v in done)
    }
    kept = [(k, r) for (k, v), r in done.items() if v < want.get(k, 0)]
    others = other_keys([r for (k, _), r in done.items() if k.startswith("marked:")], cfg.other_keys, threshold)
    null = null_summary([r for k, r in kept if is_null_row(k)], threshold, num_bits)
    recorded = recorded_page(cfg.output.with_suffix(".json"))
    old = recorded if cfg.page_only else {}
    res = {
        "other_keys": others,
        "null": null,
        "command": "python -m gsticker_plugin.bench.unposed " + " ".join(a for a in sys.argv[1:] if a != "--page-only"),
        "not_reached": not_reached(cfg, done),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_info(),
        **({"machine": old["machine"], "decoded": old.get("decoded", old["date"])} if old else {}),
        "key_sha256": old.get("key_sha256") if old else file_sha256(cfg.key),
        "threshold": threshold,
        "psnr_marked_vs_clean_db": {"mean": psnr["mean"], "min": psnr["min"]},
        "rows": table,
        "per_image": list(done.values()),
    }
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    js = cfg.output.with_suffix(".json")
    js.write_text(json.dumps(res, indent=1))
    lines = [
        "# Images alone: the informed image decoder finds each image's camera",
        "",
        (
            f"Command (images decoded on {res['machine'].get('cpu', '')}, first page {res['decoded']}; this page "
            f"rewritten from their rows on {res['date']} with `--page-only`: the columns say which route each image "
            "was read through then, the text below describes the decoder as it is now; every number here is in "
            f"[{js.name}]({js.name})):"
            if "decoded" in res
            else f"Command ({res['date']}, {res['machine'].get('cpu', '')}; every number here is in [{js.name}]({js.name}), written by it):"
        ),
        "",
        "```bash",
        res["command"],
        "```",
        "",
        f"{cfg.num_views} orbit cameras drawn with seed {cfg.camera_seed} (held out: the sticker never trained or "
        "calibrated on them), the watermarked run rendered there with its sticker on (*marked*) and off (*clean*: "
        f"the owner's base), 8-bit; PSNR marked vs clean {psnr['mean']:.2f} dB mean, {psnr['min']:.2f} dB "
        "worst view. Every image is decoded **without its camera**: a search over candidate poses against the owner's "
        "base, Gauss-Newton on the pixels (on V; again on RGB with the base rendered through a colour map of its "
        f"samples when that map explains at least {MAP_SEARCH_SHARE:.0%} of the image's difference from the base "
        "render: a recoloured copy), then the image fit with the pose Jacobian beside the message (through a blur or a "
        "JPEG of the base render when one explains the image far better; again without a rectangle the fitted mark is "
        "missing from, when one stands far above the noise: a cropout pasted from an unmarked render) "
        f"([verify-notes.md](verify-notes.md)). A view passes at >= {threshold}/48 (per-view false-positive rate 1e-6)."
        + (f" Owner key sha256 `{res['key_sha256'][:16]}`." if res.get("key_sha256") else ""),
        "",
        "| images | attack | decoded | bit accuracy | matches mean (min-max) | passing | read by V / colour map / camera searched through map / through a blur / as a turned render / through a JPEG / around a covered rectangle | camera error median / max (deg) | s per image (wall) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row, t in table.items():
        which, _, spec = row.partition(":")
        spec = spec.partition("@")[0]
        cam = (
            f"{t['rotation_error_deg_median']:.4f} / {t['rotation_error_deg_max']:.3f}"
            if "rotation_error_deg_median" in t
            else "-"
        )
        if "~" in spec:
            spec += f" (drawn per view: {drawn([r for (k, v), r in done.items() if k == row and v < want[row]])})"
        if "crop" in spec:  # rows decoded before crop_fill was recorded painted a white rectangle
            fills = sorted({r.get("crop_fill") or "white" for (k, _), r in done.items() if k == row})
            spec += f" ({' / '.join(fills)})"
        lines.append(
            f"| {which} | {spec or 'none'} | {t['images']} | {100 * t['bit_acc']:.2f} % | {t['matches_mean']:.1f} "
            f"({t['matches_min']}-{t['matches_max']}){unread(t)} | {t['passing']}/{t['images']} | {t['read_by_value']} / "
            f"{t['read_through_map']} / {t['searched_through_map']} / {t['read_through_blur']} / {t.get('read_as_turned', 0)} / {t.get('read_through_jpeg', 0)} / {t.get('read_around_cover', 0)} | {cam} | "
            f"{t['seconds_per_image']:.0f} |"
        )
    if others is not None:
        lines.append(
            f"| marked, checked with {others['keys']} other keys (one image each) | none | {others['checks']} checks | - | "
            f"{others['matches_mean']:.1f} (max {others['matches_max']}; every image with every key: max "
            f"{others.get('matches_max_pairs', others['matches_max'])}) | {others['passing']}/{others['checks']} | - | - "
            "| - |"
        )
    development = [
        row for row, n in want.items() if row in table and cfg.development_views and n <= cfg.development_views
    ]
    if development:
        held = [row for row in table if row not in development]
        which = (
            "every row but " + ", ".join(f"`{row}`" for row in held)
            if held and len(held) < len(development)
            else "the rows " + ", ".join(f"`{row}`" for row in development)
        )
        lines += [
            "",
            f"Views 0-{cfg.development_views - 1} of these cameras were looked at while the decoder's rules or the "
            f"sticker's recipe were chosen; {which} read only those views: development evidence, not held out.",
        ]
    if others is not None:
        lines += [
            "",
            f"*Other keys*: the marked images' decoded bits checked against {others['keys']} other random messages "
            "(one image each, the images in turn). It checks the messages' randomness, not the decoder on an unmarked "
            "input, so it is its own row and not part of the null.",
        ]
    if null is not None:
        lines += [
            "",
            f"**The null: {null['images']} distinct unmarked images, each decoded once**"
            + (
                f" ({null['nothing_read']} more with nothing to read, left out: every bit undetermined, no ray the gate "
                "reads at the camera found)"
                if null.get("nothing_read")
                else ""
            )
            + f": matches mean {null['matches_mean']:.1f}, max {null['matches_max']}; {null['passing']} pass at >= "
            f"{threshold}/48: empirical false-positive rate {null['fpr']:.4f}, 95 % upper bound "
            f"{null['fpr_upper_95']:.4f} (Clopper-Pearson).",
        ]
        chart = cfg.output.with_name(cfg.output.stem + "-null.png")
        null_chart(
            null,
            [r["matches"] for k, r in kept if not is_null_row(k) and not is_removal_row(k)],
            [r["matches"] for k, r in kept if is_removal_row(k)],
            chart,
            num_bits,
            threshold,
        )
        lines += ["", f"![matches of the null beside the marked images]({chart.name})"]
    if res["not_reached"]:
        lines += [
            "",
            "Not decoded in this run (the page was written from the images done, `--page-only`): "
            + ", ".join(f"`{row}` {n} images" for row, n in res["not_reached"].items())
            + ".",
            "",
        ]
    threat = threat_curves(cfg, table, threshold, num_bits, recorded.get("threat", []))
    if threat:
        res["threat"] = threat
        js.write_text(json.dumps(res, indent=1))
        lines += threat_lines(threat, cfg.output, cfg.purify_lr, cfg.purify_rays_per_step)
    lines += [
        "",
        "*clean*, *foreign*, *scene* (another scene) and *random* images do not carry the owner's message: the null. "
        "Decoded the same way, their matches follow Binomial(48, 1/2) when the decoder is honest (mean 24).",
    ]
    cfg.output.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


def threat_curves(
    cfg: PageConfig, table, threshold: int, num_bits: int, recorded: Sequence[Dict[str, Any]] = ()
) -> List[Dict[str, Any]]:
    """Bit accuracy against PSNR (vs the shared marked renders) of the ``purify=``, ``leak=`` and ``pgd=`` rows
    (images alone, and an informed decoder beside them); a PNG chart beside the page. A row whose record is not in
    the work dir (one restored from a page's per-image rows) keeps its point from ``recorded`` (the page's JSON)."""
    paths = {attack: cfg.work_dir / f"{attack}.json" for attack in ("purify", "leak", "pgd")}
    records = {attack: json.loads(path.read_text()) if path.exists() else {} for attack, path in paths.items()}
    out = []

    def point(attack: str, strength: float, p: Dict[str, Any], t: Dict[str, Any], **informed) -> Dict[str, Any]:
        read: Dict[str, Any] = {
            "geometric_bit_acc": None,
            "geometric_passing": None,
            "posed_bit_acc": None,
            "posed_passing": None,
        }
        for decoder, matches in informed.items():  # an informed decoder's matches per view beside the images alone
            m = torch.tensor(matches)
            read[f"{decoder}_bit_acc"] = p[f"{decoder}_bit_acc"]
            read[f"{decoder}_passing"] = f"{int((m >= threshold).sum())}/{len(m)}"
        return {
            "attack": attack,
            "strength": strength,
            "psnr_vs_marked_db": p["psnr_vs_marked_db"],
            "psnr_vs_clean_db": p["psnr_vs_clean_db"],
            "images_bit_acc": t["bit_acc"],
            "images_passing": f"{t['passing']}/{t['images']}",
            **read,
            "purify_seconds": p.get("purify_seconds"),
        }

    on_page = {(r["attack"], float(r["strength"])): r for r in recorded}
    for row, t in table.items():
        attack, _, value = row.partition(":")[0].partition("=")
        if attack not in records:
            continue
        p = records[attack].get(value if attack == "purify" else str(float(value)))
        if p is None:
            if (attack, float(value)) in on_page:
                read = {"images_bit_acc": t["bit_acc"], "images_passing": f"{t['passing']}/{t['images']}"}
                out.append({**on_page[(attack, float(value))], **read})
        elif attack == "purify":
            out.append(point("purify", p["steps"], p, t, geometric=p["geometric_matches"]))
        elif attack == "leak":
            out.append(point("leak", float(value), p, t))
        else:
            out.append(point("pgd", float(value), p, t, posed=p["posed_matches"]))
    if out:
        threat_chart(out, cfg.output.with_suffix(".png"), num_bits, threshold)
    return out


def threat_chart(points: List[Dict[str, Any]], path: Path, num_bits: int, threshold: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    series = [
        ("purify", "images_bit_acc", "purification: images alone", "o-"),
        ("purify", "geometric_bit_acc", "purification: informed geometric", "s--"),
        ("leak", "images_bit_acc", "blend toward the owner's base: images alone", "^-"),
        ("pgd", "images_bit_acc", "leaked-key PGD: images alone", "v-"),
        ("pgd", "posed_bit_acc", "leaked-key PGD: informed image decoder, true cameras", "d--"),
    ]
    for attack, field, label, style in series:
        pts = sorted(
            (p["psnr_vs_marked_db"], p[field]) for p in points if p["attack"] == attack and p[field] is not None
        )
        if pts:
            ax.plot([x for x, _ in pts], [100 * y for _, y in pts], style, label=label)
    ax.axhline(100 * threshold / num_bits, color="gray", lw=0.8, ls=":", label=f"pass line ({threshold}/{num_bits})")
    ax.axhline(50, color="gray", lw=0.8)
    ax.set_xlabel("PSNR of the attacked renders vs the shared marked renders (dB)")
    ax.set_ylabel("bit accuracy (%)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def threat_lines(
    points: List[Dict[str, Any]], output: Path, purify_lr: float = 1e-3, purify_rays: int = 1024
) -> List[str]:
    lines = [
        "",
        "## Threat model: the recipient removes the mark",
        "",
        f"![bit accuracy against PSNR]({output.with_suffix('.png').name})",
        "",
        "*purify*: every parameter of the shared watermarked run fine-tuned on the clean training images (Adam, "
        f"learning rate {purify_lr:g}, {purify_rays} rays per step: the evaluation's purify stage), cumulative steps; the same model read by the informed geometric decoder at the "
        "base run's cameras beside the images-alone decoder at the held-out views. *leak*: the marked renders blended "
        "toward the owner's base renders by the share (what a holder of the base, i.e. of the owner key, can do; "
        "without the key the recipient has no unmarked render to blend toward). *pgd*: each marked render attacked by "
        "projected gradient descent on the informed image decoder at its true camera within a PSNR budget (dB), the "
        "leaked-key attack (`evaluation.leaked_key.leaked_key_attack`), read without the camera and, beside it, by the "
        "informed image decoder given the true camera. PSNR is against the shared marked renders at the held-out "
        "views.",
        "",
        "| attack | steps / share / budget | PSNR vs marked (dB) | PSNR vs clean (dB) | images alone: bit acc, passing | informed geometric: bit acc, passing | informed image, true cameras: bit acc, passing | purify s |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def reading(p: Dict[str, Any], decoder: str) -> str:
        acc = p.get(f"{decoder}_bit_acc")
        return "-" if acc is None else f"{100 * acc:.1f} %, {p[f'{decoder}_passing']}"

    for p in points:
        lines.append(
            f"| {p['attack']} | {p['strength']} | {p['psnr_vs_marked_db']:.2f} | {p['psnr_vs_clean_db']:.2f} | "
            f"{reading(p, 'images')} | {reading(p, 'geometric')} | {reading(p, 'posed')} | "
            f"{'-' if p['purify_seconds'] is None else p['purify_seconds']} |"
        )
    return lines + [""] + breaking_points(points)


def breaking_points(points: List[Dict[str, Any]]) -> List[str]:
    """One line per attack and decoder: the strongest setting at which every image still passes and the weakest at
    which one fails (settings in increasing strength), with their PSNR against the marked renders."""

    def fraction(passing: str) -> float:
        k, n = passing.split("/")
        return int(k) / max(1, int(n))

    def setting(p: Dict[str, Any]) -> str:
        if p["attack"] == "purify":
            return f"{p['strength']} step" + ("" if p["strength"] == 1 else "s")
        if p["attack"] == "pgd":
            return f"a {p['strength']:g} dB budget"
        return f"{p['strength']} blended" if p["attack"] == "leak" else str(p["strength"])

    def strength(p: Dict[str, Any]) -> float:  # a smaller PSNR budget is the stronger attack
        return -p["strength"] if p["attack"] == "pgd" else p["strength"]

    lines = []
    decoders = (
        ("images", "images alone"),
        ("geometric", "informed geometric"),
        ("posed", "informed image, true cameras"),
    )
    for attack in dict.fromkeys(p["attack"] for p in points):
        rows = sorted((p for p in points if p["attack"] == attack), key=strength)
        for decoder, name in decoders:
            read = [(p, fraction(p[f"{decoder}_passing"])) for p in rows if p.get(f"{decoder}_passing") is not None]
            if not read:
                continue
            broke = next((p for p, f in read if f < 1.0), None)
            held = [p for p, f in read if broke is None or strength(p) < strength(broke)]
            text = f"- {attack}, {name}: " + (
                f"every image passes up to {setting(held[-1])} ({held[-1]['psnr_vs_marked_db']:.1f} dB vs marked)"
                if held
                else "the weakest setting tried already breaks it"
            )
            if broke is None:
                text += "; no setting tried breaks it"
            else:
                text += (
                    f"; breaks at {setting(broke)} ({broke['psnr_vs_marked_db']:.1f} dB vs marked, "
                    f"{100 * broke[f'{decoder}_bit_acc']:.1f} % of bits)"
                )
            lines.append(text + ".")
    return lines
