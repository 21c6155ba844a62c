"""Per-key statistics of decoded views: thresholds from the binomial (and measured) null, the view vote, the verdict."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Dict, List, Optional

from gsticker_plugin import metrics
from gsticker_plugin.decoders.result import Decoded
from gsticker_plugin.key import OwnerKey, bits_to_str
from gsticker_plugin.verify.results import KeyResult, MultipleTesting, NullSummary, Thresholds, ViewResult
from gsticker_plugin.views import Views

NULL_FORMAT_VERSION = 1


def decoder_null(key: OwnerKey, decoder: str) -> Optional[Dict[str, Any]]:
    """The empirical null stored for ``decoder``: the extractor's in ``key.null``, the geometric decoder's in
    ``key.geometry["null"]``, the image decoder's in ``key.geometry["image_null"]`` (each decoder is only ever
    compared with its own null)."""
    if decoder == "geometry":
        return (key.geometry or {}).get("null")
    if decoder == "image":
        return (key.geometry or {}).get("image_null")
    return key.null


def null_summary(key: OwnerKey, fpr: float, decoder: str = "extractor") -> Optional[NullSummary]:
    """The key's stored empirical null for ``decoder``, and the per-view threshold it implies at ``fpr``."""
    null = decoder_null(key, decoder)
    if not null or not null.get("matches"):
        return None
    m = [int(x) for x in null["matches"]]
    k = key.num_bits
    m_emp = metrics.empirical_threshold(m, fpr, k)
    n = len(m)
    mean = sum(m) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in m) / max(1, n - 1))
    return {
        "n": n,
        "mean_matches": mean,
        "sd_matches": sd,
        "max_matches": max(m),
        "chance_mean": k / 2,
        "chance_sd": math.sqrt(k) / 2,
        "threshold": m_emp,
        "sources": null.get("sources", []),
        "created": null.get("created"),
        "meaning": (
            f"smallest match count reached by at most a share {fpr:g} of the {n} unmarked null views; "
            f"with fpr < 1/n it is one more than the largest null count ({max(m)}); on its own it "
            f"certifies a per-view FPR of no less than ~{metrics.clopper_pearson_upper(0, n):.2g} "
            "(95 % upper bound, rule of three), so it only makes the binomial threshold stricter"
        ),
    }


def key_result(
    key: OwnerKey,
    key_path: Path,
    dec: Decoded,
    views: Views,
    fpr: float,
    min_share: float,
    decoder: str = "extractor",
) -> KeyResult:
    """One key's result on the decoded views: the per-view threshold (the stricter of the binomial and the key's
    measured null), each view's pass, the view vote and the verdict."""
    k = key.num_bits
    m_theo = metrics.min_matches_for_fpr(k, fpr)
    emp = null_summary(key, fpr, decoder)
    m_emp = emp["threshold"] if emp else None
    m_star = max(m_theo, m_emp) if m_emp is not None else m_theo
    matches = dec["matches"]
    passed = (matches >= m_star).tolist()
    vote = metrics.combine_view_decisions(passed, min_share)
    n = len(passed)
    needed = metrics.views_needed(n, min_share)
    p_model = metrics.vote_pvalue(matches, k, min_share)
    t_stat = metrics.vote_statistic(matches, min_share)
    per_view_fpr_used = metrics.binomial_tail_pvalue(m_star, k)
    if emp is not None:
        exceed = sum(1 for x in (decoder_null(key, decoder) or {})["matches"] if int(x) >= m_star)
        emp["exceed_at_used_threshold"] = exceed
        emp["exceed_upper95_at_used_threshold"] = metrics.clopper_pearson_upper(exceed, emp["n"])
    scores = dec.get("scores")
    geo = dec.get("geometry")
    img_fit = dec.get("image")
    per_view: List[ViewResult] = []
    for i, v in enumerate(views.views):
        vr: ViewResult = {
            "name": v.name,
            "matches": int(matches[i]),
            "num_bits": k,
            "bit_accuracy": float(dec["bit_acc"][i]),
            "pvalue": float(dec["pvalues"][i]),
            "score": float(scores[i]) if scores is not None else None,
            "passed": bool(passed[i]),
            "decoded": bits_to_str(dec["bits"][i]),
        }
        if v.note:
            vr["note"] = v.note
        if geo is not None:
            vr["geometry"] = geo[i]
        if img_fit is not None:
            vr["image_fit"] = img_fit[i]
        per_view.append(vr)
    mlist = sorted(int(x) for x in matches.tolist())
    thresholds: Thresholds = {
        "theoretical": m_theo,
        "empirical": m_emp,
        "used": m_star,
        "per_view_fpr_target": fpr,
        "per_view_fpr_at_used": per_view_fpr_used,
    }
    result: KeyResult = {
        "key": str(key_path),
        "owner_id": key.owner_id or Path(key_path).stem,
        "num_bits": k,
        "verdict": "owned" if vote.passed else "not shown",
        "owned": bool(vote.passed),
        "thresholds": thresholds,
        "views": n,
        "views_passing": int(sum(passed)),
        "share_passing": vote.share,
        "views_needed": needed,
        "min_share": min_share,
        "model_fpr_bound": metrics.combined_fpr_bound(per_view_fpr_used, min_share),
        "model_pvalue": p_model,
        "vote_statistic": t_stat,
        "matches_min": mlist[0],
        "matches_median": mlist[n // 2],
        "matches_max": mlist[-1],
        "mean_bit_accuracy": float(dec["bit_acc"].float().mean()),
        "mean_score": float(scores.float().mean()) if scores is not None else None,
        "decoder": decoder,
        "mark": "field" if key.field_mark else "sticker",
        "null_exact": not key.null_caveats(),
        "null_caveats": key.null_caveats(),
        "message_source": key.message_source,
        "empirical_null": emp,
        "per_view": per_view,
    }
    if decoder in ("geometry", "image") and emp is None and key.null:
        result["null_note"] = (
            f"the key's empirical null was measured with the extractor and does not apply to the "
            f"{'geometric' if decoder == 'geometry' else 'image'} decoder; run `ns-verify-owner "
            f"calibrate --decode {decoder}` to measure its own"
        )
    return result


def correct_keys(results: List[KeyResult], fpr: float, min_share: float, correction: str) -> MultipleTesting:
    """Several keys: correct the model-level p-values and re-decide each key at the family-wise level."""
    alpha = metrics.combined_fpr_bound(fpr, min_share)
    pv = [r["model_pvalue"] for r in results]
    adj = metrics.holm(pv) if correction == "holm" else metrics.bonferroni(pv)
    for r, a in zip(results, adj):
        emp = r["thresholds"]["empirical"]
        r["adjusted_pvalue"] = float(a)
        r["owned"] = bool(a <= alpha and (emp is None or r["vote_statistic"] >= emp))
        r["verdict"] = "owned" if r["owned"] else "not shown"
    return {
        "keys": len(results),
        "correction": correction,
        "family_wise_fpr": alpha,
        "rule": (
            "a key is 'owned' when its corrected model-level p-value is <= fpr / min-share and its vote "
            "statistic also reaches the key's empirical threshold"
        ),
    }
