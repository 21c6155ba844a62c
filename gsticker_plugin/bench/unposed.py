"""Images alone: the informed image decoder on held-out orbit renders whose cameras it has to find.

    python -m gsticker_plugin.bench.unposed --load-config RUN/config.yml --key RUN.gskey --data ../shared/data/lego100

Draws ``--num-views`` orbit cameras with ``--camera-seed`` (like the pool's novel views, never used in training),
renders the watermarked run (sticker on) and its base (sticker off) there, rounds them to 8 bits, applies each row's
image attack, and decodes every image without its camera (:func:`gsticker_plugin.decoders.unposed.decode_unposed_images`);
random images are decoded too. Writes per-image rows to ``--work-dir/rows.jsonl`` as they finish (a rerun resumes),
then a Markdown page and a JSON beside it.
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch
import tyro
from jaxtyping import Float
from torch import Tensor

from gsticker_plugin import compat, metrics
from gsticker_plugin.attacks.spec import apply_attacks, parse_attack_spec
from gsticker_plugin.decoders.image import decode_posed_images, image_reference, leaked_key_attack
from gsticker_plugin.decoders.pose import PoseSearch
from gsticker_plugin.decoders.reference import any_reference_view, cpu_sticker, load_base_reference
from gsticker_plugin.decoders.unposed import MAP_SEARCH_SHARE, decode_unposed_images
from gsticker_plugin.evaluate import final_rgb
from gsticker_plugin.fastpath import novel_cameras
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.machine import machine_info
from gsticker_plugin.metrics import as_8_bit
from gsticker_plugin.runs import load_run
from gsticker_plugin.views import random_views


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
    num_views: int = 24
    """Held-out orbit cameras."""
    camera_seed: int = 12345
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
    """Other owners' random messages, each checked against one marked image's bits, the images in turn (a null of
    independent checks; the largest match over every image and key is reported beside it)."""
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
    nothing; the held-out views' PSNR comes from the work dir, else from the page's own JSON, else a render."""
    work_dir: Path = Path("outputs/bench-unposed")
    output: Path = Path("docs/bench-unposed.md")
    """The page; its JSON goes beside it."""


def rotation_error_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """Angle (degrees) between two rotation matrices, accurate near zero (from the skew part)."""
    rel = a.double().T @ b.double()
    skew = torch.stack([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]]) / 2
    cos = (torch.trace(rel) - 1) / 2
    return math.degrees(math.atan2(float(skew.norm()), float(cos)))


def drawn_spec(spec: str, generator: torch.Generator) -> str:
    """``spec`` with every ``name=~v`` replaced by a strength drawn uniformly from [-v, v] (a jitter: ``hue=~0.5``,
    ``rotate=~30``)."""
    items = []
    for item in spec.split(","):
        name, eq, value = item.partition("=")
        if eq and value.strip().startswith("~"):
            v = float(value.strip()[1:])
            value = f"{(2 * float(torch.rand((), generator=generator)) - 1) * v:.6g}"
        items.append(f"{name}{eq}{value}")
    return ",".join(items)


def recolored_renders(cfg: "BenchUnposedConfig", edit: str, cameras) -> torch.Tensor:
    """8-bit renders at ``cameras`` of the watermarked run recoloured in memory as ``ns-recolor`` would:
    ``palette=COLOR`` (palette entry 0 set to COLOR) or ``modelhue=TURNS`` (a model-level hue turn)."""
    from gsticker_plugin.recolor.configs import HUE_METHOD, PALETTE_METHOD, PaletteEdit
    from gsticker_plugin.recolor.edits import edited_palette, extract_palette_of, set_model_palette
    from gsticker_plugin.recolor.palette import to_hex
    from gsticker_plugin.recolor.runs import build_recolor_run

    kind, _, value = edit.partition("=")
    with contextlib.redirect_stdout(sys.stderr):
        _, pipe, _, _, _ = build_recolor_run(
            cfg.load_config, cfg.data, PALETTE_METHOD if kind == "palette" else HUE_METHOD
        )
    model = pipe.model
    if kind == "palette":
        args = PaletteEdit(set_=(f"0={value}",))
        pal = extract_palette_of(args, model, pipe.datamanager.train_dataset, 0)
        model.config.palette_source = [to_hex(c) for c in pal.rgb.tolist()]
        model.config.palette_target = [to_hex(c) for c in edited_palette(args, pal)]
        model.config.softness = float(args.softness)
    elif kind == "modelhue":
        model.config.hue_shift = float(value)
    else:
        raise ValueError(f"unknown images {edit!r}: use marked, clean, palette=COLOR or modelhue=TURNS")
    set_model_palette(model)
    return renders_8_bit(model, cameras)


