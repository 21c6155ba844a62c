"""Sticker runs for the benchmarks: the settings they share, one ``ns-train geometrysticker`` run, and its mark's PSNR."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from gsticker_plugin.evaluate import load_pipeline, psnr_nhw3, render_split
from gsticker_plugin.machine import console_script, run_logged, sticker_train_argv
from gsticker_plugin.runs import checkpoint_step, latest_checkpoint


@dataclass
class StickerRunConfig:
    """The watermarked run a benchmark trains on a base (shared by bench.geometry and bench.targets)."""

    load_checkpoint: Path
    """The base run's checkpoint (RUN/nerfstudio_models/step-N.ckpt)."""
    data: Optional[Path] = None
    """The base's dataset folder, when its recorded path does not exist from here."""
    output_dir: Path = Path("outputs/bench-geometry")
    """Where the runs, reports and results are written."""
    steps: int = 200
    """Sticker training steps."""
    warmup_steps: int = 50
    """Sticker warm-up (no content loss) before the content loss ramps in."""
    pool_views: int = 16
    """Training and novel views each in the sticker's fast-path pool."""
    owner_id: str = "bench-owner"
    """Owner ID of the message."""
    message: Optional[str] = None
    """The message as 0/1 characters (default: drawn at random by ns-train); a benchmark records the bits it used,
    so passing them back reproduces its numbers."""

    def layout(self) -> Tuple[Path, Path, List[str], Path, Path]:
        """(output folder, its logs folder (made), the --data arguments, base checkpoint, base config.yml)."""
        out = self.output_dir.resolve()
        logs = out / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        data = ["--data", str(Path(self.data).resolve())] if self.data is not None else []
        base_ckpt = Path(self.load_checkpoint).resolve()
        return out, logs, data, base_ckpt, base_ckpt.parent.parent / "config.yml"


def run_step(cmd: List[str], log: Path, ok=(0,)) -> Dict[str, Any]:
    """Run one ``ns-*`` step of a benchmark, its output logged to ``log`` (fails unless its exit status is in ``ok``)."""
    return run_logged(cmd, log, ok, what="bench step")


def train_sticker(
    cfg: StickerRunConfig, out: Path, base_ckpt: Path, data: List[str], logs: Path
) -> Optional[Dict[str, Any]]:
    """``ns-train geometrysticker`` into ``out/bench/geometrysticker/watermarked`` (skipped, returning None, when
    its checkpoint and key exist)."""
    wm = out / "bench" / "geometrysticker" / "watermarked"
    if wm.with_name("watermarked.gskey").exists() and list((wm / "nerfstudio_models").glob("step-*.ckpt")):
        print("    (exists)")
        return None
    return run_step(
        sticker_train_argv(
            out,
            "bench",
            cfg.steps,
            cfg.owner_id,
            wm.with_name("watermarked.gskey"),
            "--steps-per-save",
            str(cfg.steps),
            "--pipeline.pool-train-views",
            str(cfg.pool_views),
            "--pipeline.pool-novel-views",
            str(cfg.pool_views),
            "--pipeline.monitor-views",
            "4",
            "--pipeline.steps-per-monitor",
            "50",
            "--pipeline.warmup-steps",
            str(cfg.warmup_steps),
            *(["--pipeline.message", cfg.message] if cfg.message else []),
            "--load-checkpoint",
            str(base_ckpt),
            *data,
        ),
        logs / "train.log",
    )


def psnr_watermarked_vs_clean(config: Path, views: int) -> Dict[str, float]:
    """Mean PSNR over the first ``views`` test views: sticker on vs off of the same run (for a recolored run of a
    watermarked one: the edit on the watermarked model vs the same edit on the unwatermarked base), and each of them
    against the ground truth."""
    pipe = load_pipeline(config)
    on = render_split(pipe, "test", views, sticker=True, progress=False)
    off = render_split(pipe, "test", views, sticker=False, progress=False)
    return {
        "vs_clean": float(psnr_nhw3(on["rgb"], off["rgb"]).mean()),
        "marked_vs_gt": float(psnr_nhw3(on["rgb"], on["gt"]).mean()),
        "clean_vs_gt": float(psnr_nhw3(off["rgb"], off["gt"]).mean()),
    }


def train_nulls(cfg: Any, out: Path, logs: Path) -> List[Dict[str, Any]]:
    """The null models to train: ``[{name, config, data}]`` (each trained once, skipped when its checkpoint exists)."""
    nulls = out / "nulls"
    jobs = []
    if cfg.null_seeds:
        if cfg.data is None:
            raise SystemExit("--null-seeds trains on the base's dataset: pass --data")
        data = Path(cfg.data).resolve()
        for seed in cfg.null_seeds:
            jobs.append((f"{data.name}-seed{seed}", data, ["--machine.seed", str(seed)]))
    if cfg.other_scene:
        scene = nulls / "scene"
        if not (scene / "transforms_train.json").is_file():
            run_step(
                [
                    console_script("ns-gsticker-scene"),
                    "--output-dir",
                    str(scene),
                    "--resolution",
                    "100",
                    "--num-train",
                    "100",
                    "--num-val",
                    "10",
                    "--num-test",
                    "20",
                ],
                logs / "null-scene.log",
            )
        jobs.append(("scene", scene, []))
    found = []
    for name, data, extra in jobs:
        run = nulls / name / cfg.null_preset / "base"
        if not list((run / "nerfstudio_models").glob("step-*.ckpt")):
            print(f"    training null model {name} ({cfg.null_steps} steps)", flush=True)
            run_step(
                [
                    console_script("ns-train"),
                    cfg.null_preset,
                    "--machine.device-type",
                    "cpu",
                    "--vis",
                    "tensorboard",
                    *extra,
                    "--output-dir",
                    str(nulls),
                    "--experiment-name",
                    name,
                    "--timestamp",
                    "base",
                    "--max-num-iterations",
                    str(cfg.null_steps),
                    "--steps-per-save",
                    str(cfg.null_steps),
                    "--data",
                    str(data),
                ],
                logs / f"null-{name}.log",
            )
        steps = 1 + checkpoint_step(latest_checkpoint(run / "nerfstudio_models"))
        found.append({"name": f"{name} ({cfg.null_preset}, {steps} steps)", "config": run / "config.yml", "data": data})
    return found
