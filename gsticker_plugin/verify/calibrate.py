"""``ns-verify-owner calibrate``: measure a key's null on unmarked models and images and store it in the key."""

from __future__ import annotations

import contextlib
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Dict, List

import torch

from gsticker_plugin import metrics
from gsticker_plugin.cameras import read_cameras_file
from gsticker_plugin.decoders.blind import decode_views
from gsticker_plugin.decoders.geometric import decode_suspect
from gsticker_plugin.decoders.image import decode_images_at_cameras
from gsticker_plugin.decoders.reference import (
    data_if_missing,
    load_base_reference,
    missing_geometry_message,
)
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.runs import load_run, pick_device
from gsticker_plugin.verify.configs import CalibrateConfig
from gsticker_plugin.verify.stats import NULL_FORMAT_VERSION, decoder_null
from gsticker_plugin.views import Views, images_views, model_views, random_views


def calibrate(config: CalibrateConfig) -> Dict[str, Any]:
    """Run ``calibrate``: decode unmarked views with the key and store their match counts in the key."""
    key_path = Path(config.key)
    key = OwnerKey.load(key_path, allow_legacy=config.allow_legacy)
    if key.field_mark:
        raise GStickerError(
            f"{key_path} is a field-mark key: calibrate measures sticker keys' decoders; a field-mark key's null is "
            "the binomial one of its secret uniform message (read unmarked models with ns-verify-owner to see it)"
        )
    device = pick_device(config.device)
    if config.decode == "geometry":
        return _calibrate_geometry(config, key_path, key, device)
    if config.decode == "image":
        return _calibrate_image(config, key_path, key, device)
    sources: List[Views] = []
    notes: List[str] = []

    def unmarked(run_config) -> Views:  # a run's renders with its sticker off (its unmarked base)
        return model_views(
            Path(run_config),
            config.num_views,
            config.sampled_share,
            config.seed,
            None,
            device,
            sticker=False,
            progress=config.progress,
        )

    if config.base:
        base_cfg = (key.base or {}).get("config")
        if base_cfg and Path(base_cfg).is_file():
            sources.append(unmarked(base_cfg))
        else:
            notes.append(
                f"base run skipped: its config {base_cfg!r} recorded in the key does not exist here "
                "(pass it with --load-config, or --no-base)"
            )
    for cfg in config.load_config:
        sources.append(unmarked(cfg))
    for d in config.images:
        sources.append(images_views(Path(d), config.max_side, config.min_side, config.max_pixels, config.progress))
    if config.random_images > 0:
        if config.random_size < config.min_side:
            raise GStickerError(f"--random-size {config.random_size} is below --min-side {config.min_side}")
        sources.append(random_views(config.random_images, config.random_size, config.seed))
    if not any(s.views for s in sources):
        raise GStickerError("no unmarked view to calibrate on; pass --load-config, --images or --random-images N")
    matches: List[int] = []
    src_info = []
    for s in sources:
        if not s.views:
            continue
        dec = decode_views(key, s, device)
        m = [int(x) for x in dec["matches"].tolist()]
        matches += m
        src_info.append(
            {
                "kind": s.kind,
                "source": s.source,
                "n": len(m),
                "mean_matches": sum(m) / len(m),
                "max_matches": max(m),
                "skipped": len(s.skipped),
                **({"details": s.details} if s.details else {}),
            }
        )
    return _store_null(config, key_path, key, "extractor", matches, src_info, notes)


def _store_null(
    config: CalibrateConfig,
    key_path: Path,
    key: OwnerKey,
    decoder: str,
    matches: List[int],
    src_info: List[Dict[str, Any]],
    notes: List[str],
) -> Dict[str, Any]:
    old = decoder_null(key, decoder) if config.append else None
    if old:
        matches = [int(x) for x in old.get("matches", [])] + matches
        src_info = list(old.get("sources", [])) + src_info
    null = {
        "version": NULL_FORMAT_VERSION,
        "num_bits": key.num_bits,
        "matches": matches,
        "sources": src_info,
        "created": time.time(),
        "decoder": decoder,
    }
    if decoder == "geometry":
        key.geometry = {**key.geometry, "null": null}
    elif decoder == "image":
        key.geometry = {**key.geometry, "image_null": null}
    else:
        key.null = null
    backup = None
    if config.backup:
        backup = key_path.with_name(key_path.name + ".bak")
        shutil.copy2(key_path, backup)
    key.save(key_path)
    OwnerKey.load(key_path)  # the rewritten key passes its own integrity check
    k = key.num_bits
    return {
        "key": str(key_path),
        "backup": str(backup) if backup else None,
        "null_views": len(matches),
        "decoder": decoder,
        "sources": src_info,
        "notes": notes,
        **distinct_sources(src_info),
        "mean_matches": sum(matches) / len(matches),
        "max_matches": max(matches),
        "thresholds": {
            f"{a:g}": {
                "theoretical": metrics.min_matches_for_fpr(k, a),
                "empirical": metrics.empirical_threshold(matches, a, k),
            }
            for a in (1e-3, 1e-6, 1e-9)
        },
    }


