"""The verification report: the text summary printed first, ``report.json`` and the ``report.png`` figure."""

from __future__ import annotations

import json
import math
import os
import statistics
from pathlib import Path
from typing import Any, Optional

import torch

from gsticker_plugin import metrics
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.verify.results import KeyResult, Report
from gsticker_plugin.verify.stats import decoder_null
from gsticker_plugin.views import Views

DECODER_NAMES = {"extractor": "extractor", "geometry": "geometric decoder", "image": "image decoder"}


THUMB_SIDE = 128  # side of the view thumbnails kept for the figure


def _fmt_p(p: float) -> str:
    return f"{p:.2g}" if p >= 1e-3 or p == 0 else f"{p:.1e}"


def nothing_read(key_report: KeyResult) -> int:
    """Images of a key's result whose every bit the informed image decoder left undetermined (its fit read no ray)."""
    return sum(
        (v.get("image_fit") or {}).get("undetermined", 0) >= key_report["num_bits"] for v in key_report["per_view"]
    )


def timing_line(key_report: KeyResult) -> str:
    """Seconds of the image decoder's stages, when it found the cameras ('' otherwise): the view bank apart, then the
    median per image of the camera search and of the whole decode."""
    fits = [v.get("image_fit") or {} for v in key_report["per_view"]]
    searched = [f["search_seconds"] for f in fits if "search_seconds" in f]
    if not searched:
        return ""
    bank = sum(f.get("view_bank_seconds", 0.0) for f in fits)
    whole = statistics.median(f.get("seconds", 0.0) for f in fits)
    return (
        f"    seconds: view bank {bank:.1f} (once), then per image median {whole:.1f} of which the camera search "
        f"{statistics.median(searched):.1f}"
    )


def summary_text(report: Report) -> str:
    """The text summary printed before anything else: the verdict, the input, the decoder and each key's result."""
    lines = []
    owners = report["owned_by"]
    if report["verdict"] == "owned":
        lines.append(f"VERDICT: OWNED by {', '.join(owners)}")
    else:
        lines.append("VERDICT: NOT SHOWN (no key's message is shown at the chosen false-positive rate)")
    inp = report["input"]
    desc = f"{inp['kind']} {inp['source']}: {inp['views']} views"
    if inp["kind"] == "model":
        d = inp.get("details", {})
        desc += (
            f" ({d.get('own_cameras', 0)} run cameras, {d.get('sampled_poses', 0)} sampled poses; {d.get('method')})"
        )
    if inp["skipped"]:
        desc += f"; {len(inp['skipped'])} skipped (listed in report.json)"
    lines.append("  input: " + desc)
    dec = report.get("decoder") or {}
    if dec:
        lines.append(f"  decoder: {dec['kind']} ({dec['description']})")
        for note in dec.get("notes", []):
            lines.append(f"    note: {note}")
    if report["settings"]["attack"] and dec.get("kind") != "geometry":
        lines.append(f"  attack before decoding: {report['settings']['attack']}")
    for r in report["keys"]:
        t = r["thresholds"]
        calib = "ns-verify-owner calibrate" + (
            f" --decode {r['decoder']}" if r.get("decoder", "extractor") != "extractor" else ""
        )
        emp = (
            f"empirical {t['empirical']} from {r['empirical_null']['n']} null views"
            if r["empirical_null"]
            else "the fit never reads the message, so with a random secret message the null is this binomial"
            if r.get("mark") == "field"
            else f"no empirical null for this decoder (run {calib})"
        )
        lines.append(f"  key {r['owner_id']} ({r['key']}): {r['verdict'].upper()}")
        for c in r.get("null_caveats", []):
            lines.append(f"    weaker claim: {c}")
        lines.append(
            f"    {r['views_passing']}/{r['views']} views pass ({100 * r['share_passing']:.0f} %; needs "
            f"{r['views_needed']} = {100 * r['min_share']:.0f} %) at >= {t['used']}/{r['num_bits']} matches "
            f"(theoretical {t['theoretical']} at per-view FPR {t['per_view_fpr_target']:g}; {emp})"
        )
        unread = nothing_read(r)
        if unread:
            lines.append(
                f"    {unread} view(s) with nothing to read: every bit undetermined (no ray the gate reads in that "
                "view; an image at a camera found away from the owner's scene), counted as 0 matches"
            )
        best = max(r["per_view"], key=lambda v: v["matches"])
        lines.append(
            f"    matches min/median/max {r['matches_min']}/{r['matches_median']}/{r['matches_max']} of "
            f"{r['num_bits']} (best view {best['name']}: p = {_fmt_p(best['pvalue'])}); mean bit accuracy "
            f"{r['mean_bit_accuracy']:.3f}; "
            + (
                f"classifier score {r['mean_score']:.2f}"
                if r["mean_score"] is not None
                else f"classifier not used ({DECODER_NAMES[r.get('decoder', 'geometry')]})"
            )
        )
        timing = timing_line(r)
        if timing:
            lines.append(timing)
        if r.get("soft_score_pvalue") is not None:
            lines.append(
                f"    soft correlation score over all views: p <= {_fmt_p(r['soft_score_pvalue'])} (Hoeffding over the "
                "random message; a diagnostic, not the verdict)"
            )
        line = (
            f"    model-level p-value {_fmt_p(r['model_pvalue'])}; FPR of this verdict <= "
            f"{r['model_fpr_bound']:.2g} under any dependence between views"
        )
        mt = report.get("multiple_testing")
        if "adjusted_pvalue" in r and mt is not None:
            line += f"; {mt['correction']}-adjusted p {_fmt_p(r['adjusted_pvalue'])}"
        lines.append(line)
    committed = report.get("commitment")
    if committed:
        if "given" in committed:
            lines.append(
                f"  commitment {committed['given'][:16]}... matches the key: it existed when this commitment was "
                "published"
            )
        if "public_key" in committed:
            lines.append(
                f"  signed by the public key {committed['public_key'][:16]}...: its identity's holder made this key"
            )
    mt = report.get("multiple_testing")
    if mt:
        lines.append(
            f"  {mt['keys']} keys tested, {mt['correction']} correction; family-wise FPR <= {mt['family_wise_fpr']:.2g}"
        )
    for f in report.get("files", []):
        lines.append(f"  wrote {f}")
    return "\n".join(lines)


