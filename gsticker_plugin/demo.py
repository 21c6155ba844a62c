"""``make demo``: the whole story on the embedded scene, on a CPU, with stock Nerfstudio commands.

1. ``ns-gsticker-scene``: render the built-in textured scene (100 px, Blender format).
2. ``ns-train gsticker-nerfacto-small``: train the right-sized base.
3. ``ns-train geometrysticker --load-checkpoint``: stick the owner message onto its geometry.
4. Verify: decode test views of the watermarked model and of the unwatermarked base with the owner key.
Later stages (recolor, ns-verify-owner) run when their commands are installed.

Each stage is skipped when its output already exists, so an interrupted demo resumes where it stopped.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import List

import tyro


@dataclass
class DemoConfig:
    """Run the gsticker demo end to end (scene -> base -> watermark -> verify)."""

    output_dir: Path = Path("outputs/demo")
    """Where everything is written."""
    resolution: int = 100
    """Scene resolution in pixels."""
    base_iterations: int = 1500
    """Training steps of the small nerfacto base."""
    sticker_iterations: int = 1000
    """Training steps of the sticker stage."""
    test_views: int = 50
    """Test views decoded in the verification stage."""
    owner_id: str = "demo-owner"
    """Owner ID the message is derived from."""


def _bin(name: str) -> str:
    cand = Path(sys.executable).with_name(name)
    return str(cand) if cand.exists() else (shutil.which(name) or name)


def _run(cmd: List[str], log: Path) -> None:
    print("  $ " + " ".join(cmd), flush=True)
    t0 = time.time()
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    with open(log, "w") as f:
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env)
    if proc.returncode != 0:
        tail = log.read_text().splitlines()[-15:]
        print("\n".join(tail))
        raise SystemExit(f"demo step failed (exit {proc.returncode}); full log: {log}")
    print(f"    done in {time.time() - t0:.0f} s (log: {log})", flush=True)


def main(cfg: DemoConfig) -> None:
    out = cfg.output_dir
    out.mkdir(parents=True, exist_ok=True)
    logs = out / "logs"
    logs.mkdir(exist_ok=True)
    scene = out / "scene"
    t_start = time.time()

    print("[1/4] Rendering the embedded scene", flush=True)
    if not (scene / "transforms_train.json").exists():
        _run([_bin("ns-gsticker-scene"), "--output-dir", str(scene), "--resolution", str(cfg.resolution),
              "--num-train", "100", "--num-val", "10", "--num-test", str(max(cfg.test_views, 1))], logs / "scene.log")
    else:
        print("    (exists)")

    print("[2/4] Training the small nerfacto base", flush=True)
    base_run = out / "demo" / "gsticker-nerfacto-small" / "base"
    if not list((base_run / "nerfstudio_models").glob("step-*.ckpt")):
        _run([_bin("ns-train"), "gsticker-nerfacto-small", "--machine.device-type", "cpu", "--vis", "tensorboard",
              "--output-dir", str(out), "--experiment-name", "demo", "--timestamp", "base",
              "--max-num-iterations", str(cfg.base_iterations), "--steps-per-save", "500",
              "--data", str(scene)], logs / "base.log")
    else:
        print("    (exists)")
    base_ckpt = max((base_run / "nerfstudio_models").glob("step-*.ckpt"))

    print("[3/4] Sticking the owner message onto the geometry", flush=True)
    wm_run = out / "demo" / "geometrysticker" / "watermarked"
    key_path = wm_run.with_name("watermarked.gskey")
    if not key_path.exists() or not list((wm_run / "nerfstudio_models").glob("step-*.ckpt")):
        _run([_bin("ns-train"), "geometrysticker", "--machine.device-type", "cpu", "--vis", "tensorboard",
              "--output-dir", str(out), "--experiment-name", "demo", "--timestamp", "watermarked",
              "--max-num-iterations", str(cfg.sticker_iterations), "--pipeline.owner-id", cfg.owner_id,
              "--load-checkpoint", str(base_ckpt)], logs / "sticker.log")
    else:
        print("    (exists)")

    print("[4/4] Verifying: decode test views with the owner key", flush=True)
    from gsticker_plugin import metrics
    from gsticker_plugin.evaluate import decode_images, load_pipeline, psnr_nhw3, render_split
    from gsticker_plugin.key import OwnerKey

    key = OwnerKey.load(key_path)
    pipe = load_pipeline(wm_run / "config.yml")
    marked = render_split(pipe, "test", cfg.test_views, sticker=True)
    clean = render_split(pipe, "test", cfg.test_views, sticker=False)
    threshold = metrics.min_matches_for_fpr(key.num_bits, 1e-6)
    dm, dc = decode_images(key, marked["rgb"]), decode_images(key, clean["rgb"])
    summary = {
        "test_views": int(marked["rgb"].shape[0]),
        "bit_acc_watermarked": float(dm.bit_acc.mean()),
        "bit_acc_unwatermarked": float(dc.bit_acc.mean()),
        "views_passing_1e-6_watermarked": float((dm.matches >= threshold).float().mean()),
        "views_passing_1e-6_unwatermarked": float((dc.matches >= threshold).float().mean()),
        "psnr_watermarked_vs_unwatermarked": float(psnr_nhw3(marked["rgb"], clean["rgb"]).mean()),
        "psnr_watermarked_vs_gt": float(psnr_nhw3(marked["rgb"], marked["gt"]).mean()),
        "psnr_unwatermarked_vs_gt": float(psnr_nhw3(clean["rgb"], clean["gt"]).mean()),
    }
    (out / "demo_summary.json").write_text(json.dumps(summary, indent=2))
    for k, v in summary.items():
        print(f"    {k}: {v:.4f}" if isinstance(v, float) else f"    {k}: {v}")

    for cmd in ("ns-recolor", "ns-verify-owner"):
        if shutil.which(cmd) or Path(sys.executable).with_name(cmd).exists():
            print(f"    ({cmd} is installed; see README for its demo commands)")

    print(f"\nDone in {(time.time() - t_start) / 60:.1f} min.")
    print(f"  scene:               {scene}")
    print(f"  base model:          {base_run / 'config.yml'}")
    print(f"  watermarked model:   {wm_run / 'config.yml'}   (shareable: ns-viewer --load-config ...)")
    print(f"  owner key (secret):  {key_path}")
    print(f"  summary:             {out / 'demo_summary.json'}")


def entrypoint() -> None:
    main(tyro.cli(DemoConfig))


if __name__ == "__main__":
    entrypoint()
