"""Does the geometric decoder still read a *fused* export (a stock run of the base's method, distilled from the
watermarked run)? Writes docs/experiments/bench-fuse.md and docs/experiments/bench-fuse.json.

    python -m gsticker_plugin.bench.fuse --load-config outputs/fuse/wm/geometrysticker/run/config.yml \\
        --key outputs/fuse/wm.gskey --output-dir outputs/fuse

1. ``gsticker_plugin.fuse`` distils the watermarked run into a stock run of its base's method (skipped when the
   fused run exists and ``--reuse``);
2. ``ns-verify-owner --decode geometry`` (the installed CLI, in a subprocess: the fused run is opened as any stock
   run) on the fused run and, for comparison, on the watermarked run; per-view matches, views passing, verdict;
3. PSNR at the run's eval cameras: fused vs watermarked render, fused vs unwatermarked (sticker off) render,
   watermarked vs unwatermarked, and each against the ground truth.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import subprocess
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

import torch
import tyro

from gsticker_plugin import compat
from gsticker_plugin.fuse import FuseConfig, eval_cameras, fuse, psnr
from gsticker_plugin.runs import final_rgb, load_run

PSNR_PAIRS = (
    "fused_vs_watermarked",
    "fused_vs_base",
    "watermarked_vs_base",
    "fused_vs_gt",
    "watermarked_vs_gt",
    "base_vs_gt",
)
"""The render pairs whose PSNR the page reports."""


@dataclass
class BenchFuseConfig:
    """Fuse a watermarked run into a stock run and measure what the geometric decoder reads from it."""

    load_config: Path
    """The watermarked run's config.yml."""
    key: Path
    """Its owner key (version 2)."""
    output_dir: Path = Path("outputs/fuse")
    """Fused run (OUTPUT_DIR/fused/METHOD/fused) and the verification reports."""
    data: Optional[Path] = None
    fuse: FuseConfig = field(default_factory=lambda: FuseConfig(load_config=Path("-")))
    """Distillation settings (load_config and output_dir are taken from above)."""
    reuse: bool = True
    """Reuse an existing fused run (and reports) instead of distilling again."""
    num_views: int = 8
    """ns-verify-owner --num-views."""
    psnr_views: int = 4
    """Eval cameras for the PSNR comparison."""
    verify_watermarked: bool = True
    """Also verify the watermarked run itself (the reference row)."""
    doc: Path = Path("docs/experiments/bench-fuse.md")
    """Markdown report; the JSON goes beside it."""


def verify(config: Path, key: Path, out: Path, num_views: int, data: Optional[Path], reuse: bool) -> Dict[str, Any]:
    report = out / "report.json"
    t0 = time.time()
    rc = None
    if not (reuse and report.is_file()):
        exe = Path(sys.executable).with_name("ns-verify-owner")
        cmd = [
            str(exe),
            "--load-config",
            str(config),
            "--key",
            str(key),
            "--decode",
            "geometry",
            "--num-views",
            str(num_views),
            "--output",
            str(out),
            "--no-progress",
        ]
        if data is not None:
            cmd += ["--data", str(data)]
        print("[bench-fuse] " + " ".join(cmd), file=sys.stderr, flush=True)
        rc = subprocess.run(cmd, stdout=sys.stderr).returncode
    r = json.loads(report.read_text())["keys"][0]
    return {
        "exit": rc,
        "seconds": time.time() - t0 if rc is not None else None,
        "verdict": r["verdict"],
        "views_passing": r["views_passing"],
        "views": r["views"],
        "mean_bit_accuracy": r["mean_bit_accuracy"],
        "matches_min": r["matches_min"],
        "matches_median": r["matches_median"],
        "matches_max": r["matches_max"],
        "threshold": r["thresholds"]["used"],
        "explained": [v.get("geometry", {}).get("explained") for v in r["per_view"]],
        "per_view_matches": [v["matches"] for v in r["per_view"]],
    }