def distinct_sources(src_info: List[Dict[str, Any]]) -> Dict[str, int]:
    """How many *distinct* unmarked models, image folders and synthetic random images a null holds (views of one
    model are not independent samples of the null)."""

    def count(kind: str) -> int:
        return len({str(Path(x["source"]).resolve()) for x in src_info if x["kind"] == kind})

    return {
        "distinct_models": count("model"),
        "distinct_image_sources": count("images"),
        "synthetic_views": sum(int(x["n"]) for x in src_info if x["kind"] == "random"),
    }


def _calibrate_geometry(config: CalibrateConfig, key_path: Path, key: OwnerKey, device: torch.device) -> Dict[str, Any]:
    """The geometric decoder's null: decode the unwatermarked base itself and the given (unmarked) runs."""

    if not key.geometry:
        raise GStickerError(missing_geometry_message(key_path))
    notes = []
    if config.images or config.random_images:
        notes.append("images skipped: the geometric decoder reads models, not images")
    ref = load_base_reference(key, key_path, config.base_config, config.data, device)
    runs = ([ref.config_path] if config.base else []) + [Path(c) for c in config.load_config]
    if not runs:
        raise GStickerError(
            "no unmarked run to calibrate the geometric decoder on; keep the base (drop --no-base) "
            "or pass --load-config OTHER_RUN/config.yml"
        )
    matches: List[int] = []
    src_info = []
    for i, cfg in enumerate(runs):
        with contextlib.redirect_stdout(sys.stderr):
            run_cfg, pipeline, _ = load_run(cfg, data=data_if_missing(cfg, config.data), device=device)
        dec, _ = decode_suspect(
            key,
            ref,
            pipeline.model,
            config.num_views,
            config.sampled_share,
            config.seed + i,
            sticker=False,
            progress=config.progress,
            full_renders=False,
        )
        m = [int(x) for x in dec["matches"].tolist()]
        matches += m
        details = {
            "method": run_cfg.method_name,
            "sticker": "off",
            "undetermined_bits_mean": sum(g["undetermined"] for g in dec["geometry"]) / len(m),
        }
        src_info.append(null_source("model", cfg, m, 0, details))
    return _store_null(config, key_path, key, "geometry", matches, src_info, notes)


def null_source(kind: str, source: Any, matches: List[int], skipped: int, details: Dict[str, Any]) -> Dict[str, Any]:
    """One source's row in the key's null record: its per-view matches summarised."""
    return {
        "kind": kind,
        "source": str(source),
        "n": len(matches),
        "mean_matches": sum(matches) / len(matches),
        "max_matches": max(matches),
        "skipped": skipped,
        "details": details,
    }


def _calibrate_image(config: CalibrateConfig, key_path: Path, key: OwnerKey, device: torch.device) -> Dict[str, Any]:
    """The image decoder's null: decode unmarked images at their known cameras (--images with --cameras, e.g. the
    base dataset's own photos and its transforms_test.json)."""

    if not key.geometry:
        raise GStickerError(missing_geometry_message(key_path))
    if not config.images or config.cameras is None:
        raise GStickerError(
            "--decode image calibrates on unmarked images at known cameras: pass --images DIR "
            "(e.g. the base dataset's test photos) and --cameras transforms.json"
        )
    notes = []
    if config.load_config:
        notes.append(
            "--load-config runs skipped: the image decoder reads images (render them, e.g. with ns-render "
            "dataset, and pass them with --images)"
        )
    frames = read_cameras_file(config.cameras)
    ref = load_base_reference(key, key_path, config.base_config, config.data, device)
    matches: List[int] = []
    src_info = []
    for d in config.images:
        views = images_views(Path(d), config.max_side, config.min_side, config.max_pixels, config.progress)
        posed, dec = decode_images_at_cameras(key, ref, views, frames, config.seed + len(src_info), config.progress)
        m = [int(x) for x in dec["matches"].tolist()]
        matches += m
        src_info.append(null_source("images", d, m, len(posed.skipped), {"cameras": str(config.cameras)}))
    return _store_null(config, key_path, key, "image", matches, src_info, notes)


def calibrate_text(res: Dict[str, Any]) -> str:
    lines = [
        f"calibrated {res['key']} ({res['decoder']} decoder): {res['null_views']} unmarked views in its null "
        f"(mean {res['mean_matches']:.1f}, max {res['max_matches']} matches; chance mean 24 of 48), from "
        f"{res['distinct_models']} distinct models, {res['distinct_image_sources']} image folders and "
        f"{res['synthetic_views']} synthetic random images"
    ]
    for s in res["sources"]:
        lines.append(
            f"  {s['kind']} {s['source']}: {s['n']} views, mean {s['mean_matches']:.1f}, max {s['max_matches']}"
        )
    for n in res["notes"]:
        lines.append(f"  note: {n}")
    for a, t in res["thresholds"].items():
        lines.append(
            f"  per-view FPR {a}: threshold theoretical {t['theoretical']}, empirical {t['empirical']} "
            f"-> verify uses {max(t['theoretical'], t['empirical'])}"
        )
    if res["backup"]:
        lines.append(f"  previous key kept as {res['backup']}")
    return "\n".join(lines)
