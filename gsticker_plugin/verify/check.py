"""``ns-verify-owner [verify]``: render or read the suspect's views, decode them with each key, give the verdict."""

from __future__ import annotations

import contextlib
import sys
import time
import warnings
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import torch

from gsticker_plugin.attacks import parse_attack_spec
from gsticker_plugin.cameras import read_cameras_file, same_aspect
from gsticker_plugin.decoders import fieldimage as field_images
from gsticker_plugin.decoders import fieldmark as field_decoder
from gsticker_plugin.decoders.blind import decode_views
from gsticker_plugin.decoders.geometric import decode_suspect
from gsticker_plugin.decoders.image import (
    base_pose_map,
    decode_images_at_cameras,
    posed_views,
)
from gsticker_plugin.decoders.pose import PoseSearch
from gsticker_plugin.decoders.reference import (
    load_base_reference,
    missing_geometry_message,
    recorded_base_config,
)
from gsticker_plugin.decoders.result import Decoded
from gsticker_plugin.decoders.unposed import decode_unposed_images
from gsticker_plugin.decoders.viewbank import bank_folder
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.key import KEY_SUFFIX, OwnerKey, commitment, signature_valid
from gsticker_plugin.runs import load_run, pick_device
from gsticker_plugin.verify.configs import EXIT_NOT_SHOWN, EXIT_OWNED, VerifyConfig
from gsticker_plugin.verify.report import write_figure, write_json
from gsticker_plugin.verify.results import Commitment, DecoderInfo, KeyResult, Report
from gsticker_plugin.verify.stats import correct_keys, key_result
from gsticker_plugin.views import (
    Views,
    apply_attack,
    images_views,
    model_views,
    progress_bar,
)

DecoderRun = Tuple[List[KeyResult], Views, DecoderInfo]
"""A decoder's run over every key: per-key results, the views it read, the report's decoder entry."""


def _load_keys(key: Optional[Path], keys: Optional[Path], allow_legacy: bool = False) -> List[Tuple[Path, OwnerKey]]:
    if key is not None and keys is not None:
        raise GStickerError("pass either --key KEY.gskey or --keys DIR, not both")
    if key is None and keys is None:
        raise GStickerError("no owner key given; pass --key KEY.gskey (or --keys DIR of keys)")
    if key is not None:
        paths = [Path(key)]
    else:
        d = Path(keys)
        if not d.is_dir():
            raise GStickerError(f"--keys {d} is not a folder; pass a folder of {KEY_SUFFIX} files or use --key")
        paths = sorted(d.glob(f"*{KEY_SUFFIX}"))
        if not paths:
            raise GStickerError(f"--keys {d} holds no *{KEY_SUFFIX} files; pass the folder of owner keys")
    return [(p, OwnerKey.load(p, allow_legacy=allow_legacy)) for p in paths]


def _check_stats(fpr: float, min_share: float) -> None:
    if not 0.0 < fpr < 0.5:
        raise GStickerError(f"--fpr must be in (0, 0.5), got {fpr}; e.g. 1e-6")
    if not 0.0 < min_share <= 1.0:
        raise GStickerError(f"--min-share must be in (0, 1], got {min_share}")


def choose_decoder(config: VerifyConfig, keys: List[Tuple[Path, OwnerKey]]) -> Tuple[str, List[str]]:
    """``--decode``: geometry or extractor, and why (auto); one-line errors for impossible choices."""
    if config.cameras is not None and config.images is None:
        raise GStickerError(
            "--cameras gives the cameras of --images; a model (--load-config) is rendered at its own "
            "cameras: drop --cameras"
        )
    marked = [p for p, k in keys if k.field_mark]
    if marked:
        return choose_field_decoder(config, marked, len(keys))
    if config.decode in ("geometry", "image"):
        if config.decode == "geometry" and config.load_config is None:
            raise GStickerError(
                "--decode geometry reads a model's geometry, not images: pass --load-config "
                "SUSPECT/config.yml, or use --decode image --cameras CAMERAS.json with --images"
            )
        if config.decode == "image" and config.images is None:
            raise GStickerError(
                "--decode image reads images: pass --images DIR (with --cameras transforms.json when their cameras "
                "are known; for a model use --decode geometry)"
            )
        for path, key in keys:
            if not key.geometry:
                raise GStickerError(missing_geometry_message(path))
        return config.decode, []
    if config.decode == "extractor":
        return "extractor", []
    kind, what = ("geometry", "geometric") if config.load_config is not None else ("image", "image")
    for path, key in keys:
        if not key.geometry:
            return "extractor", [
                f"auto: {path} has no geometry reference (version-1 key), so the extractor decodes; "
                "add it with `ns-verify-owner export-key`"
            ]
        cfg = Path(config.base_config) if config.base_config is not None else recorded_base_config(key)
        if cfg is None or not cfg.exists():
            return "extractor", [
                f"auto: the owner's base run {cfg} is not reachable from here, so the extractor "
                f"decodes; pass --base-config BASE_RUN/config.yml for {what} decoding"
            ]
    return kind, []


