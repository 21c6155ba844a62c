"""Views: the images a decoder reads (renders of a run, a folder of images, random images) and how they are made."""

from __future__ import annotations

import contextlib
import math
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from gsticker_plugin.attacks import apply_attacks, parse_attack_spec
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.fastpath import novel_cameras
from gsticker_plugin.runs import final_rgb, load_run


@dataclass
class View:
    name: str
    image: Tensor  # [3 H W] float in [0, 1], CPU
    note: str = ""


@dataclass
class Views:
    kind: str  # "model" | "images" | "random"
    source: str
    views: List[View] = field(default_factory=list)
    skipped: List[Dict[str, str]] = field(default_factory=list)
    details: Dict[str, Any] = field(default_factory=dict)


class SkipImage(Exception):
    pass


def progress_bar(iterable, desc: str, enabled: bool, total: Optional[int] = None):
    if not enabled:
        return iterable

    return tqdm(iterable, desc=desc, total=total, leave=False, file=sys.stderr)


def read_image(
    path: Path, max_side: int = 400, min_side: int = 16, max_pixels: int = 1_000_000_000
) -> Tuple[Tensor, str]:
    """An image file as ``[3 H W]`` float RGB in [0, 1]; raises ``SkipImage(reason)`` when it cannot be used.

    Grayscale is replicated to RGB, alpha is composited on white, 8/16-bit integers are normalised to [0, 1] and
    float (HDR) values are clamped to [0, 1]. Images with a longer side above ``max_side`` are reduced by an
    integer area average while being read in strips (memory stays bounded for any size), then resized exactly.
    """
    # deferred: native image library, only image I/O needs it
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()
        raise SkipImage("not an image OpenImageIO can read")
    notes = []
    try:
        spec = inp.spec()
        w, h, nch = int(spec.width), int(spec.height), int(spec.nchannels)
        if w <= 0 or h <= 0 or nch <= 0:
            raise SkipImage(f"empty image ({w}x{h}, {nch} channels)")
        if min(w, h) < min_side:
            raise SkipImage(f"too small to carry a mark ({w}x{h} px; needs >= {min_side} px a side, see --min-side)")
        if w * h > max_pixels:
            raise SkipImage(f"too large to decode safely ({w}x{h} = {w * h:.3g} px > --max-pixels {max_pixels:.3g})")
        fmt = str(spec.format)
        is_float = fmt in ("half", "float", "double")
        alpha = int(spec.alpha_channel)
        if alpha < 0 and nch in (2, 4):
            alpha = nch - 1
        color = [c for c in range(nch) if c != alpha][:3]
        f = max(1, math.ceil(max(w, h) / max_side))
        if f > 1:
            notes.append(f"downscaled from {w}x{h}")
        if len(color) == 1:
            notes.append("grayscale replicated to RGB")
        if alpha >= 0:
            notes.append("alpha composited on white")
        if fmt not in ("uint8", "float"):
            notes.append(f"{fmt} normalised to [0, 1]")
        rows_per = f * max(1, (32 << 20) // max(1, w * nch * 4 * f))  # strips of about 32 MB of float pixels
        col_idx = np.arange(0, w, f)
        col_cnt = np.diff(np.append(col_idx, w)).astype(np.float32)
        strips = []
        clamped = False
        for y0 in range(0, h, rows_per):
            y1 = min(y0 + rows_per, h)
            a = inp.read_scanlines(0, 0, y0, y1, 0, 0, nch, "float")
            if a is None or not hasattr(a, "shape"):
                oiio.geterror()
                raise SkipImage("unreadable pixel data (truncated or corrupt file)")
            a = np.asarray(a, dtype=np.float32).reshape(y1 - y0, w, nch)
            a = np.nan_to_num(a, nan=0.0, posinf=1.0, neginf=0.0)
            if is_float and (a.min() < 0.0 or a.max() > 1.0):
                clamped = True
            a = np.clip(a, 0.0, 1.0)
            rgb = a[..., color]
            if rgb.shape[-1] == 1:
                rgb = np.repeat(rgb, 3, axis=-1)
            elif rgb.shape[-1] == 2:
                rgb = np.concatenate([rgb, rgb[..., :1]], axis=-1)
            if alpha >= 0:
                al = a[..., alpha : alpha + 1]
                rgb = rgb * al + (1.0 - al)
            if f > 1:
                rgb = np.add.reduceat(rgb, col_idx, axis=1) / col_cnt[None, :, None]
                r_idx = np.arange(0, y1 - y0, f)
                r_cnt = np.diff(np.append(r_idx, y1 - y0)).astype(np.float32)
                rgb = np.add.reduceat(rgb, r_idx, axis=0) / r_cnt[:, None, None]
            strips.append(np.ascontiguousarray(rgb, dtype=np.float32))
        if clamped:
            notes.append("float values clamped to [0, 1]")
    finally:
        inp.close()
    img = torch.from_numpy(np.concatenate(strips, axis=0)).permute(2, 0, 1).contiguous()
    hh, ww = img.shape[-2:]
    if max(hh, ww) > max_side:  # the integer reduction left it slightly above the target: exact resize
        s = max_side / max(hh, ww)
        size = (max(1, round(hh * s)), max(1, round(ww * s)))
        img = torch.nn.functional.interpolate(
            img[None], size=size, mode="bilinear", antialias=True, align_corners=False
        )[0].clamp(0, 1)
    return img, "; ".join(notes)


def list_files(folder: Path) -> List[Path]:
    if folder.is_file():
        return [folder]
    return sorted(
        p
        for p in folder.rglob("*")
        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts)
    )


