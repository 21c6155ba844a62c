"""Evaluation stage ``sticker``."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Dict, List

from gsticker_plugin.evaluation.workspace import Workspace


def run(ws: Workspace) -> Dict[str, Any]:
    res = {}
    for b in ws.p.bases:
        secs = ws.train_sticker(b.name, b.name)
        res[b.name] = {
            "config": str(ws.wm_dir(b.name) / "config.yml"),
            "key": str(ws.key_path(b.name)),
            "steps": ws.p.sticker.steps,
            "train_seconds": secs,
            "monitor": parse_monitor_log(ws.out / "logs" / f"sticker-{b.name}.log"),
        }
    return res


_MONITOR = re.compile(
    r"step (\d+): held-out bit acc ([\d.]+) \(clean renders: ([\d.]+)\), PSNR marked/clean ([\d.inf-]+) dB, (\d+) s"
)


def parse_monitor_log(log: Path) -> List[Dict[str, float]]:
    """The held-out monitor lines of an ``ns-train geometrysticker`` log."""
    if not log.is_file():
        return []
    text = re.sub(r"\x1b\[[0-9;]*m", "", log.read_text(errors="replace"))
    out = []
    for m in _MONITOR.finditer(text):
        out.append(
            {
                "step": int(m.group(1)),
                "heldout_bit_acc": float(m.group(2)),
                "clean_bit_acc": float(m.group(3)),
                "psnr": float(m.group(4)),
                "seconds": float(m.group(5)),
            }
        )
    return out
