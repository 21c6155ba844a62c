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

import copy
import dataclasses
import importlib.metadata
import json
import math
import random
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch
import tyro
import yaml
from nerfstudio.utils import profiler, writer

from gsticker_plugin import compat
from gsticker_plugin.machine import load_average, machine_info
from gsticker_plugin.runs import final_rgb

DEFAULT_PRESETS = ("gsticker-nerfacto-small", "gsticker-tensorf-small")
QUICK_ITERATIONS = 20
QUICK_TEST_VIEWS = 3


@dataclass
class BenchConfig:
    """Train and score base presets on a Blender-format scene; write a Markdown table and a JSON file."""

    data: Path = Path("../shared/data/lego100")
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


class BenchError(Exception):
    """Bad input: the message names the problem and its fix."""


def log(message: str) -> None:
    print(f"[bench-presets] {message}", flush=True)


# ----------------------------------------------------------------------------- configs


def method_config(name: str):
    """The ``TrainerConfig`` registered under ``name`` (a fresh deep copy)."""
    compat.apply()  # the plugin's host fixes (offline LPIPS, checkpoint types)

    for ep in importlib.metadata.entry_points(group="nerfstudio.method_configs"):
        if ep.name == name:
            return copy.deepcopy(ep.load().config)
    # deferred: loads every method entry point, this plugin's included
    from nerfstudio.configs.method_configs import all_methods

    if name not in all_methods:
        raise BenchError(f"unknown method {name!r}; choose one that `ns-train --help` lists")
    return copy.deepcopy(all_methods[name])


def train_config(preset: str, bench: BenchConfig, data: Path):
    """The preset's config set up as ``ns-train PRESET --data DATA --machine.device-type cpu --vis tensorboard``."""
    config = method_config(preset)
    config.max_num_iterations = bench.iterations_for(config.max_num_iterations)
    config.data = data
    config.pipeline.datamanager.data = data
    config.pipeline.datamanager.dataparser.data = data
    config.machine.device_type = "cpu"
    config.machine.num_devices = 1
    config.machine.seed = bench.seed
    config.vis = "tensorboard"
    config.viewer.quit_on_train_completion = True
    config.save_only_latest_checkpoint = True
    config.output_dir = bench.output_dir
    config.experiment_name = data.name
    config.set_timestamp()
    return config


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


def _reset_nerfstudio_globals() -> None:
    """Nerfstudio keeps its event writers and profiler in module globals; start each run clean."""
    for w in writer.EVENT_WRITERS:
        tb = getattr(w, "tb_writer", None)
        if tb is not None:
            tb.close()
    writer.EVENT_WRITERS.clear()
    writer.EVENT_STORAGE.clear()
    writer.GLOBAL_BUFFER.clear()
    profiler.PROFILER.clear()


def train(config) -> Dict[str, Any]:
    """Nerfstudio's ``train_loop`` for one process, timed: returns seconds, iterations and what was saved."""
    _reset_nerfstudio_globals()
    config.save_config()
    random.seed(config.machine.seed)
    np.random.seed(config.machine.seed)
    torch.manual_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    t0 = time.perf_counter()
    trainer.setup()
    t1 = time.perf_counter()
    trainer.train()
    t2 = time.perf_counter()
    checkpoint = trainer.checkpoint_dir / f"step-{trainer.step:09d}.ckpt"
    if not checkpoint.is_file():
        raise RuntimeError(f"training finished but wrote no checkpoint {checkpoint}")
    _reset_nerfstudio_globals()
    iterations = config.max_num_iterations
    return {
        "config": str(config.get_base_dir() / "config.yml"),
        "checkpoint": str(checkpoint),
        "iterations": iterations,
        "setup_seconds": t1 - t0,
        "train_seconds": t2 - t1,
        "seconds_per_iteration": (t2 - t1) / iterations,
    }


# ----------------------------------------------------------------------------- evaluate


def count_parameters(model: torch.nn.Module) -> int:
    """Trainable-model size: every parameter except the LPIPS metric's (``lpips.`` entries)."""
    return sum(p.numel() for name, p in model.named_parameters() if "lpips" not in name.split("."))


def load_pipeline(config_path: Path, checkpoint: Path, data: Path):
    """Like ``eval_setup``: the saved config, the pipeline on the CPU with the test split, the checkpoint."""

    compat.apply()  # the plugin's host fixes (offline LPIPS, checkpoint types)

    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    config.pipeline.datamanager.data = data
    config.pipeline.datamanager.dataparser.data = data
    pipeline = config.pipeline.setup(device="cpu", test_mode="inference")  # eval dataset = the test split
    state = torch.load(checkpoint, map_location="cpu")  # weights_only, with numpy types allow-listed
    pipeline.load_pipeline(state["pipeline"], state["step"])
    pipeline.eval()
    return pipeline


def white_composite(image: np.ndarray) -> torch.Tensor:
    """uint8 RGB(A) -> float RGB in [0, 1], alpha composited on white."""
    rgb = torch.from_numpy(image.astype(np.float32) / 255.0)
    if rgb.shape[-1] == 4:
        rgb = rgb[..., :3] * rgb[..., 3:] + (1.0 - rgb[..., 3:])
    return rgb[..., :3]


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def evaluate(config_path: Path, checkpoint: Path, data: Path, num_views: int) -> Dict[str, Any]:
    """Test PSNR over the first ``num_views`` test views, and the parameter count of the loaded model."""
    pipeline = load_pipeline(config_path, checkpoint, data)
    datamanager = pipeline.datamanager
    if getattr(datamanager, "test_split", "test") != "test":
        raise RuntimeError(f"the evaluation dataset is the {datamanager.test_split!r} split, not 'test'")
    dataset = datamanager.eval_dataset
    n = min(num_views, len(dataset))
    values: List[float] = []
    t0 = time.perf_counter()
    for i in range(n):
        camera = dataset.cameras[i : i + 1]
        with torch.no_grad():
            rgb = final_rgb(pipeline.model.get_outputs_for_camera(camera)).clamp(0.0, 1.0)
        gt = white_composite(dataset.get_numpy_image(i))
        if gt.shape != rgb.shape:
            raise RuntimeError(f"test view {i}: rendered {tuple(rgb.shape)} but the image is {tuple(gt.shape)}")
        values.append(psnr(rgb, gt))
        log(f"  test view {i + 1}/{n}: PSNR {values[-1]:.2f} dB")
    return {
        "parameters": count_parameters(pipeline.model),
        "test_psnr": float(np.mean(values)),
        "test_psnr_per_view": values,
        "test_views": n,
        "test_views_available": len(dataset),
        "eval_seconds": time.perf_counter() - t0,
    }


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