def run_renders(cfg: "BenchUnposedConfig", config: Optional[Path], cameras) -> torch.Tensor:
    """8-bit renders at ``cameras`` of the run at ``config`` (``--foreign-config``'s for ``foreign:`` rows, another
    model of the scene: a null; a ``run=PATH`` row's, e.g. an ``ns-recolor finetune`` output)."""
    if config is None:
        raise ValueError("a foreign: row needs --foreign-config RUN/config.yml (e.g. a TensoRF base of the scene)")
    if not config.exists():
        raise ValueError(f"no run config at {config}: give run=PATH/config.yml of an existing run")
    with contextlib.redirect_stdout(sys.stderr):
        _, pipe, _ = load_run(config, data=cfg.data, device=torch.device("cpu"))
    return renders_8_bit(pipe.model, cameras)


def purify_steps(rows: Tuple[str, ...]) -> List[int]:
    """The step counts of the ``purify=`` rows, increasing (the purification runs through them cumulatively)."""
    return sorted({int(r.partition(":")[0][len("purify=") :]) for r in rows if r.startswith("purify=")})


def purified_renders(cfg: "BenchUnposedConfig", key, ref, steps: int, cameras, marked, clean) -> torch.Tensor:
    """8-bit renders at ``cameras`` of the watermarked run after ``steps`` steps of purification
    (:func:`gsticker_plugin.recolor.purify.purify`, cumulative through the rows' step counts with the evaluation's
    seeds); the informed geometric decoder's reading of that model and the renders' PSNR go to
    ``--work-dir/purify.json``."""
    from gsticker_plugin.decoders.geometric import decode_suspect
    from gsticker_plugin.recolor.purify import clean_targets, purify

    with contextlib.redirect_stdout(sys.stderr):
        _, pipe, _ = load_run(cfg.load_config, data=cfg.data, device=torch.device("cpu"))
    model, ds = pipe.model, pipe.datamanager.train_dataset
    targets = clean_targets(model, ds)
    done, losses, t0 = 0, [], time.time()
    for s in [v for v in purify_steps(cfg.rows) if v <= steps] or [steps]:
        if s > done:
            losses += purify(
                model, ds.cameras, targets, s - done, cfg.purify_lr, cfg.purify_rays_per_step, seed=done, progress=True
            )
            done = s
    seconds = time.time() - t0
    model.eval()
    src = renders_8_bit(model, cameras)
    with contextlib.redirect_stdout(sys.stderr):
        dec, _ = decode_suspect(key, ref, model, cfg.geometric_views, 0.5, cfg.seed, full_renders=False)
    point = {
        "steps": steps,
        "purify_seconds": round(seconds, 1),
        "loss_last_20": float(sum(losses[-20:]) / len(losses[-20:])) if losses else None,
        "geometric_matches": [int(m) for m in dec["matches"]],
        "geometric_bit_acc": float(torch.tensor(dec["matches"], dtype=torch.float64).mean() / key.num_bits),
    }
    record_point(cfg.work_dir / "purify.json", str(steps), src, marked, clean, **point)
    return src


def leaked_key_renders(key, ref, budget: float, cameras, marked, clean, work_dir: Path) -> torch.Tensor:
    """8-bit: each marked render after the leaked-key PGD at its true camera and a PSNR budget of ``budget`` dB
    (:func:`gsticker_plugin.decoders.image.leaked_key_attack`: what a holder of the owner key and the base can do);
    the informed image decoder's reading at the true cameras and the renders' PSNR go to ``work_dir/pgd.json``."""
    st, bg = cpu_sticker(ref.model), ref.model.background_color()
    views = [(f"pgd/{i}", cameras[i : i + 1]) for i in range(len(marked))]
    out = [
        leaked_key_attack(image_reference(any_reference_view(ref, name, cam, None), bg), st, marked[i].float(), budget)
        for i, (name, cam) in enumerate(views)
    ]
    src = as_8_bit(torch.stack(out))
    with contextlib.redirect_stdout(sys.stderr):
        dec = decode_posed_images(key, ref, [x.float() for x in src], views, 0)
    matches = [int(m) for m in dec["matches"]]
    point = {
        "budget_db": budget,
        "posed_matches": matches,
        "posed_bit_acc": float(torch.tensor(matches, dtype=torch.float64).mean() / key.num_bits),
    }
    record_point(work_dir / "pgd.json", str(budget), src, marked, clean, **point)
    return src


def record_point(path: Path, name: str, images, marked, clean, **extra) -> None:
    """Add ``name``'s mean PSNR vs the marked and the clean renders (and ``extra``) to the JSON at ``path``."""
    as_chw = lambda x: x.permute(0, 3, 1, 2)  # noqa: E731
    point = {
        "psnr_vs_marked_db": float(metrics.psnr(as_chw(images), as_chw(marked)).mean()),
        "psnr_vs_clean_db": float(metrics.psnr(as_chw(images), as_chw(clean)).mean()),
        **extra,
    }
    points = json.loads(path.read_text()) if path.exists() else {}
    points[name] = point
    path.write_text(json.dumps(points, indent=1))
    print(name, point, flush=True)


