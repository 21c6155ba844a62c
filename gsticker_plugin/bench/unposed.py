"""Images alone: the informed image decoder on held-out orbit renders whose cameras it has to find.

    python -m gsticker_plugin.bench.unposed --load-config RUN/config.yml --key RUN.gskey --data ../shared/data/lego100

Draws ``--num-views`` orbit cameras with ``--camera-seed`` (like the pool's novel views, never used in training),
renders the watermarked run (sticker on) and its base (sticker off) there, rounds them to 8 bits, applies each row's
image attack, and decodes every image without its camera (:func:`gsticker_plugin.decoders.unposed.decode_unposed_images`);
random images are decoded too. Writes per-image rows to ``--work-dir/rows.jsonl`` as they finish (a rerun resumes),
then a Markdown page and a JSON beside it (:mod:`gsticker_plugin.evaluation.unposed_page`).
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch
import tyro

from gsticker_plugin import compat, metrics
from gsticker_plugin.attacks.spec import parse_attack_spec
from gsticker_plugin.decoders.pose import PoseSearch
from gsticker_plugin.decoders.reference import load_base_reference
from gsticker_plugin.decoders.unposed import decode_unposed_images
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.evaluation.held_out import (
    HELD_OUT_CAMERA_SEED,
    HELD_OUT_VIEWS,
    drawn_spec,
    folder_images,
    held_out_renders,
    leaked_key_renders,
    purified_renders,
    random_noise,
    recolored_renders,
    record_point,
    rotation_error_deg,
    run_renders,
    view_attack,
)
from gsticker_plugin.evaluation.unposed_page import recorded_page, row_count, row_key, write_page
from gsticker_plugin.fastpath import novel_cameras
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.metrics import as_8_bit
from gsticker_plugin.runs import load_run


@dataclass
class BenchUnposedConfig:
    """Decode renders of a watermarked run at held-out orbit cameras without giving the decoder the cameras."""

    load_config: Path
    """The watermarked run's config.yml."""
    key: Path
    """Its owner key."""
    data: Optional[Path] = None
    """The dataset, when the recorded path does not exist from here."""
    base_config: Optional[Path] = None
    """The owner's base config.yml, when the key's recorded one does not exist from here."""
    num_views: int = HELD_OUT_VIEWS
    """Held-out orbit cameras."""
    camera_seed: int = HELD_OUT_CAMERA_SEED
    """Seed of the held-out cameras (the sticker's pool draws its novel views with its own seed)."""
    rows: Tuple[str, ...] = ("marked:", "clean:", "marked:hue=0.5", "marked:jpeg=50@8", "marked:blur=1@8")
    """``IMAGES:ATTACK[@N]`` rows: ``marked`` or ``clean`` renders, ``foreign`` (``--foreign-config``'s), ``random``
    images, renders of the watermarked run recoloured (``palette=blue``: palette entry 0 set to blue;
    ``modelhue=0.5``: a model-level hue turn) or of another run (``run=PATH/config.yml``, e.g. the watermarked run
    after ``ns-recolor finetune``), of the watermarked run purified (``purify=STEPS``: every parameter fine-tuned on
    the clean training images, as the evaluation's purify stage), the marked renders blended toward the clean ones
    by a share (``leak=0.5``: what a holder of the owner's base can do) or attacked by projected gradient descent
    on the informed decoder at a PSNR budget (``pgd=50``: what a holder of the owner key can do), images of another scene in a folder
    (``scene=DIR``, composited on white, sorted by name: a null), an attack spec (``noise=0.1,jpeg=50``; empty:
    none; ``hue=~0.5``: a strength drawn per view from [-0.5, 0.5]), the first ``N`` views only (rows that differ only
    in ``N`` share their images: ``marked:@12`` early, ``marked:@24`` later)."""
    other_keys: int = 64
    """Other owners' random messages, each checked against one marked image's bits, the images in turn (their own row:
    a check of the messages, not part of the null of unmarked images; the largest match over every image and key is
    reported beside it)."""
    development_views: int = 0
    """The first N held-out views were looked at while the decoder's rules or the sticker's recipe were chosen: the
    page names the rows that read only them as development evidence."""
    foreign_config: Optional[Path] = None
    """Another model of the scene (config.yml) rendered for ``foreign:`` rows, e.g. a TensoRF base: a null."""
    rolls: Tuple[float, ...] = (0.0,)
    """Turns (degrees) the camera search tries with every candidate (:class:`gsticker_plugin.decoders.pose.PoseSearch`)
    on rows whose attack rotates; other rows search without turns. Recorded per image."""
    random_images: int = 8
    """Random images decoded as a null (:func:`gsticker_plugin.views.random_views`)."""
    crop_cover: bool = True
    """``crop=`` attacks paste the clean render of the same camera into their rectangle (the paper's cropout, and the
    evaluation protocol's); off: a white rectangle (what a recipient without the owner's base can paint). Recorded
    per image."""
    purify_lr: float = 1e-3
    """Adam learning rate of ``purify=`` rows (the evaluation's ``geometry.purify_lr``)."""
    purify_rays_per_step: int = 1024
    """Rays per step of ``purify=`` rows."""
    geometric_views: int = 8
    """Cameras of the base run the informed geometric decoder reads every ``purify=`` model at (beside the images)."""
    seed: int = 0
    page_only: bool = False
    """Write the page from the images already decoded in ``--work-dir`` (rows not reached are left out), decode
    nothing; the held-out views' PSNR comes from the work dir, else from the page's own JSON, else a render. Without
    the work dir's rows, the page is rewritten from its own JSON alone (no run, key or data read)."""
    work_dir: Path = Path("outputs/bench-unposed")
    output: Path = Path("docs/experiments/bench-unposed.md")
    """The page; its JSON goes beside it."""