def images_views(folder: Path, max_side: int, min_side: int, max_pixels: int, progress: bool = True) -> Views:
    """Every usable image of a folder (recursive) or a single image file; unusable files are listed as skipped."""
    folder = Path(folder)
    if not folder.exists():
        raise GStickerError(f"--images {folder} does not exist; pass a folder of suspect images")
    files = list_files(folder)
    if not files:
        raise GStickerError(f"--images {folder} holds no files; pass a folder with the suspect images")
    out = Views(kind="images", source=str(folder))
    for p in progress_bar(files, "reading images", progress):
        name = str(p.relative_to(folder)) if p != folder else p.name
        try:
            img, note = read_image(p, max_side=max_side, min_side=min_side, max_pixels=max_pixels)
        except SkipImage as s:
            out.skipped.append({"name": name, "reason": str(s)})
            continue
        except (OSError, ValueError, RuntimeError, MemoryError) as e:  # any reader failure is a skip, not a crash
            out.skipped.append({"name": name, "reason": f"could not be read ({type(e).__name__}: {e})"[:200]})
            continue
        out.views.append(View(name=name, image=img, note=note))
    if not out.views:
        reasons = "; ".join(f"{s['name']}: {s['reason']}" for s in out.skipped[:3])
        raise GStickerError(
            f"no usable image among the {len(files)} files of {folder} ({reasons}"
            f"{'; ...' if len(out.skipped) > 3 else ''}); pass a folder of renders or screenshots"
        )
    return out


def random_views(n: int, size: int, seed: int) -> Views:
    """Random unmarked images for the null: uniform noise, smooth noise, flat colours and gradients."""
    g = torch.Generator().manual_seed(seed)
    out = Views(kind="random", source=f"{n} random images ({size} px)")
    for i in range(n):
        kind = i % 4
        if kind == 0:
            img = torch.rand(3, size, size, generator=g)
        elif kind == 1:
            cells = int(torch.randint(2, 9, (1,), generator=g))
            img = torch.nn.functional.interpolate(
                torch.rand(1, 3, cells, cells, generator=g), size=(size, size), mode="bicubic", align_corners=False
            )[0].clamp(0, 1)
        elif kind == 2:
            img = torch.rand(3, 1, 1, generator=g).expand(3, size, size).clone()
            img = (img + 0.02 * torch.randn(3, size, size, generator=g)).clamp(0, 1)
        else:
            a, b = torch.rand(3, 1, 1, generator=g), torch.rand(3, 1, 1, generator=g)
            t = torch.linspace(0, 1, size)
            ramp = t.view(1, 1, -1) if i % 8 == 3 else t.view(1, -1, 1)
            img = (a + (b - a) * ramp).expand(3, size, size).clone()
        out.views.append(View(name=f"random-{i:04d}", image=img))
    return out