def folder_images(folder: Path, count: int, hw: Tuple[int, int]) -> torch.Tensor:
    """The first ``count`` images of ``folder`` (sorted by name, alpha on white) as 8-bit ``[N H W 3]``; every image
    must be ``hw`` in size."""
    from gsticker_plugin.views import images_views

    views = images_views(folder, max_side=max(hw), min_side=1, max_pixels=10**8, progress=False).views[:count]
    if len(views) < count or any(tuple(v.image.shape[1:]) != hw for v in views):
        raise ValueError(f"scene={folder}: needs {count} images of {hw[1]}x{hw[0]} px (the held-out renders' size)")
    return as_8_bit(torch.stack([v.image.permute(1, 2, 0) for v in views]))


def attacked(
    image: Float[Tensor, "H W 3"], spec: str, generator: torch.Generator, cover: Optional[Float[Tensor, "H W 3"]]
) -> Float[Tensor, "H W 3"]:
    """``image`` after the attacks of ``spec``, 8-bit; a cropout pastes ``cover`` (the clean render of the same
    camera: the paper's cropout) into its rectangle, or white without one."""
    c = None if cover is None else cover.float().permute(2, 0, 1)[None]
    out = apply_attacks(image.float().permute(2, 0, 1)[None], spec, generator=generator, cover=c)
    return as_8_bit(out[0].clamp(0, 1).permute(1, 2, 0))


def held_out_renders(pipe, cameras) -> Tuple[torch.Tensor, torch.Tensor]:
    """8-bit renders of the watermarked run with its sticker on and off at ``cameras``: ``[N H W 3]`` each."""
    out = {}
    for on in (True, False):
        with pipe.model.sticker_enabled(on):
            out[on] = renders_8_bit(pipe.model, cameras)
    return out[True], out[False]


@torch.no_grad()
def renders_8_bit(model, cameras) -> torch.Tensor:
    """``model``'s final colour at every camera of ``cameras``, rounded to 8 bits: ``[N H W 3]``."""
    imgs = [
        final_rgb(model.get_outputs_for_camera(cameras[i : i + 1])).clamp(0, 1).cpu() for i in range(cameras.shape[0])
    ]
    return as_8_bit(torch.stack(imgs))


def main(cfg: BenchUnposedConfig) -> Dict[str, Any]:
    compat.apply()
    warnings.filterwarnings("ignore")  # nerfstudio 1.1.5's camera indexing warns on every render with this torch
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
        return write_page(cfg, key, done, threshold, {"mean": sum(per_view) / len(per_view), "min": min(per_view)})
    recorded = recorded_psnr(cfg.output.with_suffix(".json"))
    if cfg.page_only and recorded is not None:  # the page's own record: the run may have changed since
        return write_page(cfg, key, done, threshold, recorded)
    t0 = time.time()
    marked, clean = held_out_renders(pipe, cams)
    per_view = metrics.psnr(marked.permute(0, 3, 1, 2), clean.permute(0, 3, 1, 2))
    psnr = {"mean": float(per_view.mean()), "min": float(per_view.min())}
    psnr_path.write_text(json.dumps({"per_view_db": [float(v) for v in per_view]}))
    print(
        f"rendered {cfg.num_views} held-out views in {time.time() - t0:.0f} s; PSNR marked vs clean {psnr['mean']:.2f} dB"
    )
    if cfg.page_only:
        return write_page(cfg, key, done, threshold, psnr)
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
            src = folder_images(Path(which[len("scene=") :]), n, tuple(marked.shape[1:3]))
        else:
            src = recolored_renders(cfg, which, cams[:n])
        at_cameras = which != "random" and not which.startswith("scene=")
        for i in range(n):
            img = src[i].float()
            drawn = ""
            if spec:
                g = torch.Generator().manual_seed(cfg.seed * 1000 + i)
                drawn = drawn_spec(spec, g)
                img = attacked(img, drawn, g, clean[i] if at_cameras and cfg.crop_cover else None)
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
    return write_page(cfg, key, done, threshold, psnr)


def read_nothing(row: Dict[str, Any]) -> bool:
    """Whether an image's every bit is undetermined: the camera found showed no ray the gate reads."""
    return "bits" in row and not any(c in "01" for c in row["bits"])


def unread(summary: Dict[str, Any]) -> str:
    """The table's note on a row's images with nothing to read (none: empty)."""
    n = summary.get("nothing_read", 0)
    return f"; {n} with nothing to read" if n else ""