@torch.no_grad()
def psnr_table(wm_config: Path, fused_config: Path, data: Optional[Path], num: int) -> Dict[str, float]:
    dev = torch.device("cpu")
    with contextlib.redirect_stdout(sys.stderr):
        _, wm_pipe, _ = load_run(wm_config, data=data, device=dev)
        fcfg, fused_pipe, _ = load_run(fused_config, data=data, device=dev)
    wm, fused = wm_pipe.model, fused_pipe.model
    ds = wm_pipe.datamanager.eval_dataset
    rows: Dict[str, List[float]] = {k: [] for k in PSNR_PAIRS}
    cams = eval_cameras(wm_pipe, num)
    for name, cam in cams:
        i = int(name.split("/")[1])
        with wm.sticker_enabled(True):
            a = final_rgb(wm.get_outputs_for_camera(cam)).cpu()
        with wm.sticker_enabled(False):
            b = final_rgb(wm.get_outputs_for_camera(cam)).cpu()
        f = final_rgb(fused.get_outputs_for_camera(cam)).cpu()
        gt = ds.get_image_float32(i)
        if gt.shape[-1] == 4:
            bg = wm.background_color().image_color()
            gt = gt[..., :3] * gt[..., 3:] + bg * (1.0 - gt[..., 3:])
        rows["fused_vs_watermarked"].append(psnr(f, a))
        rows["fused_vs_base"].append(psnr(f, b))
        rows["watermarked_vs_base"].append(psnr(a, b))
        rows["fused_vs_gt"].append(psnr(f, gt))
        rows["watermarked_vs_gt"].append(psnr(a, gt))
        rows["base_vs_gt"].append(psnr(b, gt))
    out = {k: float(sum(v) / len(v)) for k, v in rows.items()}
    out["views"] = len(cams)
    out["fused_method"] = fcfg.method_name
    out["fused_model_class"] = type(fused).__name__
    return out


