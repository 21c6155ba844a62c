"""The sticker's targets read on every test view: per-view readings summarized against the paper's targets, and
their chart."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional

from gsticker_plugin import metrics

TARGETS = {"bit_acc": 0.995, "psnr_vs_clean_db": 35.0, "psnr_drop_db": 0.3, "train_minutes": 15.0}
PER_VIEW_FPR = 1e-6  # the per-view false-positive rate of the threshold (ns-verify-owner's default --fpr)


def summarize(
    rows: List[Dict[str, Any]], num_bits: int, train: Optional[Dict[str, Any]], split_size: int
) -> Dict[str, Any]:
    """Totals over the decoded views and each target met or not (training time: None when not trained here)."""
    matches = [r["matches"] for r in rows]
    n = len(rows)
    mean = lambda k: sum(r[k] for r in rows) / max(1, n)  # noqa: E731
    thr = metrics.min_matches_for_fpr(num_bits, PER_VIEW_FPR)
    bit_acc = sum(matches) / max(1, n * num_bits)
    drop = mean("psnr_clean_vs_gt_db") - mean("psnr_marked_vs_gt_db")
    change = [r["psnr_marked_vs_gt_db"] - r["psnr_clean_vs_gt_db"] for r in rows]  # per view, watermarked - base
    minutes = train["wall_s"] / 60.0 if train else None
    return {
        "views": n,
        "split_views": split_size,
        "num_bits": num_bits,
        "bit_acc": bit_acc,
        "bits_matched": sum(matches),
        "bits_total": n * num_bits,
        "matches_min": min(matches) if matches else None,
        "views_all_bits": sum(m == num_bits for m in matches),
        "views_below_all_bits": [
            {"index": r["index"], "matches": r["matches"]} for r in rows if r["matches"] < num_bits
        ],
        "views_passing": sum(m >= thr for m in matches),
        "threshold": thr,
        "per_view_fpr": PER_VIEW_FPR,
        "psnr_vs_clean_db": mean("psnr_vs_clean_db"),
        "psnr_vs_clean_min_db": min((r["psnr_vs_clean_db"] for r in rows), default=None),
        "psnr_marked_vs_gt_db": mean("psnr_marked_vs_gt_db"),
        "psnr_clean_vs_gt_db": mean("psnr_clean_vs_gt_db"),
        "psnr_drop_db": drop,
        "psnr_change_per_view_db": {"min": min(change, default=None), "max": max(change, default=None)},
        "decode_s_per_view": mean("decode_s"),
        "train_wall_s": train["wall_s"] if train else None,
        "train_minutes": minutes,
        "targets": {
            "bit_acc >= 99.5 %": bit_acc >= TARGETS["bit_acc"] if n == split_size else None,
            "PSNR vs unwatermarked >= 35 dB": mean("psnr_vs_clean_db") >= TARGETS["psnr_vs_clean_db"],
            "test PSNR within 0.3 dB of the base": drop <= TARGETS["psnr_drop_db"],
            "training <= 15 min": None if minutes is None else minutes <= TARGETS["train_minutes"],
        },
    }


def report(v: Dict[str, Any]) -> str:
    """The targets table and the per-view counts, from :func:`summarize`'s numbers only."""
    fmt = lambda x, f="{:.2f}": "n/a" if x is None else f.format(x)  # noqa: E731
    met = lambda b: "not measured (here / on all views)" if b is None else ("met" if b else "not met")  # noqa: E731
    t, k = v["targets"], v["num_bits"]
    below = ", ".join(f"view {r['index']} {r['matches']}/{k}" for r in v.get("views_below_all_bits", []))
    ch = v.get("psnr_change_per_view_db") or {}
    wall = v.get("train_wall_s")
    lines = [
        f"Test views decoded: {v['views']} of {v['split_views']} ({k} bits, informed geometric decoder)",
        "",
        "| target | measured | |",
        "|---|---|---|",
        f"| {k} bits, bit accuracy >= 99.5 % over all test views | **{100 * v['bit_acc']:.2f} %** "
        f"({v.get('bits_matched', 'n/a')} of {v.get('bits_total', 'n/a')} bits; {v['views_all_bits']} views {k}/{k}"
        f"{'; ' + below if below else ''}) | {met(t['bit_acc >= 99.5 %'])} |",
        f"| PSNR watermarked vs unwatermarked >= 35 dB | **{fmt(v['psnr_vs_clean_db'])} dB** mean, "
        f"{fmt(v['psnr_vs_clean_min_db'])} dB worst view | {met(t['PSNR vs unwatermarked >= 35 dB'])} |",
        f"| test PSNR against ground truth within 0.3 dB of the base | **{fmt(v['psnr_marked_vs_gt_db'], '{:.3f}')} vs "
        f"{fmt(v['psnr_clean_vs_gt_db'], '{:.3f}')} dB** ({fmt(-v['psnr_drop_db'], '{:+.3f}')} dB; per view "
        f"{fmt(ch.get('min'), '{:+.2f}')}..{fmt(ch.get('max'), '{:+.2f}')}) | {met(t['test PSNR within 0.3 dB of the base'])} |",
        f"| training <= 15 min on this CPU | **{fmt(v['train_minutes'], '{:.1f}')} min** ("
        f"{fmt(wall, '{:.0f}')} s wall for `ns-train geometrysticker`: setup, pool rendering and training steps) | "
        f"{met(t['training <= 15 min'])} |",
        "",
        f"Views passing the per-view threshold ({v['threshold']}/{k} at a per-view false-positive rate of "
        f"{v.get('per_view_fpr', PER_VIEW_FPR):g}): {v['views_passing']} of {v['views']}; decoding "
        f"{v['decode_s_per_view']:.1f} s per view.",
    ]
    return "\n".join(lines) + "\n"


def chart(rows: List[Dict[str, Any]], num_bits: int, threshold: int, path: Path) -> Optional[Path]:
    """Per test view: matched bits (with the per-view threshold) and PSNR watermarked vs unwatermarked."""
    if not rows:
        return None
    # deferred: only charts need it, slow to import
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [r["index"] for r in rows]
    fig, (a, b) = plt.subplots(2, 1, figsize=(7, 4.2), sharex=True)
    a.plot(x, [r["matches"] for r in rows], ".", ms=4)
    a.axhline(threshold, color="black", lw=0.8, ls="--")
    a.axhline(num_bits / 2, color="red", lw=0.8, ls=":")
    a.set_ylim(0, num_bits + 1)
    a.set_ylabel(f"matched bits / {num_bits}")
    b.plot(x, [r["psnr_vs_clean_db"] for r in rows], ".", ms=4, color="green")
    b.axhline(TARGETS["psnr_vs_clean_db"], color="black", lw=0.8, ls="--")
    b.set_ylabel("PSNR wm vs clean (dB)")
    b.set_xlabel("test view")
    a.set_title("every test view (dashed: per-view threshold / 35 dB target; dotted: chance)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