def summarize(rows: List[Dict[str, Any]], threshold: int, num_bits: int, null: bool = False) -> Dict[str, Any]:
    """A row's images: their matches (a ``null`` row's over the images with bits read, those with nothing to read
    counted apart; a marked image with nothing to read counts its 0 matches), the routes they were read through, the
    camera error and the seconds."""
    read = ([r for r in rows if not read_nothing(r)] if null else rows) or rows
    m = torch.tensor([r["matches"] for r in read], dtype=torch.float64)
    out = {
        "images": len(rows),
        "nothing_read": sum(map(read_nothing, rows)),
        "bit_acc": float(m.mean() / num_bits),
        "matches_mean": float(m.mean()),
        "matches_min": int(m.min()),
        "matches_max": int(m.max()),
        "passing": int((m >= threshold).sum()),
        "read_by_value": sum(r["signals"] == ["value"] for r in rows),
        "read_through_map": sum(bool(r.get("color_map")) for r in rows),
        "searched_through_map": sum((r.get("map_share_at_search") or 0.0) >= MAP_SEARCH_SHARE for r in rows),
        "read_through_blur": sum(r.get("degradation", "none").startswith("blur") for r in rows),
        "read_as_turned": sum(r.get("degradation", "none").startswith("rotate") for r in rows),
        "read_through_jpeg": sum(r.get("degradation", "none").startswith("jpeg") for r in rows),
        "read_around_cover": sum((r.get("covered_share") or 0.0) > 0 for r in rows),
        "seconds_per_image": float(sum(r["seconds"] for r in rows) / len(rows)),
    }
    rot = [r["rotation_error_deg"] for r in rows if "rotation_error_deg" in r]
    if rot:
        out["rotation_error_deg_median"] = float(torch.tensor(rot).median())
        out["rotation_error_deg_max"] = float(max(rot))
    return out


def other_keys(rows: List[Dict[str, Any]], count: int, threshold: int) -> Optional[Dict[str, Any]]:
    """The marked images' decoded bits checked against ``count`` other owners' keys (messages drawn uniformly at
    random, seed 99): the same model under a second key, a null. Each key is one check, against one marked image
    (the images in turn), so the checks are independent draws; ``matches_max_pairs`` and ``passing_pairs`` cover
    every image with every key (those pairs share images, so they are not independent). None without rows or keys."""
    rows = [r for r in rows if "bits" in r]
    if not rows or count <= 0:
        return None
    n = len(rows[0]["bits"])
    msgs = torch.randint(0, 2, (count, n), generator=torch.Generator().manual_seed(99))
    bits = torch.tensor([[int(c) if c in "01" else -1 for c in r["bits"]] for r in rows])
    m = (bits[:, None, :] == msgs[None]).sum(-1)  # [images, keys]
    one = m[torch.arange(count) % len(rows), torch.arange(count)].double()  # key j against image j mod images
    return {
        "keys": count,
        "images": len(rows),
        "checks": count,
        "matches_mean": float(one.mean()),
        "matches_max": int(one.max()),
        "passing": int((one >= threshold).sum()),
        "histogram": match_histogram(one.long().tolist(), n),
        "pairs": int(m.numel()),
        "matches_max_pairs": int(m.max()),
        "passing_pairs": int((m >= threshold).sum()),
    }


def match_histogram(matches: List[int], num_bits: int) -> List[int]:
    """How many checks matched 0, 1, ..., ``num_bits`` bits."""
    out = [0] * (num_bits + 1)
    for v in matches:
        out[int(v)] += 1
    return out


NULL_IMAGES = ("clean", "foreign", "random", "scene")
"""Rows of images that never held the owner's message."""


def is_null_row(row: str) -> bool:
    """Whether a row's images never held the owner's message (its images are one of :data:`NULL_IMAGES`)."""
    return row.partition(":")[0].partition("=")[0] in NULL_IMAGES


REMOVAL_ATTACKS = ("pgd", "purify", "leak")
"""Rows of the threat model: the recipient removing the mark (they may read like the null where they break it)."""


def is_removal_row(row: str) -> bool:
    """Whether a row's images are a removal attack's (:data:`REMOVAL_ATTACKS`)."""
    return row.partition(":")[0].partition("=")[0] in REMOVAL_ATTACKS


