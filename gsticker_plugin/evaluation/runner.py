"""Runs the evaluation protocol stage by stage (``evaluation/stages/<stage>.py``); finished stages are skipped."""

from __future__ import annotations

import functools
import json
import time
from typing import Any, Dict, Sequence

from gsticker_plugin.evaluation import report
from gsticker_plugin.evaluation.config import to_plain
from gsticker_plugin.evaluation.stages import (
    bases,
    curves,
    distortions,
    false_positives,
    geometry,
    purify,
    quality,
    recolor,
    renders,
    scene,
    seeds,
    speed,
    sticker,
    wild,
)
from gsticker_plugin.evaluation.workspace import Workspace
from gsticker_plugin.machine import machine_info

STAGES = {
    "scene": scene,
    "bases": bases,
    "sticker": sticker,
    "renders": renders,
    "quality": quality,
    "geometry": geometry,
    "seeds": seeds,
    "distortions": distortions,
    "curves": curves,
    "recolor": recolor,
    "purify": purify,
    "false_positives": false_positives,
    "speed": speed,
    "wild": wild,
}
"""Every stage in protocol order; each module's ``run(ws)`` returns the stage's numbers."""


class Runner(Workspace):
    """The protocol's workspace that runs its stages."""

    def run(self, stages: Sequence[str]) -> Dict[str, Any]:
        t0 = time.time()
        fns = {name: functools.partial(stage.run, self) for name, stage in STAGES.items()}
        want = [s for s in fns if s in stages]
        if self.p.geometry is None:
            want = [s for s in want if s not in ("geometry", "purify", "seeds")]
        if not self.p.sticker.seeds and "seeds" in want:
            want.remove("seeds")
        if self.p.geometry is not None and not self.p.geometry.purify_steps and "purify" in want:
            want.remove("purify")
        if self.p.recolor is None and "recolor" in want:
            want.remove("recolor")
        if not self.p.curves and "curves" in want:
            want.remove("curves")
        if not self.p.distortions and "distortions" in want:
            want.remove("distortions")
        if self.p.wild is None and "wild" in want:
            want.remove("wild")
        for i, s in enumerate(want):
            self.say(f"[eval] stage {i + 1}/{len(want)}: {s}")
            self.stage(s, fns[s])
        results = {
            "protocol": to_plain(self.p),
            "threshold": self.threshold,
            "machine": machine_info(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "paper": report.paper_numbers(),
        }
        for s in fns:
            if self.stage_path(s).is_file():
                results[s] = json.loads(self.stage_path(s).read_text())
        results["wall_seconds_this_invocation"] = round(time.time() - t0, 1)
        (self.out / "results.json").write_text(json.dumps(results, indent=1, default=str))
        if "report" in stages:
            report.write_all(results, self.out)
        return results
