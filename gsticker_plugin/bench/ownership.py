"""The ownership claim on real data: a sticker with a random secret message, read back, beside distinct nulls.

    python -m gsticker_plugin.bench.ownership \\
        --load-checkpoint ../shared/checkpoints/lego100-nerfacto-small/nerfacto/base/nerfstudio_models/step-000002999.ckpt \\
        --data ../shared/data/lego100 --nulls OTHER_BASE/config.yml ... --output-dir outputs/bench-ownership

Trains the sticker with the defaults a user gets (random secret message; bench.geometry.train_sticker), trains
the null models (``--null-seeds``: the base's preset on its data with other seeds; ``--other-scene``: the preset on
the generated scene), verifies the watermarked run, the owner's unwatermarked base, the null models and every
``--nulls`` run with ``ns-verify-owner --decode geometry`` and the same key, and writes ``results.json`` and ``results.md`` into ``--output-dir`` (``--doc``: also
copies both beside that page). A rerun skips finished stages.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

import tyro

from gsticker_plugin.evaluation.sticker_runs import (
    StickerRunConfig,
    psnr_watermarked_vs_clean,
    train_nulls,
    train_sticker,
)
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.verify import cli as V


@dataclass
class BenchOwnershipConfig(StickerRunConfig):
    """Watermark a base with a random secret message and verify it beside distinct unwatermarked models."""

    output_dir: Path = Path("outputs/bench-ownership")
    """Where the run, its key, the reports and the results are written."""
    steps: int = 300
    """Sticker training steps."""
    nulls: List[Path] = field(default_factory=list)
    """config.yml of unwatermarked models to verify with the owner's key (other seeds of the base, other scenes)."""
    null_seeds: List[int] = field(default_factory=lambda: [1, 2])
    """Train the base's preset (--null-preset) on --data with these seeds as null models of the same scene."""
    other_scene: bool = True
    """Train the preset on the generated scene (ns-gsticker-scene) as a null model of another scene."""
    null_preset: str = "gsticker-nerfacto-small"
    """Method of the trained null models."""
    null_steps: int = 700
    """Training steps of each trained null model (a null needs an independent model, not a good one)."""
    null_data: List[Path] = field(default_factory=list)
    """Dataset folder of each --nulls run, in the same order, when its recorded one does not exist from here."""
    num_views: int = 12
    """Views per ns-verify-owner run."""
    fpr: float = 1e-6
    """Per-view false-positive rate of the verdicts."""
    doc: Optional[Path] = None
    """Also write the results page here (and its JSON beside it, same stem)."""
    more_messages: int = 0
    """Also watermark the base with this many more random secret messages (same settings, one sticker run each) and
    read each back: how the watermarked bit accuracy spreads over messages."""


def verify_run(
    cfg: BenchOwnershipConfig, name: str, config: Path, key: Path, out: Path, data: Optional[Path]
) -> Dict[str, Any]:
    """``ns-verify-owner --decode geometry`` of one run (in this process); its report's numbers."""
    report_dir = out / "reports" / name
    if not (report_dir / "report.json").is_file():
        argv = [
            "--load-config",
            str(config),
            "--key",
            str(key),
            "--decode",
            "geometry",
            "--num-views",
            str(cfg.num_views),
            "--fpr",
            str(cfg.fpr),
            "--output",
            str(report_dir),
            "--no-progress",
        ]
        if data is not None:
            argv += ["--data", str(data)]
        if cfg.data is not None:
            argv += ["--base-data", str(Path(cfg.data).resolve())]
        t0 = time.time()
        status = V.main(argv)
        if status == V.EXIT_ERROR:
            raise SystemExit(f"ns-verify-owner failed on {name} ({config}); see the error above")
        (report_dir / "seconds.txt").write_text(f"{time.time() - t0:.1f}")
    rep = json.loads((report_dir / "report.json").read_text())
    (r,) = rep["keys"]
    matches = [v["matches"] for v in r["per_view"]]
    return {
        "name": name,
        "config": str(config),
        "verdict": r["verdict"],
        "views": r["views"],
        "views_passing": r["views_passing"],
        "matches": matches,
        "bit_accuracy": r["mean_bit_accuracy"],
        "threshold": r["thresholds"]["used"],
        "model_pvalue": r["model_pvalue"],
        "undetermined_mean": sum(v["decoded"].count("?") for v in r["per_view"]) / max(1, len(matches)),
        "null_caveats": r.get("null_caveats", []),
        "seconds": float((report_dir / "seconds.txt").read_text()),
    }


