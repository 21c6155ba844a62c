"""Extractor decoding (the blind decoder): the owner key's CNN reads each view's RGB; no base, no camera."""

from __future__ import annotations

import torch

from gsticker_plugin import metrics
from gsticker_plugin.decoders.result import Decoded, decoded
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.views import Views


@torch.no_grad()
def decode_views(key: OwnerKey, views: Views, device: torch.device) -> Decoded:
    """Per view: extractor logits -> bits, matches with the key's message, the classifier's score and the soft
    correlation score's p-value (``blind`` diagnostics; ``soft_pvalue_pooled`` over all views)."""
    heads = key.build_heads().to(device)
    logits, scores = [], []
    for v in views.views:
        img = v.image[None].to(device).float()
        logits.append(heads.decode(img).float().cpu()[0])
        scores.append(torch.sigmoid(heads.classify(img).float()).cpu().reshape(-1)[0])
    z = torch.stack(logits)
    details = [{"soft_pvalue": metrics.soft_score_pvalue(zi, key.message)} for zi in z]
    out = decoded(key, list(metrics.decode_bits(z)), "blind", details, scores=torch.stack(scores))
    out["soft_pvalue_pooled"] = metrics.soft_score_pvalue(z, key.message)
    return out