def choose_field_decoder(config: VerifyConfig, marked: List[Path], num_keys: int) -> Tuple[str, List[str]]:
    """Field-mark keys are read by the geometric decoder from a model and by the image decoder from images; one-line
    errors for anything else."""
    if len(marked) != num_keys:
        raise GStickerError(
            f"{marked[0]} is a field-mark key and the others are sticker keys; verify with each kind of key apart"
        )
    kind = "geometry" if config.load_config is not None else "image"
    if config.decode not in ("auto", kind):
        raise GStickerError(
            f"{marked[0]} is a field-mark key, read by the "
            + ("geometric decoder from a model" if kind == "geometry" else "image decoder from images")
            + f": drop --decode {config.decode}"
        )
    return kind, []


def _informed_result(
    key: OwnerKey,
    path: Path,
    dec: Decoded,
    views: Views,
    config: VerifyConfig,
    decoder: str,
    ref,
    notes: List[str],
    bases: List[str],
) -> KeyResult:
    """:func:`key_result` of an informed decoder, with the owner's base run it read against (its notes and path
    are added to ``notes`` and ``bases``)."""
    r = key_result(key, path, dec, views, config.fpr, config.min_share, decoder=decoder)
    r["base"] = {"config": str(ref.config_path), "checkpoint": str(ref.checkpoint), "method": ref.method}
    notes += ref.notes
    bases.append(str(ref.config_path))
    return r


OTHER_SCENE_AGREEMENT = 0.5
"""Below this median :func:`gsticker_plugin.decoders.geometric.scene_agreement` the report says the key was made for
another scene."""


