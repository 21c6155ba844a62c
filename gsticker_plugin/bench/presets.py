"""Benchmark the base presets: train each with stock Nerfstudio, time it, and score it on the test split.

    python -m gsticker_plugin.bench.presets --data ../shared/data/lego100 \\
        --presets gsticker-nerfacto-small gsticker-tensorf-small --output docs/experiments/presets.md

For every preset this runs the real training loop (Nerfstudio's ``Trainer`` built from the preset's
``MethodSpecification``, as ``ns-train PRESET --machine.device-type cpu --vis tensorboard`` would), then loads
the saved ``config.yml`` and checkpoint again (as ``ns-eval``/``ns-render`` would), renders the first N views of
the Blender test split and scores them (PSNR against the ground truth composited on white). It writes a
Markdown table (preset, parameters, s/iteration, test PSNR, minutes, iterations) with the exact command and
the machine, and the same numbers as JSON beside it (``docs/experiments/presets.json``).

``--quick`` (20 iterations, 3 test views) checks the whole path in well under a minute on a tiny scene.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch
import tyro

from gsticker_plugin.evaluation.base_runs import (
    BenchError,
    evaluate,
    log,
    train,
    train_config,
)
from gsticker_plugin.machine import load_average, machine_info

DEFAULT_PRESETS = ("gsticker-nerfacto-small", "gsticker-tensorf-small")
QUICK_ITERATIONS = 20
QUICK_TEST_VIEWS = 3


@dataclass
class BenchConfig:
    """Train and score base presets on a Blender-format scene; write a Markdown table and a JSON file."""

    data: Path
    """Blender-format scene (transforms_{train,val,test}.json)."""
    presets: Tuple[str, ...] = DEFAULT_PRESETS
    """Registered Nerfstudio method names to benchmark (ours or stock)."""
    output: Path = Path("docs/experiments/presets.md")
    """Markdown report; the JSON goes beside it with the suffix .json."""
    output_dir: Path = Path("outputs/bench-presets")
    """Where the training runs (config.yml, checkpoints, tensorboard events) are written."""
    max_num_iterations: Optional[int] = None
    """Override every preset's iterations, as ns-train --max-num-iterations does (its schedules are not rescaled)."""
    num_test_views: Optional[int] = None
    """Score the first N test views (default 25, or 3 with --quick)."""
    quick: bool = False
    """Smoke run: 20 iterations and 3 test views (unless given explicitly)."""
    seed: int = 42
    """Nerfstudio's machine seed for every run."""
    threads: Optional[int] = None
    """torch CPU threads (default: torch's, one per core); on a CPU others are busy with, 1 can be several times faster."""

    def iterations_for(self, preset_default: int) -> int:
        if self.max_num_iterations is not None:
            return self.max_num_iterations
        return QUICK_ITERATIONS if self.quick else preset_default

    def test_views(self) -> int:
        if self.num_test_views is not None:
            return self.num_test_views
        return QUICK_TEST_VIEWS if self.quick else 25


# ----------------------------------------------------------------------------- configs


def validate(bench: BenchConfig) -> Path:
    data = bench.data.expanduser()
    blender = all((data / f"transforms_{split}.json").is_file() for split in ("train", "test"))
    if not blender and not (data / "transforms.json").is_file():
        raise BenchError(
            f"{data} is neither a Blender-format scene (no transforms_train.json and transforms_test.json) nor "
            "nerfstudio-data (no transforms.json); pass --data with a dataset folder"
        )
    if not bench.presets:
        raise BenchError("no presets given; pass --presets NAME [NAME ...]")
    if bench.iterations_for(1) < 1:
        raise BenchError("--max-num-iterations must be at least 1")
    if bench.test_views() < 1:
        raise BenchError("--num-test-views must be at least 1")
    if bench.threads is not None and bench.threads < 1:
        raise BenchError("--threads must be at least 1")
    if bench.output.suffix.lower() != ".md":
        raise BenchError(f"--output {bench.output} should be a Markdown file (.md)")
    return data


# ----------------------------------------------------------------------------- train


# ----------------------------------------------------------------------------- evaluate


# ----------------------------------------------------------------------------- report


def _fmt_psnr(value: float) -> str:
    return f"{value:.2f} dB" if math.isfinite(value) else str(value)


