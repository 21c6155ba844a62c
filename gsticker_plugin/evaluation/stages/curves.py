"""Evaluation stage ``curves``."""

from __future__ import annotations

import contextlib
import inspect
import sys
from typing import Any, Dict

import torch
from torch import Tensor

from gsticker_plugin.decoders.image import image_reference
from gsticker_plugin.decoders.reference import any_reference_view, cpu_sticker
from gsticker_plugin.evaluation.config import LEAKED_KEY
from gsticker_plugin.evaluation.leaked_key import leaked_key_attack
from gsticker_plugin.evaluation.workspace import Workspace, describe_spec, over_seeds
from gsticker_plugin.metrics import as_8_bit
from gsticker_plugin.views import progress_bar


def run(ws: Workspace) -> Dict[str, Any]:

    v = ws.views(ws.primary)
    key = ws.key(ws.primary)
    curves = {}
    for name, strengths in ws.p.curves.items():
        pts = []
        for s in progress_bar(strengths, f"curve {name}", ws.progress):
            accs, shares, verdicts, image_per_seed = [], [], [], []
            leaked = leaked_key_attacked(ws, v["watermarked"], float(s)) if name == LEAKED_KEY else None
            for seed in ws.p.seeds:
                x = (
                    leaked
                    if leaked is not None
                    else ws.attacked(v["watermarked"], v["sticker_off"], [(name, float(s))], seed)
                )
                d = ws.decode(key, x)
                accs.append(d["bit_acc"])
                shares.append(d["share_passing"])
                verdicts.append(float(d["verdict"]))
                if ws.reads_images:
                    image_per_seed.append({"seed": seed, **ws.image_decode(x)})
            a = torch.tensor(accs)
            pt = {
                "strength": float(s),
                "bit_acc_mean": float(a.mean()),
                "bit_acc_std": float(a.std(unbiased=False)),
                "bit_acc_per_seed": accs,
                "share_passing_mean": sum(shares) / len(shares),
                "verdict_rate": sum(verdicts) / len(verdicts),
            }
            if image_per_seed:
                pt["image_decoder"] = over_seeds(image_per_seed)
            if leaked is not None:  # the PSNR the attack reached (8-bit image vs the 8-bit watermarked one)
                pt["attack_psnr"] = ws.image_metrics(as_8_bit(leaked), as_8_bit(v["watermarked"]))["psnr"]
            pts.append(pt)
        below = next((p["strength"] for p in pts if p["bit_acc_mean"] < 0.9), None)
        fails = next((p["strength"] for p in pts if p["verdict_rate"] < 0.5), None)
        curves[name] = {
            "points": pts,
            "bit_acc_below_90_at": below,
            "verdict_fails_at": fails,
            "randomized": name in ("noise", "crop"),
            "definition": describe_leaked_key() if name == LEAKED_KEY else describe_spec(f"{name}={strengths[-1]}"),
        }
        if ws.reads_images:
            curves[name]["image_decoder"] = {
                "bit_acc_below_90_at": next((p["strength"] for p in pts if p["image_decoder"]["bit_acc"] < 0.9), None),
                "verdict_fails_at": next(
                    (p["strength"] for p in pts if p["image_decoder"]["verdict_rate"] < 0.5), None
                ),
            }
    return {
        "base": ws.primary,
        "seeds": list(ws.p.seeds),
        "curves": curves,
        "image_decoder": ws.reads_images,
        "note": "seeds change the distortions' randomness only (noise samples, cropout rectangle); rotation, "
        "blur, JPEG, resize and a fixed hue shift are deterministic, so their spread over seeds is 0. "
        "The models are trained once.",
    }


def leaked_key_attacked(ws: Workspace, wm: Tensor, psnr_budget: float) -> Tensor:
    """The primary base's watermarked test views (as 8-bit files) attacked by someone holding its owner key and
    the base: PGD on the informed image decoder at each view's camera, within ``psnr_budget`` dB."""

    ref, cache = ws.geo_reference(ws.primary)
    st = cpu_sticker(ref.model)
    bg = ref.model.background_color()
    out = []
    for (name, cam), image in zip(ws.test_cameras(ws.primary), as_8_bit(wm)):
        with contextlib.redirect_stdout(sys.stderr):
            view = any_reference_view(ref, name, cam, cache)
        out.append(leaked_key_attack(image_reference(view, bg), st, image, psnr_budget))
    return torch.stack(out)


def describe_leaked_key() -> str:

    doc = inspect.getdoc(leaked_key_attack) or ""
    return "leaked_key (strength: PSNR budget in dB): " + " ".join(doc.split("\n\n")[0].split())
