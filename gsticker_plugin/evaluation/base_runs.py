"""Base runs for the presets benchmark: a preset trained by Nerfstudio's own training loop, loaded back as ns-eval
would, and scored on the test split."""

from __future__ import annotations

import copy
import importlib.metadata
import math
import random
import time
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import torch
import yaml
from nerfstudio.utils import profiler, writer

from gsticker_plugin import compat
from gsticker_plugin.runs import final_rgb


class BenchError(Exception):
    """Bad input: the message names the problem and its fix."""


def log(message: str) -> None:
    print(f"[bench-presets] {message}", flush=True)


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


def train_config(preset: str, bench: Any, data: Path):
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
