"""Geometric (informed) decoding on real data: watermark a base briefly, recolor it, verify everything.

    python -m gsticker_plugin.bench.geometry \\
        --load-checkpoint ../shared/checkpoints/lego100-nerfacto-small/nerfacto/base/nerfstudio_models/step-000002999.ckpt \\
        --data ../shared/data/lego100 --output-dir outputs/bench-geometry

Stages (each skipped when its output exists, so a rerun only redoes what is missing), all stock commands run as
subprocesses and printed:

1. ``ns-train geometrysticker`` for ``--steps`` steps on the base (small pool, short warm-up);
2. PSNR of the watermarked vs the unwatermarked render (test views, sticker on/off of the same run);
3. ``ns-recolor palette``, ``ns-recolor hue`` and (``--finetune-steps`` > 0) ``ns-recolor finetune`` of the run;
4. ``ns-verify-owner --decode geometry`` on the watermarked run, the recolored runs and the unwatermarked base
   (and ``--decode extractor`` on the watermarked run, for comparison), timed.

Writes ``results.json`` and ``results.md`` (a table: matches per view, verdict, exit status, wall time) into
``--output-dir``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Dict

import tyro

from gsticker_plugin.evaluation.sticker_runs import StickerRunConfig, psnr_watermarked_vs_clean, run_step, train_sticker
from gsticker_plugin.machine import config_under, console_script, recolor_into


@dataclass
class BenchGeometryConfig(StickerRunConfig):
    """Watermark a base, recolor it, and verify every run with the geometric decoder."""

    num_views: int = 24
    """Views per ns-verify-owner run."""
    finetune_steps: int = 100
    """Steps of the attacker's color-only fine-tune (0: skip it)."""
    extractor: bool = True
    """Also verify the watermarked run with the blind extractor, for comparison."""
    verify: bool = True
    """Run the ns-verify-owner stage (``--no-verify``: only training, PSNR and recolor numbers)."""
    psnr_views: int = 10
    """Test views for the watermarked-vs-clean PSNR."""