def select_cameras(pipeline, num_views: int, sampled_share: float, seed: int):
    """``num_views`` cameras: evenly spaced run cameras (train then eval) and sampled orbit poses."""

    dm = pipeline.datamanager
    own = []
    for split, ds in (("train", getattr(dm, "train_dataset", None)), ("eval", getattr(dm, "eval_dataset", None))):
        if ds is None:
            continue
        for i in range(len(ds.cameras)):
            own.append((f"{split}/{i:03d}", ds.cameras, i))
    if not own:
        raise GStickerError("the run has no cameras to render from (empty datasets)")
    n_sampled = int(round(num_views * sampled_share))
    n_own = num_views - n_sampled
    chosen = []
    if n_own > 0:
        idx = sorted({int(round(j * (len(own) - 1) / max(1, n_own - 1))) for j in range(n_own)}) if n_own > 1 else [0]
        chosen += [(name, cams[i : i + 1]) for name, cams, i in (own[j] for j in idx)]
        n_sampled = num_views - len(chosen)  # fewer own cameras than asked: fill with sampled poses
    if n_sampled > 0:
        g = torch.Generator().manual_seed(seed)
        cams = dm.train_dataset.cameras
        novel = novel_cameras(cams, n_sampled, g)
        chosen += [(f"sampled/{i:03d}", novel[i : i + 1]) for i in range(n_sampled)]
    return chosen


@torch.no_grad()
def model_views(
    config_path: Path,
    num_views: int,
    sampled_share: float,
    seed: int,
    data: Optional[Path],
    device: torch.device,
    sticker: Optional[bool] = None,
    progress: bool = True,
) -> Views:
    """Render ``num_views`` views of a run (sticker as the run has it unless ``sticker`` says otherwise)."""
    if num_views <= 0:
        raise GStickerError(f"--num-views must be positive, got {num_views}")
    if not 0.0 <= sampled_share <= 1.0:
        raise GStickerError(f"--sampled-share must be in [0, 1], got {sampled_share}")

    with contextlib.redirect_stdout(sys.stderr):  # Nerfstudio's setup chatter; stdout is kept for the verdict
        config, pipeline, ckpt = load_run(config_path, data=data, device=device)
    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
    model = pipeline.model
    cams = select_cameras(pipeline, num_views, sampled_share, seed)
    ctx = model.sticker_enabled(sticker) if (sticker is not None and hasattr(model, "sticker_enabled")) else None
    out = Views(
        kind="model",
        source=str(config_path),
        details={
            "method": config.method_name,
            "model": type(model).__name__,
            "checkpoint": str(ckpt),
            "sticker": (None if not hasattr(model, "sticker_enabled") else ("off" if sticker is False else "on")),
        },
    )
    if ctx is not None:
        ctx.__enter__()
    try:
        for name, cam in progress_bar(cams, f"rendering {Path(config_path).parent.name}", progress):
            o = model.get_outputs_for_camera(cam.to(model.device))
            rgb = final_rgb(o).detach().float().clamp(0, 1).cpu()
            out.views.append(View(name=name, image=rgb.permute(2, 0, 1).contiguous()))
    finally:
        if ctx is not None:
            ctx.__exit__(None, None, None)
    out.details["own_cameras"] = sum(1 for v in out.views if not v.name.startswith("sampled/"))
    out.details["sampled_poses"] = sum(1 for v in out.views if v.name.startswith("sampled/"))
    return out


def apply_attack(views: Views, spec: str, seed: int) -> None:
    if not spec.strip():
        return

    try:
        steps = parse_attack_spec(spec)
    except ValueError as e:
        raise GStickerError(f"--attack: {e}") from None
    g = torch.Generator().manual_seed(seed)
    for v in views.views:
        v.image = apply_attacks(v.image[None].float(), steps, generator=g)[0].clamp(0, 1)