def render_markdown(report: Dict[str, Any]) -> str:
    m = report["machine"]
    n = report["settings"]["num_test_views"]
    lines = [
        "# Base presets, measured",
        "",
        f"Scene `{report['settings']['data']}`; test PSNR over the first {n} test views (rendered on the CPU, "
        "ground truth composited on white). Written by `gsticker_plugin/bench/presets.py`.",
        "",
        f"| preset | parameters | s/iteration | test PSNR (first {n} test views) | minutes | iterations |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in report["results"]:
        lines.append(
            f"| `{r['preset']}` | {r['parameters']:,} | {r['seconds_per_iteration']:.3f} | {_fmt_psnr(r['test_psnr'])} "
            f"| {r['train_seconds'] / 60:.1f} | {r['iterations']} |"
        )
    lines += [
        "",
        "- parameters: model parameters excluding the LPIPS metric's backbone (`lpips.` entries).",
        "- s/iteration: training wall time / iterations; minutes: training wall time (Nerfstudio's training loop "
        "with its periodic eval and checkpointing; not setup or the test scoring).",
    ]
    if any(r["test_views"] < n for r in report["results"]):
        lines.append("- the scene has fewer test views than asked for; all of them were scored.")
    lines += [
        "",
        "Command:",
        "",
        "```",
        report["command"],
        "```",
        "",
        f"Machine: {m['nproc']} CPU cores (nproc), {m['cpu']}; torch {m['torch']} ({m['torch_threads']} threads), "
        f"nerfstudio {m['nerfstudio']}, numpy {m['numpy']}, Python {m['python']}; {m['date']}.",
    ]
    loads = [m.get("load_average_at_start")] + [r.get("load_average_after") for r in report["results"]]
    loads = [x for x in loads if x]
    if loads:
        worst = max(x[0] for x in loads)
        lines.append(
            f"Load average (1 min) during the run: up to {worst:.1f} on {m['nproc']} cores"
            + (" (the machine was shared: timings are pessimistic)." if worst > m["nproc"] + 0.5 else ".")
        )
    lines.append("")
    return "\n".join(lines)


def write_report(report: Dict[str, Any], output: Path) -> Path:
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(render_markdown(report), "utf8")
    json_path = output.with_suffix(".json")
    json_path.write_text(json.dumps(report, indent=2) + "\n", "utf8")
    return json_path


def command_line(argv: Optional[List[str]]) -> str:
    args = sys.argv[1:] if argv is None else argv
    return "python -m gsticker_plugin.bench.presets " + shlex.join(args)


def main(bench: BenchConfig, argv: Optional[List[str]] = None) -> int:
    try:
        data = validate(bench)
    except BenchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report: Dict[str, Any] = {
        "command": command_line(argv),
        "machine": machine_info(),
        "settings": {
            **{k: str(v) if isinstance(v, Path) else v for k, v in dataclasses.asdict(bench).items()},
            "num_test_views": bench.test_views(),
        },
        "results": [],
    }
    if bench.threads is not None:
        torch.set_num_threads(bench.threads)
    report["machine"]["torch_threads"] = torch.get_num_threads()
    for k, preset in enumerate(bench.presets, 1):
        try:
            config = train_config(preset, bench, data)
        except BenchError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        log(f"({k}/{len(bench.presets)}) training {preset}: {config.max_num_iterations} iterations on {data}")
        trained = train(config)
        log(
            f"({k}/{len(bench.presets)}) {preset}: {trained['train_seconds'] / 60:.1f} min, "
            f"{trained['seconds_per_iteration']:.3f} s/iteration; scoring {bench.test_views()} test views"
        )
        scored = evaluate(Path(trained["config"]), Path(trained["checkpoint"]), data, bench.test_views())
        result = {"preset": preset, **trained, **scored, "load_average_after": load_average()}
        report["results"].append(result)
        json_path = write_report(report, bench.output)  # after every preset: partial results survive a crash
        log(
            f"({k}/{len(bench.presets)}) {preset}: test PSNR {_fmt_psnr(scored['test_psnr'])}, "
            f"{scored['parameters']:,} parameters"
        )
    log(f"wrote {bench.output} and {json_path}")
    return 0


def entrypoint() -> None:
    sys.exit(main(tyro.cli(BenchConfig)))


if __name__ == "__main__":
    entrypoint()
