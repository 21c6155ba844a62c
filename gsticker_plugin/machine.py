"""The machine a command runs on (for benchmark and evaluation records) and the console scripts beside Python."""

from __future__ import annotations

import datetime
import importlib.metadata
import os
import platform
import shutil
import subprocess
import sys
import time
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
    """``ns-train geometrysticker --pipeline.mark sticker`` on the CPU into ``OUTPUT/EXPERIMENT/geometrysticker/watermarked`` with its owner
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
        "--pipeline.mark",
        "sticker",
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


def run_logged(cmd: List[str], log: Path, ok: tuple = (0,), what: str = "step") -> Dict[str, Any]:
    """Run a command with its output in ``log`` (warnings off, no downloads); on an exit status outside ``ok``,
    print the log's tail and stop with a one-line message. Returns the command, its exit status and wall seconds."""
    print("  $ " + " ".join(f"'{c}'" if " " in c else c for c in cmd), flush=True)
    t0 = time.time()
    env = dict(os.environ, PYTHONWARNINGS="ignore", GSTICKER_NO_DOWNLOAD="1")
    with open(log, "w") as f:
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env)
    wall = time.time() - t0
    if proc.returncode not in ok:
        print("\n".join(log.read_text().splitlines()[-15:]))
        raise SystemExit(f"{what} failed (exit {proc.returncode}); full log: {log}")
    print(f"    exit {proc.returncode}, {wall:.0f} s (log: {log})", flush=True)
    return {"command": cmd, "exit": proc.returncode, "wall_s": wall}


def config_under(folder: Path) -> Path:
    """The first config.yml below ``folder`` (a run written by ns-train or ns-recolor there)."""
    found = sorted(folder.glob("**/config.yml"))
    if not found:
        raise SystemExit(f"no config.yml under {folder}")
    return found[0]


def recolor_into(args: List[str], config: Path, dest: Path, log: Path, what: str = "step") -> Optional[Dict[str, Any]]:
    """``ns-recolor ARGS --load-config CONFIG`` into ``dest`` unless a run is there already (then None)."""
    if list(dest.glob("**/config.yml")):
        print(f"    ({dest} exists)")
        return None
    argv = [console_script("ns-recolor"), *args, "--load-config", str(config), "--output-dir", str(dest), "--overwrite"]
    return run_logged(argv, log, what=what)
