"""Extractor decoding (the blind decoder): the owner key's CNN reads each view's RGB; no base, no camera."""

from __future__ import annotations

from typing import Dict

import torch
from torch import Tensor

from gsticker_plugin import metrics
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.views import Views


@torch.no_grad()
def decode_views(key: OwnerKey, views: Views, device: torch.device) -> Dict[str, Tensor]:
    """Per view: extractor logits -> bits, matches with the key's message, and the classifier's score."""
    heads = key.build_heads().to(device)
    logits, scores = [], []
    for v in views.views:
        img = v.image[None].to(device).float()
        logits.append(heads.decode(img).float().cpu()[0])
        scores.append(torch.sigmoid(heads.classify(img).float()).cpu().reshape(-1)[0])
    lg = torch.stack(logits)
    bits = metrics.decode_bits(lg)
    m = metrics.count_matches(bits, key.message)
    return {"bits": bits, "matches": m, "bit_acc": metrics.bit_accuracy(bits, key.message),
            "pvalues": metrics.binomial_tail_pvalues(m, key.num_bits), "scores": torch.stack(scores)}