def page_from_json(cfg: BenchUnposedConfig) -> Dict[str, Any]:
    """The page rewritten from its own JSON: the images it recorded, its threshold and PSNR."""
    recorded = recorded_page(cfg.output.with_suffix(".json"))
    if not recorded:
        raise GStickerError(
            f"--page-only: neither {cfg.work_dir / 'rows.jsonl'} nor {cfg.output.with_suffix('.json')} exists"
        )
    done = {(row_key(r["row"]), r["view"]): r for r in recorded["per_image"]}
    num_bits = len(next(r["bits"] for r in recorded["per_image"] if "bits" in r))
    return write_page(cfg, num_bits, done, int(recorded["threshold"]), recorded["psnr_marked_vs_clean_db"])


def main(cfg: BenchUnposedConfig) -> Dict[str, Any]:
    compat.apply()
    warnings.filterwarnings("ignore")  # nerfstudio 1.1.5's camera indexing warns on every render with this torch
    if cfg.page_only and not (cfg.work_dir / "rows.jsonl").exists():
        return page_from_json(cfg)
    device = torch.device("cpu")
    key = OwnerKey.load(cfg.key)
    with contextlib.redirect_stdout(sys.stderr):
        _, pipe, _ = load_run(cfg.load_config, data=cfg.data, device=device)
        ref = load_base_reference(key, cfg.key, cfg.base_config, cfg.data, device)
    train = pipe.datamanager.train_dataset.cameras
    cams = novel_cameras(train, cfg.num_views, torch.Generator().manual_seed(cfg.camera_seed))
    threshold = metrics.min_matches_for_fpr(key.num_bits, 1e-6)
    cfg.work_dir.mkdir(parents=True, exist_ok=True)
    rows_path = cfg.work_dir / "rows.jsonl"
    done = {}
    if rows_path.exists():
        for line in rows_path.read_text().splitlines():
            r = json.loads(line)
            done[(row_key(r["row"]), r["view"])] = r
    psnr_path = cfg.work_dir / "psnr.json"
    if cfg.page_only and psnr_path.exists():
        per_view = json.loads(psnr_path.read_text())["per_view_db"]
        return write_page(
            cfg, key.num_bits, done, threshold, {"mean": sum(per_view) / len(per_view), "min": min(per_view)}
        )
    recorded = recorded_page(cfg.output.with_suffix(".json")).get("psnr_marked_vs_clean_db") if cfg.page_only else None
    if recorded is not None:  # the page's own record: the run may have changed since
        return write_page(cfg, key.num_bits, done, threshold, recorded)
    t0 = time.time()
    marked, clean = held_out_renders(pipe, cams)
    per_view = metrics.psnr(marked.permute(0, 3, 1, 2), clean.permute(0, 3, 1, 2))
    psnr = {"mean": float(per_view.mean()), "min": float(per_view.min())}
    psnr_path.write_text(json.dumps({"per_view_db": [float(v) for v in per_view]}))
    print(
        f"rendered {cfg.num_views} held-out views in {time.time() - t0:.0f} s; PSNR marked vs clean {psnr['mean']:.2f} dB"
    )
    if cfg.page_only:
        return write_page(cfg, key.num_bits, done, threshold, psnr)
    jobs: List[Tuple[str, int, torch.Tensor, str]] = []
    for row in cfg.rows:
        which, _, spec = row.partition(":")
        spec = spec.partition("@")[0]
        parse_attack_spec(drawn_spec(spec, torch.Generator().manual_seed(0)))
        n = row_count(cfg, row)
        if all((row_key(row), i) in done for i in range(n)):  # decoded already: no renders needed
            continue
        if which in ("marked", "clean"):
            src = marked if which == "marked" else clean
        elif which == "random":
            src = torch.stack([v.image.permute(1, 2, 0) for v in random_noise(n, int(marked.shape[1]), cfg.seed)])
        elif which == "foreign":
            src = run_renders(cfg, cfg.foreign_config, cams[:n])
        elif which.startswith("run="):
            src = run_renders(cfg, Path(which[len("run=") :]), cams[:n])
        elif which.startswith("purify="):
            src = purified_renders(cfg, key, ref, int(which[len("purify=") :]), cams[:n], marked[:n], clean[:n])
        elif which.startswith("leak="):
            t = float(which[len("leak=") :])
            src = as_8_bit(marked[:n] * (1 - t) + clean[:n] * t)
            record_point(cfg.work_dir / "leak.json", str(t), src, marked[:n], clean[:n])
        elif which.startswith("pgd="):
            src = leaked_key_renders(
                key, ref, float(which[len("pgd=") :]), cams[:n], marked[:n], clean[:n], cfg.work_dir
            )
        elif which.startswith("scene="):
            src = folder_images(Path(which[len("scene=") :]), n, (int(marked.shape[1]), int(marked.shape[2])))
        else:
            src = recolored_renders(cfg, which, cams[:n])
        at_cameras = which != "random" and not which.startswith("scene=")
        for i in range(n):
            img = src[i].float()
            drawn = ""
            if spec:
                img, drawn = view_attack(img, spec, i, clean[i] if at_cameras and cfg.crop_cover else None, cfg.seed)
            jobs.append((row, i, img, drawn))
    for i, v in enumerate(random_noise(cfg.random_images, int(marked.shape[1]), cfg.seed)):
        jobs.append(("random:", i, as_8_bit(v.image.permute(1, 2, 0)), ""))
    search_cache: Dict[Tuple[int, int], Any] = {}  # the candidates' renders, made once for all images
    for row, i, img, drawn in jobs:
        if (row_key(row), i) in done:
            continue
        rolls = cfg.rolls if "rotate" in row else (0.0,)
        dec = decode_unposed_images(
            key, ref, [img], cfg.seed, search=PoseSearch(rolls=rolls), names=[f"{row}{i}"], renders=search_cache
        )
        d = dec["image"][0]
        r = {
            "row": row,
            "view": i,
            "matches": int(dec["matches"][0]),
            "bits": "".join(str(int(b)) if int(b) in (0, 1) else "?" for b in dec["bits"][0].tolist()),
            "signals": d["signals"],
            "explained": d["explained"],
            "pose_rms": d["pose_rms"],
            "seconds": d["seconds"],
            "rolls": list(rolls),
            "color_map": bool(d.get("color_map", False)),
            "map_share_at_search": d.get("map_share_at_search"),
            "degradation": d.get("degradation", "none"),
            "covered_share": d.get("covered_share", 0.0),
            "attack": drawn,
            "crop_fill": ("clean render" if cfg.crop_cover else "white") if "crop" in drawn else None,
        }
        if not row.startswith("random"):
            c2w = torch.tensor(d["c2w"])
            true = cams.camera_to_worlds[i].float()
            r["rotation_error_deg"] = rotation_error_deg(true[:, :3], c2w[:, :3])
            r["translation_error"] = float((true[:, 3] - c2w[:, 3]).norm())
        done[(row_key(row), i)] = r
        with rows_path.open("a") as f:
            f.write(json.dumps(r) + "\n")
        print(r, flush=True)
    return write_page(cfg, key.num_bits, done, threshold, psnr)


if __name__ == "__main__":
    main(tyro.cli(BenchUnposedConfig))
