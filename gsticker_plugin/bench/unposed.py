"""Images alone: the informed image decoder on held-out orbit renders whose cameras it has to find.

    python -m gsticker_plugin.bench.unposed --load-config RUN/config.yml --key RUN.gskey --data ../shared/data/lego100

Draws ``--num-views`` orbit cameras with ``--camera-seed`` (like the pool's novel views, never used in training),
renders the watermarked run (sticker on) and its base (sticker off) there, rounds them to 8 bits, applies each row's
image attack, and decodes every image without its camera (:func:`gsticker_plugin.decoders.unposed.decode_unposed_images`);
random images are decoded too. Writes per-image rows to ``--work-dir/rows.jsonl`` as they finish (a rerun resumes),
then a Markdown page and a JSON beside it (:mod:`gsticker_plugin.bench.unposed_page`).
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
from gsticker_plugin.bench.unposed_page import recorded_page, row_count, row_key, write_page
from gsticker_plugin.decoders.image import decode_posed_images, image_reference, leaked_key_attack
from gsticker_plugin.decoders.pose import PoseSearch
from gsticker_plugin.decoders.reference import any_reference_view, cpu_sticker, load_base_reference
from gsticker_plugin.decoders.unposed import decode_unposed_images
from gsticker_plugin.evaluate import final_rgb
from gsticker_plugin.fastpath import novel_cameras
from gsticker_plugin.key import OwnerKey
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
    output: Path = Path("docs/experiments/bench-unposed.md")
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


def view_attack(
    image: Float[Tensor, "H W 3"], spec: str, view: int, cover: Optional[Float[Tensor, "H W 3"]], seed: int = 0
) -> Tuple[Float[Tensor, "H W 3"], str]:
    """``image`` (held-out view ``view``) after ``spec`` drawn as this bench draws it for that view (a generator
    seeded ``seed * 1000 + view``): (the attacked 8-bit image, the drawn spec)."""
    g = torch.Generator().manual_seed(seed * 1000 + view)
    drawn = drawn_spec(spec, g)
    return attacked(image, drawn, g, cover), drawn


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
    recorded = recorded_page(cfg.output.with_suffix(".json")).get("psnr_marked_vs_clean_db") if cfg.page_only else None
    if recorded is not None:  # the page's own record: the run may have changed since
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
    return write_page(cfg, key, done, threshold, psnr)


def random_noise(count: int, size: int, seed: int):
    """The random images of the null (:func:`gsticker_plugin.views.random_views`), the same for every row."""
    return random_views(count, size, seed + 7).views if count > 0 else []


if __name__ == "__main__":
    main(tyro.cli(BenchUnposedConfig))
