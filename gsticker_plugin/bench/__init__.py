"""Benchmark commands: each measures and writes a docs page with its JSON beside it."""

import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Callable, Dict, List

TINY_POOL = [
    "--pipeline.mark",
    "sticker",
    "--pipeline.pool-train-views",
    "2",
    "--pipeline.pool-novel-views",
    "2",
    "--pipeline.monitor-views",
    "1",
    "--pipeline.steps-per-monitor",
    "5",
    "--pipeline.views-per-step",
    "2",
    "--pipeline.heads.width",
    "8",
]
"""A sticker (not the field mark) with the smallest pool and heads: the tests' tiny runs and bench.recipient's."""


def command_lines(title: str, when: str, json_name: str, command: str) -> List[str]:
    """A bench page's opening: its title, the command that wrote it (``when``: date and machine) and its JSON."""
    return [
        f"# {title}",
        "",
        f"Command ({when}; every number here is in [{json_name}]({json_name}), written by it):",
        "",
        "```bash",
        command,
        "```",
        "",
    ]


def provenance(module: str) -> Dict[str, Any]:
    """What a page records of its run: the command (``python -m MODULE`` with this process's arguments, quoted for a shell), the date and
    the machine."""
    from gsticker_plugin.machine import machine_info  # deferred: imports torch

    return {
        "command": f"python -m {module} " + shlex.join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_info(),
    }


def write_page(output: Path, res: Dict[str, Any], page: Callable[[Dict[str, Any]], str]) -> None:
    """Write ``res`` as ``OUTPUT.json`` (its name in ``res["json"]``, for the page's link) and the page ``page(res)``
    as ``OUTPUT`` (folders created)."""
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    res["json"] = output.with_suffix(".json").name
    output.with_suffix(".json").write_text(json.dumps(res, indent=1) + "\n")
    output.write_text(page(res))
    print(f"wrote {output}")


def bench_main(
    args_type: type, measure: Callable[[Any], Dict[str, Any]], page: Callable[[Dict[str, Any]], str]
) -> None:
    """A bench's command: its arguments ``args_type`` (with ``output`` and ``page_only``) from the command line, then
    ``measure(args)`` (or, with ``--page-only``, OUTPUT's JSON read back) written as the page and its JSON."""
    import tyro

    args = tyro.cli(args_type)
    res = json.loads(args.output.with_suffix(".json").read_text()) if args.page_only else measure(args)
    write_page(args.output, res, page)


def suspect_summary(rows: List[Dict[str, Any]], threshold: int, num_bits: int = 48) -> Dict[str, Any]:
    """One suspect's rows (each with ``matches``) as ns-verify-owner would judge them: views, views passing at
    ``threshold``, bit accuracy, min / median / max matches and the verdict (OWNED when half the views pass)."""
    import statistics

    from gsticker_plugin import metrics

    m = [r["matches"] for r in rows]
    if not m:
        return {"views": 0}
    passing = sum(x >= threshold for x in m)
    return {
        "views": len(m),
        "passing": passing,
        "bit_acc": sum(m) / (num_bits * len(m)),
        "min": min(m),
        "median": statistics.median(m),
        "max": max(m),
        "verdict": "OWNED" if passing >= metrics.views_needed(len(m), 0.5) else "not shown",
    }