def null_chart(
    null: Dict[str, Any], marked: List[int], removed: List[int], path: Path, num_bits: int, threshold: int
) -> None:
    """Histogram of the null's matches beside Binomial(``num_bits``, 1/2) scaled to its checks, the marked images'
    matches and the removal attacks' (log count axis), with the pass line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = list(range(num_bits + 1))
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    ax.bar(x, null["histogram"], 0.8, color="tab:gray", label=f"null: {null['checks']} checks")
    expected = [null["checks"] * math.comb(num_bits, k) / 2**num_bits for k in x]
    ax.plot(x, expected, "k-", lw=1, label=f"Binomial({num_bits}, 1/2) x checks")
    for values, color, label in (
        (marked, "tab:green", "marked model's images (attacked, recoloured)"),
        (removed, "tab:red", "removal attacks (pgd, purify)"),
    ):
        if values:
            ax.bar(x, match_histogram(values, num_bits), 0.8, color=color, alpha=0.8, label=f"{label}: {len(values)}")
    ax.axvline(threshold - 0.5, color="tab:blue", ls=":", label=f"pass line ({threshold}/{num_bits})")
    ax.set_yscale("log")
    ax.set_ylim(0.5, max(max(null["histogram"]), len(marked), len(removed), 1) * 3)
    ax.set_xlabel(f"matching bits (of {num_bits})")
    ax.set_ylabel("images or checks")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def null_summary(
    rows: List[Dict[str, Any]], others: Optional[Dict[str, Any]], threshold: int, num_bits: int = 48
) -> Optional[Dict[str, Any]]:
    """Every null check together: the unmarked images' matches (``rows`` of :data:`NULL_IMAGES`; those with nothing
    to read counted apart) and the marked images checked with other keys; the empirical false-positive rate at
    ``threshold`` with its 95 % upper bound, and the histogram of the matches."""
    m = [float(r["matches"]) for r in rows if not read_nothing(r)]
    checks, total, top = len(m), sum(m), max(m, default=0.0)
    passing = images_passing = int(sum(v >= threshold for v in m))
    histogram = match_histogram([int(v) for v in m], num_bits)
    if others is not None:
        checks += others["checks"]
        total += others["matches_mean"] * others["checks"]
        top = max(top, float(others["matches_max"]))
        passing += others["passing"]
        histogram = [a + b for a, b in zip(histogram, others.get("histogram") or [0] * (num_bits + 1))]
    if checks == 0:
        return None
    return {
        "histogram": histogram,
        "checks": checks,
        "images": len(m),
        "nothing_read": sum(map(read_nothing, rows)),
        "matches_mean": total / checks,
        "matches_max": int(top),
        "passing": int(passing),
        "fpr": passing / checks,
        "fpr_upper_95": metrics.clopper_pearson_upper(int(passing), checks),
        "images_passing": images_passing,
        "images_fpr_upper_95": metrics.clopper_pearson_upper(images_passing, len(m)) if m else 1.0,
    }


def row_key(row: str) -> str:
    """A row's images and attack (``IMAGES:ATTACK``): rows that differ in their ``@N`` share decoded images."""
    return row.partition("@")[0]


def random_noise(count: int, size: int, seed: int):
    """The random images of the null (:func:`gsticker_plugin.views.random_views`), the same for every row."""
    return random_views(count, size, seed + 7).views if count > 0 else []


def row_count(cfg: BenchUnposedConfig, row: str) -> int:
    """Images a row asks for: ``@N`` (default ``--num-views``), at most ``--num-views`` for rows at the held-out
    cameras; random images need no camera (as many as asked)."""
    count = row.partition("@")[2]
    n = int(count) if count else cfg.num_views
    return n if row.startswith("random") else min(n, cfg.num_views)


def wanted(cfg: BenchUnposedConfig) -> Dict[str, int]:
    """Images per row key (:func:`row_count`), in the order of ``--rows`` (the largest of rows sharing a key), random
    images last."""
    out: Dict[str, int] = {}
    for row in cfg.rows:
        out[row_key(row)] = max(out.get(row_key(row), 0), row_count(cfg, row))
    if cfg.random_images > 0:
        out["random:"] = max(out.get("random:", 0), cfg.random_images)
    return out


def not_reached(cfg: BenchUnposedConfig, done: Dict[Any, Dict[str, Any]]) -> Dict[str, int]:
    """Images each row asks for that have not been decoded (``--page-only`` pages)."""
    out = {}
    for key, want in wanted(cfg).items():
        have = sum(1 for k, v in done if k == key and v < want)
        if have < want:
            out[key] = want - have
    return out


def recorded_psnr(page_json: Path) -> Optional[Dict[str, float]]:
    """The marked-vs-clean PSNR (mean, min over the held-out views) a page's JSON recorded; None without one."""
    if not page_json.exists():
        return None
    return json.loads(page_json.read_text()).get("psnr_marked_vs_clean_db")


def recorded_run(page_json: Path) -> Dict[str, Any]:
    """What a page's JSON recorded of the decoding (the machine, the date it was first written, as ``decoded``) for
    a page rewritten from its rows; empty without one."""
    if not page_json.exists():
        return {}
    old = json.loads(page_json.read_text())
    return {"machine": old["machine"], "decoded": old.get("decoded", old["date"])}