def write_figure(path: Path, report: Report, views: Views, key: Optional[OwnerKey]) -> None:
    # deferred: only charts need it, slow to import
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = min(report["keys"], key=lambda x: x["model_pvalue"])  # the most significant key
    k = r["num_bits"]
    n_thumbs = min(4, len(views.views))
    fig = plt.figure(figsize=(12, 7.5))
    gs = fig.add_gridspec(2, max(1, n_thumbs), height_ratios=[1.25, 1.0])
    ax = fig.add_subplot(gs[0, :])
    xs = list(range(k + 1))
    matches = [v["matches"] for v in r["per_view"]]
    ax.hist(
        matches,
        bins=[x - 0.5 for x in range(k + 2)],
        density=True,
        color="tab:blue",
        alpha=0.7,
        label=f"suspect views (n={len(matches)})",
    )
    pmf = [
        math.exp(metrics.log_binomial_tail_pvalue(x, k)) - math.exp(metrics.log_binomial_tail_pvalue(x + 1, k))
        for x in xs
    ]
    ax.plot(xs, pmf, "k-", lw=1.5, label=f"theoretical null Binomial({k}, 1/2)")
    if r["empirical_null"] and key is not None and decoder_null(key, r.get("decoder", "extractor")):
        nm = [int(x) for x in decoder_null(key, r.get("decoder", "extractor"))["matches"]]
        ax.hist(
            nm,
            bins=[x - 0.5 for x in range(k + 2)],
            density=True,
            histtype="step",
            color="tab:orange",
            lw=2,
            label=f"empirical null (n={len(nm)})",
        )
    t = r["thresholds"]
    ax.axvline(t["theoretical"] - 0.5, color="tab:red", ls="--", label=f"theoretical threshold {t['theoretical']}")
    if t["empirical"] is not None:
        ax.axvline(t["empirical"] - 0.5, color="tab:orange", ls=":", label=f"empirical threshold {t['empirical']}")
    ax.set_xlim(-0.5, k + 0.5)
    ax.set_xlabel(f"matching bits (of {k})")
    ax.set_ylabel("share of views")
    ax.set_title(
        f"{report['verdict'].upper()} - key {r['owner_id']}: {r['views_passing']}/{r['views']} views pass "
        f">= {t['used']}/{k}; model p = {_fmt_p(r['model_pvalue'])}"
    )
    ax.legend(fontsize=8, loc="upper left")
    order = sorted(range(len(views.views)), key=lambda i: -r["per_view"][i]["matches"])
    picks = order[:n_thumbs]
    for j, i in enumerate(picks):
        a = fig.add_subplot(gs[1, j])
        img = views.views[i].image
        s = THUMB_SIDE / max(img.shape[-2:])
        if s < 1:
            img = torch.nn.functional.interpolate(img[None], scale_factor=s, mode="area")[0]
        a.imshow(img.permute(1, 2, 0).clamp(0, 1).numpy())
        v = r["per_view"][i]
        score = f"score={v['score']:.2f}" if v["score"] is not None else r.get("decoder", "geometry")
        a.set_title(
            f"{v['name'][-24:]}\n{v['matches']}/{k}  p={_fmt_p(v['pvalue'])}  {score}\n"
            f"{'PASS' if v['passed'] else 'fail'}",
            fontsize=8,
        )
        a.axis("off")
    fig.tight_layout()
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    os.replace(tmp, path)


def write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, allow_nan=False))
    os.replace(tmp, path)