def main(cfg: BenchGeometryConfig) -> Dict[str, Any]:
    out, logs, data, base_ckpt, base_config = cfg.layout()
    results: Dict[str, Any] = {"config": {k: str(v) for k, v in vars(cfg).items()}, "stages": {}}
    wm = out / "bench" / "geometrysticker" / "watermarked"
    key = wm.with_name("watermarked.gskey")

    print("[1/4] ns-train geometrysticker", flush=True)
    trained = train_sticker(cfg, out, base_ckpt, data, logs)
    if trained is not None:
        results["stages"]["train"] = trained

    print("[2/4] PSNR watermarked vs clean (test views)", flush=True)
    psnr = psnr_watermarked_vs_clean(wm / "config.yml", cfg.psnr_views)
    results["psnr_watermarked_vs_clean_db"] = psnr["vs_clean"]
    results["psnr_vs_ground_truth_db"] = {"watermarked": psnr["marked_vs_gt"], "unwatermarked": psnr["clean_vs_gt"]}
    print(
        f"    {psnr['vs_clean']:.2f} dB; against ground truth: watermarked {psnr['marked_vs_gt']:.2f} dB, "
        f"unwatermarked {psnr['clean_vs_gt']:.2f} dB",
        flush=True,
    )

    print("[3/4] ns-recolor", flush=True)
    recolors = {"palette": ["palette", "--set", "0=dodger blue", "1=magenta"], "hue": ["hue", "--shift", "0.3"]}
    if cfg.finetune_steps > 0:
        recolors["finetune"] = ["finetune", "--set", "0=dodger blue", "--steps", str(cfg.finetune_steps)]
    suspects = {"watermarked": wm / "config.yml"}
    for name, args in recolors.items():
        dest = out / f"recolor-{name}"
        run = recolor_into(args, wm / "config.yml", dest, logs / f"recolor-{name}.log", what="bench step")
        if run is not None:
            results["stages"][f"recolor-{name}"] = run
        suspects[f"{name}-recolored"] = config_under(dest)
    suspects["unwatermarked base"] = base_config
    results["psnr_recolored_watermarked_vs_clean_db"] = {}
    for name in recolors:
        p = psnr_watermarked_vs_clean(suspects[f"{name}-recolored"], cfg.psnr_views)["vs_clean"]
        results["psnr_recolored_watermarked_vs_clean_db"][name] = p
        print(f"    {name}: recolored watermarked vs the same edit on the unwatermarked model {p:.2f} dB", flush=True)
    if not cfg.verify:
        (out / "results.json").write_text(json.dumps(results, indent=2))
        return results

    print("[4/4] ns-verify-owner", flush=True)
    rows = []
    jobs = [(name, cfgp, "geometry") for name, cfgp in suspects.items()]
    if cfg.extractor:
        jobs.append(("watermarked", suspects["watermarked"], "extractor"))
    for name, cfgp, decoder in jobs:
        rep_dir = out / "verify" / f"{name.replace(' ', '-')}-{decoder}"
        run = run_step(
            [
                console_script("ns-verify-owner"),
                "--load-config",
                str(cfgp),
                "--key",
                str(key),
                "--decode",
                decoder,
                "--num-views",
                str(cfg.num_views),
                "--output",
                str(rep_dir),
                "--no-progress",
                *data,
            ],
            logs / f"verify-{name.replace(' ', '-')}-{decoder}.log",
            ok=(0, 1),
        )
        rep = json.loads((rep_dir / "report.json").read_text())
        (r,) = rep["keys"]
        m = [v["matches"] for v in r["per_view"]]
        row = {
            "suspect": name,
            "decoder": decoder,
            "verdict": rep["verdict"],
            "exit": run["exit"],
            "views_passing": r["views_passing"],
            "views": r["views"],
            "matches": m,
            "matches_min": min(m),
            "matches_median": sorted(m)[len(m) // 2],
            "matches_max": max(m),
            "threshold": r["thresholds"]["used"],
            "model_pvalue": r["model_pvalue"],
            "wall_s": run["wall_s"],
            "command": run["command"],
            "report": str(rep_dir / "report.json"),
        }
        if decoder == "geometry":
            g = [v["geometry"] for v in r["per_view"]]
            row["undetermined_bits_mean"] = sum(x["undetermined"] for x in g) / len(g)
            row["explained_min"] = min(x["explained"] for x in g)
        rows.append(row)
        print(
            f"    {name:>20} [{decoder}]: {rep['verdict']}, matches min/median/max {row['matches_min']}/"
            f"{row['matches_median']}/{row['matches_max']} of 48, {r['views_passing']}/{r['views']} views pass, "
            f"{run['wall_s']:.0f} s",
            flush=True,
        )
    results["verify"] = rows
    (out / "results.json").write_text(json.dumps(results, indent=2))
    lines = [
        "| suspect | decoder | verdict (exit) | views passing | matches min / median / max (of 48) | wall time |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['suspect']} | {row['decoder']} | {row['verdict']} ({row['exit']}) | "
            f"{row['views_passing']}/{row['views']} | {row['matches_min']} / {row['matches_median']} / "
            f"{row['matches_max']} | {row['wall_s']:.0f} s |"
        )
    lines.append("")
    lines.append(f"PSNR watermarked vs clean render (test views): {results['psnr_watermarked_vs_clean_db']:.2f} dB")
    gt = results["psnr_vs_ground_truth_db"]
    lines.append(
        f"PSNR against ground truth (test views): watermarked {gt['watermarked']:.2f} dB, unwatermarked "
        f"{gt['unwatermarked']:.2f} dB"
    )
    for name, p in results["psnr_recolored_watermarked_vs_clean_db"].items():
        lines.append(f"PSNR {name}-recolored watermarked vs the same edit on the unwatermarked model: {p:.2f} dB")
    (out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return results


def entrypoint() -> None:
    main(tyro.cli(BenchGeometryConfig))


if __name__ == "__main__":
    entrypoint()