def write_page(
    cfg: BenchUnposedConfig, key, done: Dict[Any, Dict[str, Any]], threshold: int, psnr: Dict[str, float]
) -> Dict[str, Any]:
    """The page and its JSON from the images decoded (``done``); ``psnr``: marked vs clean, mean and min (dB)."""
    table = {
        row: summarize(
            [r for (k, v), r in done.items() if k == row and v < n], threshold, key.num_bits, is_null_row(row)
        )
        for row, n in wanted(cfg).items()
        if any(k == row and v < n for k, v in done)
    }
    others = other_keys([r for (k, _), r in done.items() if k.startswith("marked:")], cfg.other_keys, threshold)
    null_rows = [
        r
        for (k, v), r in done.items()
        if k.partition(":")[0].partition("=")[0] in NULL_IMAGES and v < wanted(cfg).get(k, 0)
    ]
    null = null_summary(null_rows, others, threshold, key.num_bits)
    res = {
        "other_keys": others,
        "null": null,
        "command": "python -m gsticker_plugin.bench.unposed " + " ".join(a for a in sys.argv[1:] if a != "--page-only"),
        "not_reached": not_reached(cfg, done),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_info(),
        **(recorded_run(cfg.output.with_suffix(".json")) if cfg.page_only else {}),
        "threshold": threshold,
        "psnr_marked_vs_clean_db": {"mean": psnr["mean"], "min": psnr["min"]},
        "rows": table,
        "per_image": list(done.values()),
    }
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    js = cfg.output.with_suffix(".json")
    js.write_text(json.dumps(res, indent=1))
    lines = [
        "# Images alone: the informed image decoder finds each image's camera",
        "",
        (
            f"Command (images decoded on {res['machine'].get('cpu', '')}, first page {res['decoded']}; this page "
            f"rewritten from their rows on {res['date']} with `--page-only`: the columns say which route each image "
            "was read through then, the text below describes the decoder as it is now; every number here is in "
            f"[{js.name}]({js.name})):"
            if "decoded" in res
            else f"Command ({res['date']}, {res['machine'].get('cpu', '')}; every number here is in [{js.name}]({js.name}), written by it):"
        ),
        "",
        "```bash",
        res["command"],
        "```",
        "",
        f"{cfg.num_views} orbit cameras drawn with seed {cfg.camera_seed} (held out: the sticker never trained or "
        "calibrated on them), the watermarked run rendered there with its sticker on (*marked*) and off (*clean*: "
        f"the owner's base), 8-bit; PSNR marked vs clean {psnr['mean']:.2f} dB mean, {psnr['min']:.2f} dB "
        "worst view. Every image is decoded **without its camera**: a search over candidate poses against the owner's "
        "base, Gauss-Newton on the pixels (on V; again on RGB with the base rendered through a colour map of its "
        f"samples when that map explains at least {MAP_SEARCH_SHARE:.0%} of the image's difference from the base "
        "render: a recoloured copy), then the image fit with the pose Jacobian beside the message (through a blur or a "
        "JPEG of the base render when one explains the image far better; again without a rectangle the fitted mark is "
        "missing from, when one stands far above the noise: a cropout pasted from an unmarked render) "
        f"([verify.md](verify.md)). A view passes at >= {threshold}/48 (per-view false-positive rate 1e-6).",
        "",
        "| images | attack | decoded | bit accuracy | matches mean (min-max) | passing | read by V / colour map / camera searched through map / through a blur / as a turned render / through a JPEG / around a covered rectangle | camera error median / max (deg) | s per image (wall) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row, t in table.items():
        which, _, spec = row.partition(":")
        spec = spec.partition("@")[0]
        cam = (
            f"{t['rotation_error_deg_median']:.4f} / {t['rotation_error_deg_max']:.3f}"
            if "rotation_error_deg_median" in t
            else "-"
        )
        if "crop" in spec:  # rows decoded before crop_fill was recorded painted a white rectangle
            fills = sorted({r.get("crop_fill") or "white" for (k, _), r in done.items() if k == row})
            spec += f" ({' / '.join(fills)})"
        lines.append(
            f"| {which} | {spec or 'none'} | {t['images']} | {100 * t['bit_acc']:.2f} % | {t['matches_mean']:.1f} "
            f"({t['matches_min']}-{t['matches_max']}){unread(t)} | {t['passing']}/{t['images']} | {t['read_by_value']} / "
            f"{t['read_through_map']} / {t['searched_through_map']} / {t['read_through_blur']} / {t.get('read_as_turned', 0)} / {t.get('read_through_jpeg', 0)} / {t.get('read_around_cover', 0)} | {cam} | "
            f"{t['seconds_per_image']:.0f} |"
        )
    if others is not None:
        lines.append(
            f"| marked, checked with {others['keys']} other keys (one image each) | none | {others['checks']} checks | - | "
            f"{others['matches_mean']:.1f} (max {others['matches_max']}; every image with every key: max "
            f"{others.get('matches_max_pairs', others['matches_max'])}) | {others['passing']}/{others['checks']} | - | - "
            "| - |"
        )
    if null is not None:
        lines += [
            "",
            f"The null together ({null['images']} unmarked images and the other keys' checks): {null['checks']} checks, "
            + (
                f"left out: {null['nothing_read']} more unmarked image(s) with nothing to read (every bit "
                "undetermined, no ray the gate reads at the camera found); "
                if null.get("nothing_read")
                else ""
            )
            + f"matches mean {null['matches_mean']:.1f}, max {null['matches_max']}; {null['passing']} pass at >= "
            f"{threshold}/48: empirical false-positive rate {null['fpr']:.4f}, 95 % upper bound "
            f"{null['fpr_upper_95']:.4f} (Clopper-Pearson over independent checks)."
            + (
                f" The unmarked images alone: {null['images']} images, {null['images_passing']} pass, 95 % upper "
                f"bound {null['images_fpr_upper_95']:.3f}."
                if null["images"]
                else ""
            ),
        ]
        chart = cfg.output.with_name(cfg.output.stem + "-null.png")
        kept = [(k, r) for (k, v), r in done.items() if not is_null_row(k) and v < wanted(cfg).get(k, 0)]
        null_chart(
            null,
            [r["matches"] for k, r in kept if not is_removal_row(k)],
            [r["matches"] for k, r in kept if is_removal_row(k)],
            chart,
            key.num_bits,
            threshold,
        )
        lines += ["", f"![matches of the null beside the marked images]({chart.name})"]
    if res["not_reached"]:
        lines += [
            "",
            "Not decoded in this run (the page was written from the images done, `--page-only`): "
            + ", ".join(f"`{row}` {n} images" for row, n in res["not_reached"].items())
            + ".",
            "",
        ]
    threat = threat_curves(cfg, table, threshold, key.num_bits)
    if threat:
        res["threat"] = threat
        js.write_text(json.dumps(res, indent=1))
        lines += threat_lines(threat, cfg.output, cfg.purify_lr, cfg.purify_rays_per_step)
    lines += [
        "",
        "*clean*, *foreign*, *scene* (another scene) and *random* images do not carry the owner's message, and the other keys' messages were "
        "never in the model: the null. Decoded the same way, their matches follow Binomial(48, 1/2) when the decoder "
        "is honest (mean 24).",
    ]
    cfg.output.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


def threat_curves(cfg: BenchUnposedConfig, table, threshold: int, num_bits: int) -> List[Dict[str, Any]]:
    """Bit accuracy against PSNR (vs the shared marked renders) of the ``purify=`` rows (images alone, and the informed
    geometric decoder on the same model) and of the ``leak=`` rows; a PNG chart beside the page."""
    points, leaks, pgds = ({}, {}, {})
    if (cfg.work_dir / "purify.json").exists():
        points = json.loads((cfg.work_dir / "purify.json").read_text())
    if (cfg.work_dir / "leak.json").exists():
        leaks = json.loads((cfg.work_dir / "leak.json").read_text())
    if (cfg.work_dir / "pgd.json").exists():
        pgds = json.loads((cfg.work_dir / "pgd.json").read_text())
    out = []

    def point(attack: str, strength: float, p: Dict[str, Any], t: Dict[str, Any], **informed) -> Dict[str, Any]:
        read = {"geometric_bit_acc": None, "geometric_passing": None, "posed_bit_acc": None, "posed_passing": None}
        for decoder, matches in informed.items():  # an informed decoder's matches per view beside the images alone
            m = torch.tensor(matches)
            read[f"{decoder}_bit_acc"] = p[f"{decoder}_bit_acc"]
            read[f"{decoder}_passing"] = f"{int((m >= threshold).sum())}/{len(m)}"
        return {
            "attack": attack,
            "strength": strength,
            "psnr_vs_marked_db": p["psnr_vs_marked_db"],
            "psnr_vs_clean_db": p["psnr_vs_clean_db"],
            "images_bit_acc": t["bit_acc"],
            "images_passing": f"{t['passing']}/{t['images']}",
            **read,
            "purify_seconds": p.get("purify_seconds"),
        }

    for row, t in table.items():
        which = row.partition(":")[0]
        attack, _, value = which.partition("=")
        if attack == "purify" and value in points:
            p = points[value]
            out.append(point("purify", p["steps"], p, t, geometric=p["geometric_matches"]))
        elif attack == "leak" and str(float(value)) in leaks:
            out.append(point("leak", float(value), leaks[str(float(value))], t))
        elif attack == "pgd" and str(float(value)) in pgds:
            p = pgds[str(float(value))]
            out.append(point("pgd", float(value), p, t, posed=p["posed_matches"]))
    if out:
        threat_chart(out, cfg.output.with_suffix(".png"), num_bits, threshold)
    return out


def threat_chart(points: List[Dict[str, Any]], path: Path, num_bits: int, threshold: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    series = [
        ("purify", "images_bit_acc", "purification: images alone", "o-"),
        ("purify", "geometric_bit_acc", "purification: informed geometric", "s--"),
        ("leak", "images_bit_acc", "blend toward the owner's base: images alone", "^-"),
        ("pgd", "images_bit_acc", "leaked-key PGD: images alone", "v-"),
        ("pgd", "posed_bit_acc", "leaked-key PGD: informed image decoder, true cameras", "d--"),
    ]
    for attack, field, label, style in series:
        pts = sorted(
            (p["psnr_vs_marked_db"], p[field]) for p in points if p["attack"] == attack and p[field] is not None
        )
        if pts:
            ax.plot([x for x, _ in pts], [100 * y for _, y in pts], style, label=label)
    ax.axhline(100 * threshold / num_bits, color="gray", lw=0.8, ls=":", label=f"pass line ({threshold}/{num_bits})")
    ax.axhline(50, color="gray", lw=0.8)
    ax.set_xlabel("PSNR of the attacked renders vs the shared marked renders (dB)")
    ax.set_ylabel("bit accuracy (%)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def threat_lines(
    points: List[Dict[str, Any]], output: Path, purify_lr: float = 1e-3, purify_rays: int = 1024
) -> List[str]:
    lines = [
        "",
        "## Threat model: the recipient removes the mark",
        "",
        f"![bit accuracy against PSNR]({output.with_suffix('.png').name})",
        "",
        "*purify*: every parameter of the shared watermarked run fine-tuned on the clean training images (Adam, "
        f"learning rate {purify_lr:g}, {purify_rays} rays per step: the evaluation's purify stage), cumulative steps; the same model read by the informed geometric decoder at the "
        "base run's cameras beside the images-alone decoder at the held-out views. *leak*: the marked renders blended "
        "toward the owner's base renders by the share (what a holder of the base, i.e. of the owner key, can do; "
        "without the key the recipient has no unmarked render to blend toward). *pgd*: each marked render attacked by "
        "projected gradient descent on the informed image decoder at its true camera within a PSNR budget (dB), the "
        "leaked-key attack (`decoders.image.leaked_key_attack`), read without the camera and, beside it, by the "
        "informed image decoder given the true camera. PSNR is against the shared marked renders at the held-out "
        "views.",
        "",
        "| attack | steps / share / budget | PSNR vs marked (dB) | PSNR vs clean (dB) | images alone: bit acc, passing | informed geometric: bit acc, passing | informed image, true cameras: bit acc, passing | purify s |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def reading(p: Dict[str, Any], decoder: str) -> str:
        acc = p.get(f"{decoder}_bit_acc")
        return "-" if acc is None else f"{100 * acc:.1f} %, {p[f'{decoder}_passing']}"

    for p in points:
        lines.append(
            f"| {p['attack']} | {p['strength']} | {p['psnr_vs_marked_db']:.2f} | {p['psnr_vs_clean_db']:.2f} | "
            f"{reading(p, 'images')} | {reading(p, 'geometric')} | {reading(p, 'posed')} | "
            f"{'-' if p['purify_seconds'] is None else p['purify_seconds']} |"
        )
    return lines + [""] + breaking_points(points)


def breaking_points(points: List[Dict[str, Any]]) -> List[str]:
    """One line per attack and decoder: the strongest setting at which every image still passes and the weakest at
    which one fails (settings in increasing strength), with their PSNR against the marked renders."""

    def fraction(passing: str) -> float:
        k, n = passing.split("/")
        return int(k) / max(1, int(n))

    def setting(p: Dict[str, Any]) -> str:
        if p["attack"] == "purify":
            return f"{p['strength']} step" + ("" if p["strength"] == 1 else "s")
        if p["attack"] == "pgd":
            return f"a {p['strength']:g} dB budget"
        return f"{p['strength']} blended" if p["attack"] == "leak" else str(p["strength"])

    def strength(p: Dict[str, Any]) -> float:  # a smaller PSNR budget is the stronger attack
        return -p["strength"] if p["attack"] == "pgd" else p["strength"]

    lines = []
    decoders = (
        ("images", "images alone"),
        ("geometric", "informed geometric"),
        ("posed", "informed image, true cameras"),
    )
    for attack in dict.fromkeys(p["attack"] for p in points):
        rows = sorted((p for p in points if p["attack"] == attack), key=strength)
        for decoder, name in decoders:
            read = [(p, fraction(p[f"{decoder}_passing"])) for p in rows if p.get(f"{decoder}_passing") is not None]
            if not read:
                continue
            broke = next((p for p, f in read if f < 1.0), None)
            held = [p for p, f in read if broke is None or strength(p) < strength(broke)]
            text = f"- {attack}, {name}: " + (
                f"every image passes up to {setting(held[-1])} ({held[-1]['psnr_vs_marked_db']:.1f} dB vs marked)"
                if held
                else "the weakest setting tried already breaks it"
            )
            if broke is None:
                text += "; no setting tried breaks it"
            else:
                text += (
                    f"; breaks at {setting(broke)} ({broke['psnr_vs_marked_db']:.1f} dB vs marked, "
                    f"{100 * broke[f'{decoder}_bit_acc']:.1f} % of bits)"
                )
            lines.append(text + ".")
    return lines


if __name__ == "__main__":
    main(tyro.cli(BenchUnposedConfig))
