"""Evaluation stage ``scene``."""

from __future__ import annotations

from typing import Any, Dict

from gsticker_plugin.evaluation.workspace import Workspace
from gsticker_plugin.machine import console_script


def run(ws: Workspace) -> Dict[str, Any]:
    if ws.p.scene.data is not None:
        return {"data": str(ws.p.scene.data), "generated": False}
    g = dict(ws.p.scene.generate or {})
    scene = ws.out / "scene"
    if not ((scene / "transforms_test.json").is_file() or (scene / "transforms.json").is_file()):
        cmd = [console_script("ns-gsticker-scene"), "--output-dir", str(scene)]
        for k, v in g.items():
            cmd += [f"--{k.replace('_', '-')}", str(v)]
        if scene.exists():
            cmd.append("--overwrite")
        ws.run_cmd(cmd, "scene")
    return {"data": str(scene), "generated": True, "settings": g}