def median_agreement(dec: Decoded) -> float:
    """The median over views of the geometric decoder's scene agreement (views with no surface ray left out; NaN when
    none has one)."""
    vals = sorted(
        g["scene_agreement"]
        for g in dec["geometry"]
        if isinstance(g.get("scene_agreement"), float) and g["scene_agreement"] == g["scene_agreement"]
    )
    return float(vals[len(vals) // 2]) if vals else float("nan")


def _verify_geometry(config: VerifyConfig, keys: List[Tuple[Path, OwnerKey]], device: torch.device) -> DecoderRun:
    """Geometric decoding of the suspect run for every key (each against its own base run)."""

    with contextlib.redirect_stdout(sys.stderr):
        run_cfg, pipeline, ckpt = load_run(config.load_config, data=config.data, device=device)
    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
    model = pipeline.model
    results: List[KeyResult] = []
    views: Optional[Views] = None
    bases: List[str] = []
    notes: List[str] = []
    for path, key in keys:
        dec, vlist, ref = _decode_geometry(config, path, key, model, device)
        kv = Views(
            kind="model",
            source=str(config.load_config),
            views=vlist,
            details={
                "method": run_cfg.method_name,
                "model": type(model).__name__,
                "checkpoint": str(ckpt),
                "sticker": "on" if hasattr(model, "sticker_enabled") else None,
                "own_cameras": sum(1 for v in vlist if not v.name.startswith("sampled/")),
                "sampled_poses": sum(1 for v in vlist if v.name.startswith("sampled/")),
                "cameras_of": f"the owner's base run {ref.config_path}",
            },
        )
        result = _informed_result(key, path, dec, kv, config, "geometry", ref, notes, bases)
        agreement = median_agreement(dec)
        result["scene_agreement"] = agreement if agreement == agreement else None  # NaN: no view had a surface
        if agreement < OTHER_SCENE_AGREEMENT:
            notes.append(
                f"{path} was made for another scene: the suspect's geometry agrees with the key's base at "
                f"{agreement:.0%} of the base's surface pixels (median over views; a model of the same scene "
                f"agrees at most of them); pass the key made for this scene"
            )
        results.append(result)
        views = views or kv
        del ref
    signals = sorted({tuple(g["signals"]) for r in results for g in (v["geometry"] for v in r["per_view"])})
    info: DecoderInfo = {
        "kind": "geometry",
        "informed": True,
        "description": "",
        "notes": notes,
        "bases": bases,
        "signals": [list(s) for s in signals],
    }
    assert views is not None
    return results, views, info


def _decode_geometry(config: VerifyConfig, path: Path, key: OwnerKey, model, device: torch.device):
    """One key's geometric decoding of the suspect ``model``: with its field mark, or its sticker. Returns
    ``(dec, views, reference)``."""
    data = config.base_data or config.data
    if key.field_mark:
        ref = field_decoder.load_field_reference(key, path, config.base_config, data, device)
        decode = field_decoder.decode_suspect
    else:
        ref = load_base_reference(key, path, config.base_config, data, device)
        decode = decode_suspect
    dec, vlist = decode(key, ref, model, config.num_views, config.sampled_share, config.seed, progress=config.progress)
    return dec, vlist, ref


def _verify_images_informed(
    config: VerifyConfig, keys: List[Tuple[Path, OwnerKey]], views: Views, device: torch.device
) -> DecoderRun:
    """The informed image decoder for every key (each against its own base run): on the images that have a camera in
    --cameras, or, without it, on every image of the base's aspect ratio at a camera found against the base."""

    frames = read_cameras_file(config.cameras) if config.cameras is not None else None
    results: List[KeyResult] = []
    used: Optional[Views] = None
    bases: List[str] = []
    notes: List[str] = []
    for path, key in keys:
        if key.field_mark:
            posed, dec, ref = _field_images(config, path, key, views, frames, device)
            results.append(_informed_result(key, path, dec, posed, config, "image", ref, notes, bases))
            used = used or posed
            continue
        ref = load_base_reference(key, path, config.base_config, config.base_data or config.data, device)
        if frames is not None:
            posed, dec = decode_images_at_cameras(key, ref, views, frames, config.seed, config.progress)
            posed.details["cameras_of"] = str(config.cameras)
        else:
            posed = same_aspect_views(views, ref.pipeline.datamanager.train_dataset.cameras)
            with contextlib.redirect_stdout(sys.stderr):
                dec = decode_unposed_images(
                    key,
                    ref,
                    [v.image.permute(1, 2, 0) for v in posed.views],
                    config.seed,
                    progress=config.progress,
                    names=[v.name for v in posed.views],
                    search=PoseSearch(rolls=tuple(config.rolls)),
                    bank=bank_folder(path) if config.view_bank else None,
                )
            posed.details["cameras_of"] = "found by a camera search against the owner's base"
        results.append(_informed_result(key, path, dec, posed, config, "image", ref, notes, bases))
        used = used or posed
        del ref
    info: DecoderInfo = {
        "kind": "image",
        "informed": True,
        "description": "",
        "notes": notes,
        "bases": bases,
        "cameras": str(config.cameras) if config.cameras is not None else "estimated",
    }
    assert used is not None
    return results, used, info


def _field_images(config: VerifyConfig, path: Path, key: OwnerKey, views: Views, frames, device: torch.device):
    """One field-mark key's image decoding: at the cameras in --cameras, or at cameras found against the base (with
    their framing for images of another aspect ratio). Returns ``(views read, dec, reference)``."""
    ref = field_decoder.load_field_reference(key, path, config.base_config, config.base_data or config.data, device)
    if frames is not None:
        posed, cams = posed_views(views, frames, base_pose_map(ref))
        cameras = [c for _, c in cams]
        posed.details["cameras_of"] = str(config.cameras)
    else:
        posed, cameras = views, None  # any size and aspect ratio: framed pictures are searched with their framing
        posed.details["cameras_of"] = "found by a camera search against the owner's base"
    with contextlib.redirect_stdout(sys.stderr):
        dec = field_images.decode_images(
            key,
            ref,
            [v.image.permute(1, 2, 0) for v in posed.views],
            config.seed,
            cameras=cameras,
            search=PoseSearch(rolls=tuple(config.rolls)),
            names=[v.name for v in posed.views],
            bank=bank_folder(path) if config.view_bank and cameras is None else None,
            progress=config.progress,
        )
    return posed, dec, ref


def same_aspect_views(views: Views, cameras) -> Views:
    """The images with the aspect ratio of the base's cameras (the camera search scales their intrinsics); the others
    are added to ``skipped`` with the fix."""
    w0, h0 = float(cameras.width[0]), float(cameras.height[0])
    out = Views(kind=views.kind, source=views.source, skipped=list(views.skipped), details=dict(views.details))
    for v in views.views:
        h, w = v.image.shape[-2:]
        if not same_aspect(w, h, w0, h0):
            out.skipped.append(
                {
                    "name": v.name,
                    "reason": f"{w}x{h} px, not the aspect ratio of the base's {int(w0)}x{int(h0)} cameras: crop or "
                    "pad it back to the base's frame, or pass --cameras",
                }
            )
        else:
            out.views.append(v)
    if not out.views:
        raise GStickerError(
            f"none of the {len(views.views)} images has the aspect ratio of the base's {int(w0)}x{int(h0)} cameras; "
            "crop or pad them back to the base's frame, or pass --cameras"
        )
    return out


def _check_inputs(config: VerifyConfig) -> None:
    """One-line errors for settings that cannot work, before anything is loaded."""
    _check_stats(config.fpr, config.min_share)
    if (config.load_config is None) == (config.images is None):
        raise GStickerError("pass exactly one input: --load-config RUN/config.yml or --images DIR")
    if config.max_side < config.min_side or config.min_side < 1:
        raise GStickerError(f"need 1 <= --min-side <= --max-side, got {config.min_side} and {config.max_side}")
    if config.attack.strip():  # fail early on a bad spec, before rendering
        try:
            parse_attack_spec(config.attack)
        except ValueError as e:
            raise GStickerError(f"--attack: {e}") from None


def _mark_name(keys: List[Tuple[Path, OwnerKey]]) -> str:
    return "field mark" if any(k.field_mark for _, k in keys) else "sticker"


def _run_geometry(config: VerifyConfig, keys: List[Tuple[Path, OwnerKey]], device: torch.device) -> DecoderRun:
    """The geometric decoder on the suspect model: ``(results, views, decoder info)``."""
    results, views, info = _verify_geometry(config, keys, device)
    if config.attack.strip():
        info["notes"].append(
            f"--attack {config.attack!r} not applied: attacks are image-level distortions, and the "
            "geometric decoder reads the model's geometry, not images"
        )
    signals = " + ".join(sorted({n.replace("_", " ") for sig in info.get("signals", []) for n in sig}))
    info["description"] = (
        f"informed: fits the key's {_mark_name(keys)} to the suspect's geometry ({signals}) against the owner's "
        "unwatermarked base run; model-level only"
    )
    return results, views, info


def _run_images(config: VerifyConfig, keys: List[Tuple[Path, OwnerKey]], device: torch.device) -> DecoderRun:
    """The informed image decoder on --images: ``(results, views, decoder info)``."""
    views = images_views(config.images, config.max_side, config.min_side, config.max_pixels, config.progress)
    apply_attack(views, config.attack, config.seed)
    results, views, info = _verify_images_informed(config, keys, views, device)
    cameras = (
        "--cameras" if config.cameras is not None else "found against the base; its error fitted beside the message"
    )
    info["description"] = (
        f"informed: fits the key's {_mark_name(keys)} to each image's colour change from the owner's unwatermarked "
        f"base rendered at the image's camera ({cameras})"
    )
    return results, views, info


def _run_extractor(config: VerifyConfig, keys: List[Tuple[Path, OwnerKey]], device: torch.device) -> DecoderRun:
    """The blind extractor on a model's renders or on --images: ``(results, views, decoder info)``."""
    leaning = [str(p) for p, k in keys if k.owner_message_prob > 0]
    if leaning:
        raise GStickerError(
            f"{', '.join(leaning)}: its extractor was trained on the owner's message "
            "(--pipeline.owner-message-prob > 0) and decodes it from unmarked images too; its "
            "binomial null does not hold: use --decode geometry or --decode image"
        )
    if config.load_config is not None:
        views = model_views(
            config.load_config,
            config.num_views,
            config.sampled_share,
            config.seed,
            config.data,
            device,
            progress=config.progress,
        )
    else:
        views = images_views(config.images, config.max_side, config.min_side, config.max_pixels, config.progress)
    if not views.views:
        raise GStickerError("no view to decode; nothing to base a verdict on")
    apply_attack(views, config.attack, config.seed)
    results: List[KeyResult] = []
    for path, key in progress_bar(keys, "decoding", config.progress and len(keys) > 1):
        dec = decode_views(key, views, device)
        results.append(key_result(key, path, dec, views, config.fpr, config.min_share))
        # a diagnostic beside the verdict: distribution-free over the random message, not used to decide
        results[-1]["soft_score_pvalue"] = dec["soft_pvalue_pooled"]
    what = "renders" if views.kind == "model" else "images"
    description = f"blind: the key's extractor reads the message from RGB {what}"
    return results, views, {"kind": "extractor", "informed": False, "description": description, "notes": []}


DECODERS: Dict[str, Callable[[VerifyConfig, List[Tuple[Path, OwnerKey]], torch.device], DecoderRun]] = {
    "geometry": _run_geometry,
    "image": _run_images,
    "extractor": _run_extractor,
}
"""Each decoder's run: ``(config, keys, device) -> (per-key results, the views read, the report's decoder entry)``."""


def verify(config: VerifyConfig) -> Tuple[int, Report]:
    """Run ``verify``; returns (exit status, report). Raises GStickerError for bad input."""
    _check_inputs(config)
    keys = _load_keys(config.key, config.keys, config.allow_legacy)
    committed = check_commitment(config.commitment, keys, config.public_key)
    device = pick_device(config.device)
    decoder, notes = choose_decoder(config, keys)
    results, views, decoder_info = DECODERS[decoder](config, keys, device)
    decoder_info["notes"] = notes + decoder_info["notes"]
    report = _report(config, keys, views, results, decoder_info, committed)
    _write_report(config, report, views, keys, results)
    return report["exit_status"], report


def _report(
    config: VerifyConfig,
    keys,
    views: Views,
    results: List[KeyResult],
    decoder_info: DecoderInfo,
    committed: Optional[Commitment],
) -> Report:
    """The report: input, settings, decoder, per-key results and the verdict."""
    owned = [r["owner_id"] for r in results if r["owned"]]
    return {
        "tool": "ns-verify-owner",
        "created": time.time(),
        "input": {
            "kind": views.kind,
            "source": views.source,
            "views": len(views.views),
            "skipped": views.skipped,
            "details": views.details,
        },
        "settings": {
            "fpr": config.fpr,
            "min_share": config.min_share,
            "attack": config.attack,
            "num_views": config.num_views if views.kind == "model" else None,
            "seed": config.seed,
            "correction": config.correction if len(keys) > 1 else None,
        },
        "decoder": decoder_info,
        "commitment": committed,
        "keys": results,
        "multiple_testing": correct_keys(results, config.fpr, config.min_share, config.correction)
        if len(keys) > 1
        else None,
        "verdict": "owned" if owned else "not shown",
        "owned_by": owned,
        "exit_status": EXIT_OWNED if owned else EXIT_NOT_SHOWN,
    }


def _write_report(config: VerifyConfig, report: Report, views: Views, keys, results: List[KeyResult]) -> None:
    """report.json (and report.png) in --output; one-line error when the folder is not writable."""
    out = Path(config.output)
    try:
        out.mkdir(parents=True, exist_ok=True)
        files = [str(out / "report.json")]
        if config.figure:
            best = min(range(len(results)), key=lambda i: results[i]["model_pvalue"])
            write_figure(out / "report.png", report, views, keys[best][1])
            files.append(str(out / "report.png"))
        report["files"] = files
        write_json(out / "report.json", report)
    except OSError as e:
        raise GStickerError(
            f"cannot write the report to {out} ({e.strerror or e}); pass --output with a writable folder"
        ) from None


def _hex_arg(given: str, option: str, what: str) -> str:
    hex_ = given.strip().lower()
    if len(hex_) != 64 or set(hex_) - set("0123456789abcdef"):
        raise GStickerError(f"{option} must be the 64 hex digits of the {what} printed by `ns-verify-owner commit`")
    return hex_


def check_commitment(
    given: Optional[str], keys: List[Tuple[Path, OwnerKey]], public_key: Optional[str] = None
) -> Optional[Commitment]:
    """``--commitment HEX`` (and ``--public-key HEX``) against the one key given: None without them; a mismatch is an
    error. The public key must have signed the key's commitment."""
    if given is None and public_key is None:
        return None
    if len(keys) != 1:
        raise GStickerError("--commitment and --public-key check one key: pass it with --key KEY.gskey, not --keys")
    path, key = keys[0]
    own = commitment(key)
    out: Commitment = {"key": str(path), "matches": True}
    if given is not None:
        hex_ = _hex_arg(given, "--commitment", "commitment")
        if own != hex_:
            raise GStickerError(
                f"{path} does not match the commitment {hex_[:16]}... (its own is {own[:16]}...): this is "
                "not the key that was committed to; pass the committed key"
            )
        out["given"] = hex_
        out["meaning"] = (
            "sha256 over a secret salt and the key's message, sticker, heads and base checksum: the key "
            "existed when this value was published or timestamped"
        )
    if public_key is not None:
        pub = _hex_arg(public_key, "--public-key", "public key")
        if not key.signature:
            raise GStickerError(
                f"{path} carries no signature (written before version 4): --public-key cannot be checked; "
                "verify with --commitment alone"
            )
        if not signature_valid(pub, key.signature, own):
            raise GStickerError(
                f"{path} was not signed by the public key {pub[:16]}...: its commitment's signature does not verify; "
                "this is not that owner's key"
            )
        out["public_key"], out["signed"] = pub, True
    return out
