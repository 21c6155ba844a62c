"""Evaluation stage ``quality``."""

from __future__ import annotations

from typing import Any, Dict

from gsticker_plugin import compat
from gsticker_plugin.evaluation.workspace import Workspace


def run(ws: Workspace) -> Dict[str, Any]:
    compat.apply()
    lp = lpips_fn()
    res = {"lpips": "available" if lp is not None else "unavailable (AlexNet weights not in the torch cache; offline)"}
    for b in ws.p.bases:
        v = ws.views(b.name)
        key = ws.key(b.name)
        res[b.name] = {
            "wm_vs_gt": ws.image_metrics(v["watermarked"], v["gt"], lp),
            "unwm_vs_gt": ws.image_metrics(v["sticker_off"], v["gt"], lp),
            "base_vs_gt": ws.image_metrics(v["base"], v["gt"], lp),
            "wm_vs_unwm": ws.image_metrics(v["watermarked"], v["sticker_off"], lp),
            "base_vs_sticker_off": ws.image_metrics(v["base"], v["sticker_off"]),
            "decode_watermarked": ws.decode(key, v["watermarked"]),
            "decode_sticker_off": ws.decode(key, v["sticker_off"]),
        }
    return res


def lpips_fn():
    """LPIPS(a, b) on [B 3 H W] in [0, 1], or None when its AlexNet weights are unavailable (offline)."""
    if not compat.lpips_backbone_available("alex"):
        return None
    # deferred: slow to import, only this metric needs it
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    m = LearnedPerceptualImagePatchSimilarity(net_type="alex", normalize=True)
    if not compat.lpips_is_available(m):
        return None
    return lambda a, b: float(m(a.clamp(0, 1), b.clamp(0, 1)))