def page(res: Dict[str, Any]) -> str:
    wm = res["watermarked"]
    lines = [
        "# Ownership on lego100: a random secret message, and distinct unwatermarked models",
        "",
        f"`{res['command']}` ({res['date']}). Numbers: `{res['json_name']}` beside this page.",
        "",
        f"Sticker: {res['config']['steps']} steps on `{res['config']['load_checkpoint']}`, message drawn with "
        f"`secrets` (key `message_source`: **{res['key']['message_source']}**, null caveats: "
        f"{', '.join(res['key']['null_caveats']) or 'none'}); PSNR watermarked vs unwatermarked render "
        f"{res['psnr']['vs_clean']:.1f} dB, test PSNR {res['psnr']['marked_vs_gt']:.2f} dB (base "
        f"{res['psnr']['clean_vs_gt']:.2f} dB). Geometric decoder, {res['config']['num_views']} views per model, "
        f"per-view FPR {res['config']['fpr']:g} (>= {wm['threshold']}/48 matches).",
        "",
        "| model | watermarked | verdict | views passing | matches min / median / max | bit accuracy | undetermined bits / view | seconds |",
        "|---|---|---|---|---|---|---|---|",
    ]
    marked = [wm, *res.get("more_messages", [])]
    for row in [*marked, *res["nulls"]]:
        m = sorted(row["matches"])
        lines.append(
            f"| {row['name']} | {'yes' if any(row is x for x in marked) else 'no'} | {row['verdict'].upper()} | "
            f"{row['views_passing']}/{row['views']} | {m[0]} / {m[len(m) // 2]} / {m[-1]} | "
            f"{100 * row['bit_accuracy']:.2f} % | {row['undetermined_mean']:.1f} | {row['seconds']:.0f} |"
        )
    n = res["distinct_null_models"]
    if len(marked) > 1:
        accs = [100 * r["bit_accuracy"] for r in marked]
        lines += [
            "",
            f"{len(marked)} random secret messages, each its own sticker run: watermarked bit accuracy "
            f"{min(accs):.2f} % to {max(accs):.2f} % (mean {sum(accs) / len(accs):.2f} %), lowest view "
            f"{min(min(r['matches']) for r in marked)}/48.",
        ]
    lines += [
        "",
        f"{n} distinct unwatermarked models, {res['null_views']} null views: "
        f"{res['null_views_passing']} pass; largest null count {res['null_max_matches']}/48. Undetermined bits "
        "count as mismatches (a model the sticker does not change reads 0/48).",
    ]
    return "\n".join(lines) + "\n"


def main(cfg: BenchOwnershipConfig) -> Dict[str, Any]:
    out, logs, data, base_ckpt, base_config = cfg.layout()
    if len(cfg.null_data) not in (0, len(cfg.nulls)):
        raise SystemExit("--null-data needs one folder per --nulls run (or none)")
    print("[1/4] null models", flush=True)
    trained_nulls = train_nulls(cfg, out, logs)
    print("[2/4] ns-train geometrysticker (random secret message)", flush=True)
    trained = train_sticker(cfg, out, base_ckpt, data, logs)
    wm = out / "bench" / "geometrysticker" / "watermarked"
    key_path = wm.with_name("watermarked.gskey")
    key = OwnerKey.load(key_path)
    res: Dict[str, Any] = {
        "command": "python -m gsticker_plugin.bench.ownership "
        + " ".join(
            [f"--load-checkpoint {cfg.load_checkpoint}"]
            + ([f"--data {cfg.data}"] if cfg.data else [])
            + [f"--steps {cfg.steps} --null-steps {cfg.null_steps} --num-views {cfg.num_views}"]
            + ([f"--more-messages {cfg.more_messages}"] if cfg.more_messages else [])
            + ([f"--nulls {' '.join(map(str, cfg.nulls))}"] if cfg.nulls else [])
            + ([f"--doc {cfg.doc}"] if cfg.doc else [])
        ),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "config": {
            k: (str(v) if isinstance(v, Path) else [str(x) for x in v] if isinstance(v, list) else v)
            for k, v in vars(cfg).items()
        },
        "train": trained,
        "key": {"message_source": key.message_source, "null_caveats": key.null_caveats()},
    }
    print("[3/4] PSNR of the watermarked render", flush=True)
    res["psnr"] = psnr_watermarked_vs_clean(wm / "config.yml", cfg.num_views)
    print("[4/4] ns-verify-owner --decode geometry", flush=True)
    res["watermarked"] = verify_run(cfg, "watermarked run", wm / "config.yml", key_path, out, None)
    nulls = [verify_run(cfg, "owner's base (unwatermarked)", base_config, key_path, out, None)]
    for n in trained_nulls:
        nulls.append(verify_run(cfg, n["name"], n["config"], key_path, out, n["data"]))
    for i, c in enumerate(cfg.nulls):
        d = cfg.null_data[i] if cfg.null_data else None
        nulls.append(
            verify_run(cfg, f"null {i + 1}: {Path(c).parent.parent.parent.name}", Path(c).resolve(), key_path, out, d)
        )
    more = []
    for i in range(1, cfg.more_messages + 1):
        print(f"[4/4] message {i + 1}: ns-train geometrysticker, ns-verify-owner", flush=True)
        sub = out / f"message-{i + 1}"
        sub_logs = sub / "logs"
        sub_logs.mkdir(parents=True, exist_ok=True)
        train_sticker(cfg, sub, base_ckpt, data, sub_logs)
        sub_wm = sub / "bench" / "geometrysticker" / "watermarked"
        sub_key = sub_wm.with_name("watermarked.gskey")
        row = verify_run(cfg, f"watermarked run, message {i + 1}", sub_wm / "config.yml", sub_key, out, None)
        more.append({**row, "message_source": OwnerKey.load(sub_key).message_source})
    res["more_messages"] = more
    res["nulls"] = nulls
    res["distinct_null_models"] = len({n["config"] for n in nulls})
    res["null_views"] = sum(n["views"] for n in nulls)
    res["null_views_passing"] = sum(n["views_passing"] for n in nulls)
    res["null_max_matches"] = max(max(n["matches"]) for n in nulls)
    targets = [out / "results.md"] + ([Path(cfg.doc)] if cfg.doc is not None else [])
    for md in targets:
        res["json_name"] = md.with_suffix(".json").name
        md.parent.mkdir(parents=True, exist_ok=True)
        md.with_suffix(".json").write_text(json.dumps(res, indent=2))
        md.write_text(page(res))
    print(page(res))
    return res


def entrypoint() -> None:
    main(tyro.cli(BenchOwnershipConfig))


if __name__ == "__main__":
    entrypoint()
