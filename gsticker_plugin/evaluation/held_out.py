"""Held-out renders and attacked images for the images-alone benchmarks: renders of a run, of its recolored or purified copies, images from a folder or of noise, and the attacks drawn on them."""

from __future__ import annotations

import contextlib
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, List, Optional, Tuple

import torch
from jaxtyping import Float
from torch import Tensor

from gsticker_plugin import metrics
from gsticker_plugin.attacks.spec import apply_attacks
from gsticker_plugin.decoders.image import decode_posed_images, image_reference
from gsticker_plugin.decoders.reference import any_reference_view, cpu_sticker
from gsticker_plugin.evaluate import final_rgb
from gsticker_plugin.evaluation.leaked_key import leaked_key_attack
from gsticker_plugin.metrics import as_8_bit
from gsticker_plugin.runs import load_run
from gsticker_plugin.views import random_views

HELD_OUT_VIEWS = 24
"""Held-out cameras the images-alone benchmarks draw."""
HELD_OUT_CAMERA_SEED = 12345
"""The seed they are drawn with (the sticker never trains or calibrates on them)."""


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


def recolored_renders(cfg: Any, edit: str, cameras) -> torch.Tensor:
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


def run_renders(cfg: Any, config: Optional[Path], cameras) -> torch.Tensor:
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


def purified_renders(cfg: Any, key, ref, steps: int, cameras, marked, clean) -> torch.Tensor:
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
    (:func:`gsticker_plugin.evaluation.leaked_key.leaked_key_attack`: what a holder of the owner key and the base can do);
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


def random_noise(count: int, size: int, seed: int):
    """The random images of the null (:func:`gsticker_plugin.views.random_views`), the same for every row."""
    return random_views(count, size, seed + 7).views if count > 0 else []