def fmt(x, nd=2):
    return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def write_doc(res: Dict[str, Any], doc: Path) -> None:
    f, v, p = res["fuse"], res["verify"], res["psnr"]
    lines = [
        "# Fused export: does the geometric decoder read a stock run distilled from the watermarked one?",
        "",
        "Generated by `python -m gsticker_plugin.bench.fuse` (issue 21, item 4). The watermarked run is distilled into a "
        f"stock `{p['fused_method']}` run ({p['fused_model_class']}, no sticker module, opens without the plugin); "
        "the owner then verifies it with `ns-verify-owner --decode geometry` against the unwatermarked base, as any "
        "suspect.",
        "",
        f"Machine: {res['machine']}. Command: `{res['command']}`.",
        "",
        "## Distillation",
        "",
        f"- pool: {f['pool_views']} views ({res['settings']['train_views']} training cameras + "
        f"{res['settings']['orbit_views']} orbit poses, seed {res['settings']['seed']}), {f['pool_rays']} rays "
        f"({f['pool_changed_rays']} changed by the sticker), cached in {f['cache_seconds']:.0f} s",
        f"- {res['settings']['steps']} steps x {res['settings']['rays_per_step']} rays, Adam {res['settings']['lr']} -> "
        f"{res['settings']['lr_final']} on the final field (hash grid + MLPs; proposal networks kept): "
        f"{f['distill_seconds']:.0f} s",
        "- final losses: " + ", ".join(f"{k} {val:.3g}" for k, val in f["final_losses"].items()),
        "",
        "## Verification (geometric decoder, theoretical threshold)",
        "",
        "| suspect | verdict | views passing | mean bit accuracy | matches min / median / max (of 48) | fit explains (median) | seconds |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in v.items():
        ex = sorted(x for x in r["explained"] if x is not None)
        med = ex[len(ex) // 2] if ex else None
        lines.append(
            f"| {name} | {r['verdict']} | {r['views_passing']}/{r['views']} | {100 * r['mean_bit_accuracy']:.1f} % "
            f"| {r['matches_min']} / {r['matches_median']} / {r['matches_max']} | "
            f"{fmt(100 * med if med is not None else None, 1)} % | {fmt(r['seconds'], 0)} |"
        )
    lines += [
        "",
        f"## Renders ({p['views']} eval cameras, mean PSNR in dB)",
        "",
        "| pair | PSNR (dB) |",
        "|---|---|",
    ]
    for k in PSNR_PAIRS:
        lines.append(f"| {k.replace('_vs_', ' vs ').replace('_', ' ')} | {p[k]:.2f} |")
    lines += ["", "## Conclusion", "", res["conclusion"], ""]
    doc.parent.mkdir(parents=True, exist_ok=True)
    doc.write_text("\n".join(lines))
    doc.with_suffix(".json").write_text(json.dumps(res, indent=1, default=str))


def conclusion(res: Dict[str, Any]) -> str:
    fz, wm = res["verify"]["fused"], res["verify"].get("watermarked")
    p = res["psnr"]
    acc = 100 * fz["mean_bit_accuracy"]
    ref = (
        f" (watermarked run: {100 * wm['mean_bit_accuracy']:.1f} %, {wm['views_passing']}/{wm['views']})" if wm else ""
    )
    if fz["verdict"] == "owned":
        return (
            f"The geometric decoder reads the fused run: {fz['views_passing']}/{fz['views']} views pass, "
            f"{acc:.1f} % of the bits{ref}; its renders are {p['fused_vs_watermarked']:.1f} dB from the "
            f"watermarked ones and {p['fused_vs_base']:.1f} dB from the unwatermarked base's."
        )
    return (
        f"The geometric decoder does not read the fused run well enough: {fz['views_passing']}/{fz['views']} views "
        f"pass, {acc:.1f} % of the bits{ref}; renders {p['fused_vs_watermarked']:.1f} dB from the watermarked "
        f"ones ({p['watermarked_vs_base']:.1f} dB is the sticker's own change). The wrapped run stays the default "
        "export."
    )


def main(cfg: BenchFuseConfig) -> Dict[str, Any]:

    compat.apply()  # the plugin's host fixes (offline LPIPS, checkpoint types)

    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
    fcfg = cfg.fuse
    fcfg.load_config = cfg.load_config
    fcfg.output_dir = cfg.output_dir
    fcfg.data = cfg.data
    summary_path = cfg.output_dir / fcfg.experiment_name / "nerfacto" / (fcfg.timestamp + ".fuse.json")
    found = sorted(cfg.output_dir.glob(f"{fcfg.experiment_name}/*/{fcfg.timestamp}.fuse.json"))
    if cfg.reuse and found:
        summary = json.loads(found[0].read_text())
    else:
        summary = fuse(fcfg)
    del summary_path
    fused_config = Path(summary["fused_config"])
    res: Dict[str, Any] = {
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(fcfg).items() if k != "losses"},
        "loss_weights": asdict(fcfg.losses),
        "fuse": {k: v for k, v in summary.items() if k not in ("log", "config")},
        "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, torch threads {torch.get_num_threads()}",
        "command": "python -m gsticker_plugin.bench.fuse " + " ".join(sys.argv[1:]),
        "log": summary.get("log"),
    }
    res["verify"] = {
        "fused": verify(fused_config, cfg.key, cfg.output_dir / "verify-fused", cfg.num_views, cfg.data, cfg.reuse)
    }
    if cfg.verify_watermarked:
        res["verify"]["watermarked"] = verify(
            cfg.load_config, cfg.key, cfg.output_dir / "verify-watermarked", cfg.num_views, cfg.data, cfg.reuse
        )
    res["psnr"] = psnr_table(cfg.load_config, fused_config, cfg.data, cfg.psnr_views)
    res["conclusion"] = conclusion(res)
    write_doc(res, cfg.doc)
    print(res["conclusion"])
    return res


def entrypoint() -> None:
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    main(tyro.cli(BenchFuseConfig))


if __name__ == "__main__":
    entrypoint()
