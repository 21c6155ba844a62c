"""One decoded result for every decoder: per-view bits, matches with the owner's message, p-values, diagnostics."""

from __future__ import annotations

from typing import Any, Dict, List, Optional, TypedDict

import torch
from torch import Tensor

from gsticker_plugin import metrics


class Decoded(TypedDict, total=False):
    """Per view (first dimension): ``bits`` (-1 undetermined), ``matches`` with the key's message, ``bit_acc``,
    binomial ``pvalues``; ``scores`` the classifier's (None for decoders that read no image); a decoder's
    diagnostics under its own name (``geometry``, ``image``, ``color``, ``blind``); the blind decoder's soft correlation
    score p-value over all views in ``soft_pvalue_pooled``."""

    bits: Tensor
    matches: Tensor
    bit_acc: Tensor
    pvalues: Tensor
    scores: Optional[Tensor]
    geometry: List[Dict[str, Any]]
    image: List[Dict[str, Any]]
    color: List[Dict[str, Any]]
    blind: List[Dict[str, Any]]
    soft_pvalue_pooled: float


def decoded(
    key,
    bits: List[Tensor],
    details_name: Optional[str] = None,
    details: Optional[List[Dict[str, Any]]] = None,
    scores: Optional[Tensor] = None,
) -> Decoded:
    """Per-view bits -> matches, bit accuracy and binomial p-values against the owner's message (every decoder)."""
    b = torch.stack(bits)
    m = metrics.count_matches(b, key.message)
    out: Decoded = {
        "bits": b,
        "matches": m,
        "bit_acc": metrics.bit_accuracy(b, key.message),
        "pvalues": metrics.binomial_tail_pvalues(m, key.num_bits),
        "scores": scores,
    }
    if details_name is not None:
        out[details_name] = details or []  # type: ignore[literal-required]
    return out
