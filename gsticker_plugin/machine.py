"""The machine a command runs on (for benchmark and evaluation records) and the console scripts beside Python."""

from __future__ import annotations

import datetime
import importlib.metadata
import os
import platform
import shutil
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import torch


def console_script(name: str) -> str:
    """The path of console script ``name`` installed beside this Python (else found on PATH, else the bare name)."""
    cand = Path(sys.executable).with_name(name)
    return str(cand) if cand.exists() else (shutil.which(name) or name)


def sticker_train_argv(
    output_dir: Path, experiment: str, max_steps: int, owner_id: str, key_path: Path, *options: str
) -> List[str]:
    """``ns-train geometrysticker`` on the CPU into ``OUTPUT/EXPERIMENT/geometrysticker/watermarked`` with its owner
    key at ``key_path``; ``options``: further flags (``--load-checkpoint`` among them)."""
    return [
        console_script("ns-train"),
        "geometrysticker",
        "--machine.device-type",
        "cpu",
        "--vis",
        "tensorboard",
        "--output-dir",
        str(output_dir),
        "--experiment-name",
        experiment,
        "--timestamp",
        "watermarked",
        "--max-num-iterations",
        str(max_steps),
        "--pipeline.owner-id",
        owner_id,
        "--pipeline.key-path",
        str(key_path),
        *options,
    ]


def load_average() -> Optional[List[float]]:
    """1, 5 and 15 minute load averages (other work on the machine skews the timings)."""
    try:
        return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
    except (OSError, ValueError):
        return None


def _version(name: str) -> str:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return "?"


def machine_info() -> Dict[str, Any]:
    """CPU model, cores, library versions, threads, CUDA, date and load: what a timing depends on."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        nproc = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        nproc = os.cpu_count() or 0
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "nproc": nproc,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "nerfstudio": _version("nerfstudio"),
        "numpy": np.__version__,
        "python": platform.python_version(),
        "cuda": torch.cuda.is_available(),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "load_average_at_start": load_average(),
    }
