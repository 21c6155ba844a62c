"""``ns-verify-owner``: does a suspect model, or a folder of suspect images, carry an owner's message?

Four subcommands (``verify`` is the default and may be left out)::

    ns-verify-owner [verify] (--load-config RUN/config.yml | --images DIR) (--key KEY.gskey | --keys DIR) [...]
    ns-verify-owner calibrate --key KEY.gskey [--load-config RUN/config.yml ...] [--images DIR ...] [...]
    ns-verify-owner export-key --load-config WATERMARKED_RUN/config.yml --key KEY.gskey [--output NEW.gskey]
    ns-verify-owner commit --key KEY.gskey      (prints the key's commitment; verify --commitment HEX checks it)

``verify`` renders N views of a run (its own cameras and sampled orbit poses) or reads the images of a folder,
decodes each view with the owner key's extractor, tests each view on its own against the binomial null
(``P(X >= m)`` for ``X ~ Binomial(48, 1/2)``), and combines the per-view decisions with the vote of
:func:`gsticker_plugin.metrics.combine_view_decisions` (never pooling bits across views). It prints the verdict
first, writes ``report.json`` and ``report.png``, and exits 0 ("owned"), 1 ("not shown") or 2 (error).

``calibrate`` decodes unmarked renders and images with a key and stores the observed null in the key (the key is
rewritten atomically; the previous file is kept as ``KEY.gskey.bak``). ``verify`` then uses the stricter of the
theoretical and the empirical per-view threshold and reports both. See docs/verify.md.

Three decoders (``--decode``): the blind *extractor* (the key's CNN reads RGB renders or images), the informed
*geometric* decoder (gsticker_plugin.geometry: fits the key's sticker to a suspect model's accumulation/depth against
the owner's unwatermarked base run; models only) and the informed *image* decoder (gsticker_plugin.image_decoder:
the same fit on the colour of images taken at known cameras, ``--images DIR --cameras transforms.json``). ``export-key`` adds the geometric decoder's reference (sticker,
gates) to a version-1 key from the watermarked run it belongs to.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple

import torch
from torch import Tensor

from gsticker_plugin import metrics
from gsticker_plugin.base_run import final_rgb
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.key import KEY_SUFFIX, OwnerKey, bits_to_str, commitment

EXIT_OWNED, EXIT_NOT_SHOWN, EXIT_ERROR = 0, 1, 2
DECODER_NAMES = {"extractor": "extractor", "geometry": "geometric decoder", "image": "image decoder"}
NULL_FORMAT_VERSION = 1
THUMB_SIDE = 128  # side of the view thumbnails kept for the figure

# ================================================================================================================
# configuration
# ================================================================================================================


@dataclass
class VerifyConfig:
    """Decide whether a suspect run or a folder of suspect images carries an owner's message.

    Exit status: 0 "owned", 1 "not shown", 2 error. Calibrate a key's empirical null first with
    `ns-verify-owner calibrate --key KEY` (see docs/verify.md).
    """

    load_config: Optional[Path] = None
    """RUN/config.yml of the suspect run (any Nerfstudio method, recolored or not); N views are rendered."""
    images: Optional[Path] = None
    """Folder (searched recursively) or single file of suspect images: renders, screenshots, any size or format
    OpenImageIO reads. Files that cannot be used are skipped and listed in the report."""
    key: Optional[Path] = None
    """The owner key (.gskey written by ns-train geometrysticker)."""
    keys: Optional[Path] = None
    """A folder of owner keys (*.gskey): every key is tested, corrected for multiple testing (--correction)."""
    num_views: int = 24
    """Views rendered from a run (--load-config): its own cameras and sampled orbit poses."""
    sampled_share: float = 0.5
    """Share of the rendered views taken from sampled orbit poses; the rest are the run's own train/eval cameras."""
    data: Optional[Path] = None
    """Dataset folder of the run, when the path recorded in its config.yml does not exist from here (also used for
    the owner's base run under --decode geometry when its recorded dataset does not exist and --base-data is unset)."""
    decode: Literal["auto", "geometry", "image", "extractor"] = "auto"
    """geometry: informed decoding from the suspect model's accumulation/depth, given the owner's unwatermarked base
    run (needs a version-2 key and --load-config; model-level only); image: informed decoding of --images taken at
    the known cameras of --cameras, given the owner's base run (the same fit on colour); extractor: the key's CNN
    reads the message from RGB renders or images (blind); auto: geometry for a model and image for images with
    --cameras when the keys' base runs are reachable, else extractor."""
    cameras: Optional[Path] = None
    """--images only: a transforms JSON (Blender format, e.g. the base dataset's transforms_test.json) giving each
    image's camera, matched by file name without extension (r_0.png <-> ./test/r_0); enables --decode image.
    Images without a camera are skipped and listed."""
    base_config: Optional[Path] = None
    """The owner's base run (config.yml) for --decode geometry, when the path recorded in the key moved."""
    base_data: Optional[Path] = None
    """Dataset folder of the owner's base run, when its recorded one does not exist from here (default: --data)."""
    fpr: float = 1e-6
    """Per-view false-positive rate of the binomial test (1e-6 = at least 41 of 48 bits)."""
    min_share: float = 0.5
    """Share of views that must pass for the model-level verdict; its FPR is at most fpr / min-share."""
    correction: Literal["holm", "bonferroni"] = "holm"
    """Multiple-testing correction across keys (--keys)."""
    attack: str = ""
    """Distortions applied before decoding, in order, e.g. 'noise=0.1,rotate=30,crop=0.25,blur=1,jpeg=50,hue=0.3'."""
    seed: int = 0
    """Seed of the sampled poses and of the random attacks."""
    output: Path = Path("verify-report")
    """Folder for report.json and report.png (created; an existing report there is replaced)."""
    figure: bool = True
    """Write report.png (histogram of matches against the null and a few decoded views)."""
    max_side: int = 400
    """Images whose longer side exceeds this are downscaled (area average, streamed) to this size before decoding."""
    min_side: int = 16
    """Images with a shorter side below this are skipped (too small to carry a mark)."""
    max_pixels: int = 1_000_000_000
    """Images with more pixels than this are skipped (decompression-bomb guard); smaller ones are streamed."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Device for rendering and decoding (auto: cuda when available)."""
    progress: bool = True
    """Show tqdm progress bars (on stderr)."""
    commitment: Optional[str] = None
    """The commitment (hex) printed by `ns-verify-owner commit` and published when the model was released: checked
    against --key (a mismatch is an error, exit 2); the report says it matched, i.e. this key existed then."""


@dataclass
class CalibrateConfig:
    """Decode unmarked renders/images with a key and store the observed null in the key.

    The key is rewritten atomically (fingerprint recomputed); the previous file is kept as KEY.gskey.bak.
    """

    key: Path
    """The owner key to calibrate (.gskey)."""
    load_config: Tuple[Path, ...] = ()
    """Unmarked runs (config.yml) to render: other scenes, other models. GeometrySticker runs are rendered with the
    sticker off (i.e. their unmarked base)."""
    images: Tuple[Path, ...] = ()
    """Folders of unmarked images."""
    base: bool = True
    """Also render the base run the key was made on (the config path recorded in the key), when it exists here."""
    decode: Literal["extractor", "geometry", "image"] = "extractor"
    """Which decoder's null to measure: the extractor's (stored in the key's null), the geometric decoder's
    (stored in the key's geometry reference; decodes the base itself and the --load-config runs, not images) or the
    image decoder's (stored beside it; decodes the --images at the cameras of --cameras, e.g. the base dataset's
    own photos: unmarked images at known cameras; random images are not used)."""
    cameras: Optional[Path] = None
    """--decode image: the transforms JSON giving the cameras of the --images (Blender format)."""
    base_config: Optional[Path] = None
    """--decode geometry: the owner's base run (config.yml), when the path recorded in the key moved."""
    data: Optional[Path] = None
    """--decode geometry: dataset folder of the owner's base run, when its recorded one does not exist here."""
    random_images: int = 64
    """Random images (noise, smooth noise, flat colours, gradients) added to the null."""
    random_size: int = 64
    """Side of the random images."""
    num_views: int = 24
    """Views rendered per run."""
    sampled_share: float = 0.5
    """Share of the rendered views taken from sampled orbit poses."""
    append: bool = False
    """Add to the null already stored in the key instead of replacing it."""
    backup: bool = True
    """Keep the previous key file as KEY.gskey.bak before rewriting it."""
    seed: int = 0
    """Seed of the sampled poses and the random images."""
    max_side: int = 400
    """Images whose longer side exceeds this are downscaled before decoding."""
    min_side: int = 16
    """Images with a shorter side below this are skipped."""
    max_pixels: int = 1_000_000_000
    """Images with more pixels than this are skipped."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Device for rendering and decoding."""
    progress: bool = True
    """Show tqdm progress bars (on stderr)."""


# ================================================================================================================
# views
# ================================================================================================================


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


class _Skip(Exception):
    pass


def _device(choice: str) -> torch.device:
    if choice == "cuda" and not torch.cuda.is_available():
        raise GStickerError("--device cuda but no CUDA device is available; use --device cpu or auto")
    if choice == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(choice)


def _tqdm(iterable, desc: str, enabled: bool, total: Optional[int] = None):
    if not enabled:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, desc=desc, total=total, leave=False, file=sys.stderr)


# ---------------------------------------------------------------------------------------------------- images
def read_image(path: Path, max_side: int = 400, min_side: int = 16, max_pixels: int = 1_000_000_000) -> Tuple[Tensor, str]:
    """An image file as ``[3 H W]`` float RGB in [0, 1]; raises ``_Skip(reason)`` when it cannot be used.

    Grayscale is replicated to RGB, alpha is composited on white, 8/16-bit integers are normalised to [0, 1] and
    float (HDR) values are clamped to [0, 1]. Images with a longer side above ``max_side`` are reduced by an
    integer area average while being read in strips (memory stays bounded for any size), then resized exactly.
    """
    import numpy as np
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()
        raise _Skip("not an image OpenImageIO can read")
    notes = []
    try:
        spec = inp.spec()
        w, h, nch = int(spec.width), int(spec.height), int(spec.nchannels)
        if w <= 0 or h <= 0 or nch <= 0:
            raise _Skip(f"empty image ({w}x{h}, {nch} channels)")
        if min(w, h) < min_side:
            raise _Skip(f"too small to carry a mark ({w}x{h} px; needs >= {min_side} px a side, see --min-side)")
        if w * h > max_pixels:
            raise _Skip(f"too large to decode safely ({w}x{h} = {w * h:.3g} px > --max-pixels {max_pixels:.3g})")
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
                raise _Skip("unreadable pixel data (truncated or corrupt file)")
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
                al = a[..., alpha: alpha + 1]
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
        img = torch.nn.functional.interpolate(img[None], size=size, mode="bilinear", antialias=True,
                                              align_corners=False)[0].clamp(0, 1)
    return img, "; ".join(notes)


def list_files(folder: Path) -> List[Path]:
    if folder.is_file():
        return [folder]
    return sorted(p for p in folder.rglob("*") if p.is_file() and not any(part.startswith(".") for part in
                                                                            p.relative_to(folder).parts))


def images_views(folder: Path, max_side: int, min_side: int, max_pixels: int, progress: bool = True) -> Views:
    """Every usable image of a folder (recursive) or a single image file; unusable files are listed as skipped."""
    folder = Path(folder)
    if not folder.exists():
        raise GStickerError(f"--images {folder} does not exist; pass a folder of suspect images")
    files = list_files(folder)
    if not files:
        raise GStickerError(f"--images {folder} holds no files; pass a folder with the suspect images")
    out = Views(kind="images", source=str(folder))
    for p in _tqdm(files, "reading images", progress):
        name = str(p.relative_to(folder)) if p != folder else p.name
        try:
            img, note = read_image(p, max_side=max_side, min_side=min_side, max_pixels=max_pixels)
        except _Skip as s:
            out.skipped.append({"name": name, "reason": str(s)})
            continue
        except (OSError, ValueError, RuntimeError, MemoryError) as e:  # any reader failure is a skip, not a crash
            out.skipped.append({"name": name, "reason": f"could not be read ({type(e).__name__}: {e})"[:200]})
            continue
        out.views.append(View(name=name, image=img, note=note))
    if not out.views:
        reasons = "; ".join(f"{s['name']}: {s['reason']}" for s in out.skipped[:3])
        raise GStickerError(f"no usable image among the {len(files)} files of {folder} ({reasons}"
                            f"{'; ...' if len(out.skipped) > 3 else ''}); pass a folder of renders or screenshots")
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
            img = torch.nn.functional.interpolate(torch.rand(1, 3, cells, cells, generator=g), size=(size, size),
                                                  mode="bicubic", align_corners=False)[0].clamp(0, 1)
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


# ---------------------------------------------------------------------------------------------------- models
def _spawns_workers(target) -> bool:
    from nerfstudio.data.datamanagers.parallel_datamanager import ParallelDataManager

    cls = getattr(target, "__origin__", target)
    return isinstance(cls, type) and issubclass(cls, ParallelDataManager)


def load_run(config_path: Path, data: Optional[Path] = None, device: Optional[torch.device] = None):
    """A run rebuilt like nerfstudio's ``eval_setup`` (test mode), with one-line errors instead of exits."""
    from gsticker_plugin import base_run

    config_path = Path(config_path)
    if config_path.is_dir() and (config_path / "config.yml").is_file():
        config_path = config_path / "config.yml"
    if not config_path.is_file():
        raise GStickerError(f"--load-config {config_path} does not exist; pass RUN/config.yml of the suspect run")
    config = base_run.load_run_config(config_path)
    from nerfstudio.configs.method_configs import all_methods
    from nerfstudio.engine.trainer import TrainerConfig

    if not isinstance(config, TrainerConfig):
        raise GStickerError(f"{config_path} is not a Nerfstudio run config; pass RUN/config.yml")
    if config.method_name not in all_methods:
        raise GStickerError(f"{config_path} was written by method {config.method_name!r}, which is not installed "
                            "here; install its package and retry")
    config.pipeline.datamanager._target = all_methods[config.method_name].pipeline.datamanager._target
    # checkpoint: where the config says, else beside the config (a run folder that was moved)
    candidates = [config.get_checkpoint_dir(), config_path.parent / config.relative_model_dir]
    ckpts: List[Path] = []
    for d in candidates:
        d = Path(d)
        if d.is_dir():
            ckpts = sorted(d.glob("step-*.ckpt"), key=lambda c: int(c.stem.split("-")[1]) if c.stem.split("-")[1].isdigit() else -1)
            if ckpts:
                break
    if not ckpts:
        raise GStickerError(f"the run {config_path.parent} has no checkpoint (no step-*.ckpt in "
                            f"{config_path.parent / config.relative_model_dir}); copy its nerfstudio_models folder")
    ckpt = ckpts[-1]
    dm = config.pipeline.datamanager
    recorded = getattr(dm, "data", None) or getattr(dm.dataparser, "data", None)
    if data is not None:
        if not Path(data).exists():
            raise GStickerError(f"--data {data} does not exist; pass the run's dataset folder")
        dm.data = Path(data)
        if hasattr(dm.dataparser, "data"):
            dm.dataparser.data = Path(data)
    elif recorded is None or not Path(recorded).exists():
        raise GStickerError(f"the run's dataset {recorded} does not exist from here (its cameras are needed); "
                            "pass --data with the run's dataset folder")
    if _spawns_workers(config.pipeline.datamanager._target):
        # nerfacto's ParallelDataManager spawns a worker process that samples training rays nobody reads here, and
        # its __del__ printed a traceback at exit: the same dataparser in nerfstudio's in-process data manager
        from gsticker_plugin.trainer import copy_datamanager

        config.pipeline.datamanager = copy_datamanager(config, None)
    device = device or torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        pipeline = config.pipeline.setup(device=device, test_mode="test")
    except GStickerError:
        raise
    except (FileNotFoundError, OSError) as e:
        raise GStickerError(f"could not load the dataset of {config_path} ({type(e).__name__}: {e}); "
                            "pass --data with the run's dataset folder") from None
    pipeline.eval()
    state = base_run.load_checkpoint_state(ckpt)
    base_run.load_pipeline_strictly(pipeline, state, ckpt)
    pipeline.eval()
    return config, pipeline, ckpt


def select_cameras(pipeline, num_views: int, sampled_share: float, seed: int):
    """``num_views`` cameras: evenly spaced run cameras (train then eval) and sampled orbit poses."""
    from gsticker_plugin.fastpath import orbit_cameras

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
        chosen += [(name, cams[i: i + 1]) for name, cams, i in (own[j] for j in idx)]
        n_sampled = num_views - len(chosen)  # fewer own cameras than asked: fill with sampled poses
    if n_sampled > 0:
        g = torch.Generator().manual_seed(seed)
        cams = dm.train_dataset.cameras
        orbit = orbit_cameras(cams, n_sampled, g)
        chosen += [(f"sampled/{i:03d}", orbit[i: i + 1]) for i in range(n_sampled)]
    return chosen


@torch.no_grad()
def model_views(config_path: Path, num_views: int, sampled_share: float, seed: int, data: Optional[Path],
                device: torch.device, sticker: Optional[bool] = None, progress: bool = True) -> Views:
    """Render ``num_views`` views of a run (sticker as the run has it unless ``sticker`` says otherwise)."""
    if num_views <= 0:
        raise GStickerError(f"--num-views must be positive, got {num_views}")
    if not 0.0 <= sampled_share <= 1.0:
        raise GStickerError(f"--sampled-share must be in [0, 1], got {sampled_share}")
    import contextlib
    import warnings

    with contextlib.redirect_stdout(sys.stderr):  # Nerfstudio's setup chatter; stdout is kept for the verdict
        config, pipeline, ckpt = load_run(config_path, data=data, device=device)
    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
    model = pipeline.model
    cams = select_cameras(pipeline, num_views, sampled_share, seed)
    ctx = model.sticker_enabled(sticker) if (sticker is not None and hasattr(model, "sticker_enabled")) else None
    out = Views(kind="model", source=str(config_path),
                details={"method": config.method_name, "model": type(model).__name__, "checkpoint": str(ckpt),
                         "sticker": (None if not hasattr(model, "sticker_enabled") else
                                     ("off" if sticker is False else "on"))})
    if ctx is not None:
        ctx.__enter__()
    try:
        for name, cam in _tqdm(cams, f"rendering {Path(config_path).parent.name}", progress):
            o = model.get_outputs_for_camera(cam.to(model.device))
            rgb = final_rgb(o).detach().float().clamp(0, 1).cpu()
            out.views.append(View(name=name, image=rgb.permute(2, 0, 1).contiguous()))
    finally:
        if ctx is not None:
            ctx.__exit__(None, None, None)
    out.details["own_cameras"] = sum(1 for v in out.views if not v.name.startswith("sampled/"))
    out.details["sampled_poses"] = sum(1 for v in out.views if v.name.startswith("sampled/"))
    return out


# ================================================================================================================
# decoding and statistics
# ================================================================================================================


def apply_attack(views: Views, spec: str, seed: int) -> None:
    if not spec.strip():
        return
    from gsticker_plugin.attacks import apply_attacks, parse_attack_spec

    try:
        steps = parse_attack_spec(spec)
    except ValueError as e:
        raise GStickerError(f"--attack: {e}") from None
    g = torch.Generator().manual_seed(seed)
    for v in views.views:
        v.image = apply_attacks(v.image[None].float(), steps, generator=g)[0].clamp(0, 1)


@torch.no_grad()
def decode_views(key: OwnerKey, views: Views, device: torch.device) -> Dict[str, Tensor]:
    """Per view: extractor logits -> bits, matches with the key's message, and the classifier's score."""
    heads = key.build_heads().to(device)
    logits, scores = [], []
    for v in views.views:
        img = v.image[None].to(device).float()
        logits.append(heads.decode(img).float().cpu()[0])
        scores.append(torch.sigmoid(heads.classify(img).float()).cpu().reshape(-1)[0])
    lg = torch.stack(logits)
    bits = metrics.decode_bits(lg)
    m = metrics.count_matches(bits, key.message)
    return {"bits": bits, "matches": m, "bit_acc": metrics.bit_accuracy(bits, key.message),
            "pvalues": metrics.binomial_tail_pvalues(m, key.num_bits), "scores": torch.stack(scores)}


def decoder_null(key: OwnerKey, decoder: str) -> Optional[Dict[str, Any]]:
    """The empirical null stored for ``decoder``: the extractor's in ``key.null``, the geometric decoder's in
    ``key.geometry["null"]``, the image decoder's in ``key.geometry["image_null"]`` (each decoder is only ever
    compared with its own null)."""
    if decoder == "geometry":
        return (key.geometry or {}).get("null")
    if decoder == "image":
        return (key.geometry or {}).get("image_null")
    return key.null


def null_summary(key: OwnerKey, fpr: float, decoder: str = "extractor") -> Optional[Dict[str, Any]]:
    """The key's stored empirical null for ``decoder``, and the per-view threshold it implies at ``fpr``."""
    null = decoder_null(key, decoder)
    if not null or not null.get("matches"):
        return None
    m = [int(x) for x in null["matches"]]
    k = key.num_bits
    m_emp = metrics.empirical_threshold(m, fpr, k)
    n = len(m)
    mean = sum(m) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in m) / max(1, n - 1))
    return {
        "n": n, "mean_matches": mean, "sd_matches": sd, "max_matches": max(m),
        "chance_mean": k / 2, "chance_sd": math.sqrt(k) / 2,
        "threshold": m_emp,
        "sources": null.get("sources", []),
        "created": null.get("created"),
        "meaning": (f"smallest match count reached by at most a share {fpr:g} of the {n} unmarked null views; "
                    f"with fpr < 1/n it is one more than the largest null count ({max(m)}); on its own it "
                    f"certifies a per-view FPR of no less than ~{metrics.clopper_pearson_upper(0, n):.2g} "
                    "(95 % upper bound, rule of three), so it only makes the binomial threshold stricter"),
    }


def key_result(key: OwnerKey, key_path: Path, dec: Dict[str, Any], views: Views, fpr: float,
               min_share: float, decoder: str = "extractor") -> Dict[str, Any]:
    k = key.num_bits
    m_theo = metrics.min_matches_for_fpr(k, fpr)
    emp = null_summary(key, fpr, decoder)
    m_emp = emp["threshold"] if emp else None
    m_star = max(m_theo, m_emp) if m_emp is not None else m_theo
    matches = dec["matches"]
    passed = (matches >= m_star).tolist()
    vote = metrics.combine_view_decisions(passed, min_share)
    n = len(passed)
    needed = metrics.views_needed(n, min_share)
    p_model = metrics.vote_pvalue(matches, k, min_share)
    t_stat = metrics.vote_statistic(matches, min_share)
    per_view_fpr_used = metrics.binomial_tail_pvalue(m_star, k)
    if emp is not None:
        exceed = sum(1 for x in decoder_null(key, decoder)["matches"] if int(x) >= m_star)
        emp["exceed_at_used_threshold"] = exceed
        emp["exceed_upper95_at_used_threshold"] = metrics.clopper_pearson_upper(exceed, emp["n"])
    scores = dec.get("scores")
    geo = dec.get("geometry")
    img_fit = dec.get("image")
    per_view = []
    for i, v in enumerate(views.views):
        per_view.append({
            "name": v.name, "matches": int(matches[i]), "num_bits": k, "bit_accuracy": float(dec["bit_acc"][i]),
            "pvalue": float(dec["pvalues"][i]), "score": float(scores[i]) if scores is not None else None,
            "passed": bool(passed[i]), "decoded": bits_to_str(dec["bits"][i]), **({"note": v.note} if v.note else {}),
            **({"geometry": geo[i]} if geo is not None else {}),
            **({"image_fit": img_fit[i]} if img_fit is not None else {}),
        })
    mlist = sorted(int(x) for x in matches.tolist())
    return {
        "key": str(key_path), "owner_id": key.owner_id or Path(key_path).stem, "num_bits": k,
        "verdict": "owned" if vote.passed else "not shown", "owned": bool(vote.passed),
        "thresholds": {"theoretical": m_theo, "empirical": m_emp, "used": m_star,
                       "per_view_fpr_target": fpr, "per_view_fpr_at_used": per_view_fpr_used},
        "views": n, "views_passing": int(sum(passed)), "share_passing": vote.share, "views_needed": needed,
        "min_share": min_share,
        "model_fpr_bound": metrics.combined_fpr_bound(per_view_fpr_used, min_share),
        "model_pvalue": p_model, "vote_statistic": t_stat,
        "matches_min": mlist[0], "matches_median": mlist[n // 2], "matches_max": mlist[-1],
        "mean_bit_accuracy": float(dec["bit_acc"].float().mean()),
        "mean_score": float(scores.float().mean()) if scores is not None else None,
        "decoder": decoder,
        "null_exact": not key.null_caveats(),
        "null_caveats": key.null_caveats(),
        "message_source": key.message_source,
        "empirical_null": emp,
        **({"null_note": (f"the key's empirical null was measured with the extractor and does not apply to the "
                          f"{'geometric' if decoder == 'geometry' else 'image'} decoder; run `ns-verify-owner "
                          f"calibrate --decode {decoder}` to measure its own")}
           if decoder in ("geometry", "image") and emp is None and key.null else {}),
        "per_view": per_view,
    }


def correct_keys(results: List[Dict[str, Any]], fpr: float, min_share: float, correction: str) -> Dict[str, Any]:
    """Several keys: correct the model-level p-values and re-decide each key at the family-wise level."""
    alpha = metrics.combined_fpr_bound(fpr, min_share)
    pv = [r["model_pvalue"] for r in results]
    adj = metrics.holm(pv) if correction == "holm" else metrics.bonferroni(pv)
    for r, a in zip(results, adj):
        emp = r["thresholds"]["empirical"]
        r["adjusted_pvalue"] = float(a)
        r["owned"] = bool(a <= alpha and (emp is None or r["vote_statistic"] >= emp))
        r["verdict"] = "owned" if r["owned"] else "not shown"
    return {"keys": len(results), "correction": correction, "family_wise_fpr": alpha,
            "rule": ("a key is 'owned' when its corrected model-level p-value is <= fpr / min-share and its vote "
                     "statistic also reaches the key's empirical threshold")}


# ================================================================================================================
# report
# ================================================================================================================


def _fmt_p(p: float) -> str:
    return f"{p:.2g}" if p >= 1e-3 or p == 0 else f"{p:.1e}"


def summary_text(report: Dict[str, Any]) -> str:
    lines = []
    owners = report["owned_by"]
    if report["verdict"] == "owned":
        lines.append(f"VERDICT: OWNED by {', '.join(owners)}")
    else:
        lines.append("VERDICT: NOT SHOWN (no key's message is shown at the chosen false-positive rate)")
    inp = report["input"]
    desc = f"{inp['kind']} {inp['source']}: {inp['views']} views"
    if inp["kind"] == "model":
        d = inp.get("details", {})
        desc += f" ({d.get('own_cameras', 0)} run cameras, {d.get('sampled_poses', 0)} sampled poses; {d.get('method')})"
    if inp["skipped"]:
        desc += f"; {len(inp['skipped'])} skipped (listed in report.json)"
    lines.append("  input: " + desc)
    dec = report.get("decoder") or {}
    if dec:
        lines.append(f"  decoder: {dec['kind']} ({dec['description']})")
        for note in dec.get("notes", []):
            lines.append(f"    note: {note}")
    if report["settings"]["attack"] and dec.get("kind") != "geometry":
        lines.append(f"  attack before decoding: {report['settings']['attack']}")
    for r in report["keys"]:
        t = r["thresholds"]
        calib = "ns-verify-owner calibrate" + (f" --decode {r['decoder']}" if r.get("decoder", "extractor") != "extractor"
                                               else "")
        emp = (f"empirical {t['empirical']} from {r['empirical_null']['n']} null views"
               if r["empirical_null"] else f"no empirical null for this decoder (run {calib})")
        lines.append(f"  key {r['owner_id']} ({r['key']}): {r['verdict'].upper()}")
        for c in r.get("null_caveats", []):
            lines.append(f"    weaker claim: {c}")
        lines.append(f"    {r['views_passing']}/{r['views']} views pass ({100 * r['share_passing']:.0f} %; needs "
                     f"{r['views_needed']} = {100 * r['min_share']:.0f} %) at >= {t['used']}/{r['num_bits']} matches "
                     f"(theoretical {t['theoretical']} at per-view FPR {t['per_view_fpr_target']:g}; {emp})")
        best = max(r["per_view"], key=lambda v: v["matches"])
        lines.append(f"    matches min/median/max {r['matches_min']}/{r['matches_median']}/{r['matches_max']} of "
                     f"{r['num_bits']} (best view {best['name']}: p = {_fmt_p(best['pvalue'])}); mean bit accuracy "
                     f"{r['mean_bit_accuracy']:.3f}; " + (f"classifier score {r['mean_score']:.2f}"
                                                          if r["mean_score"] is not None else
                                                          f"classifier not used ({DECODER_NAMES[r.get('decoder', 'geometry')]})"))
        line = (f"    model-level p-value {_fmt_p(r['model_pvalue'])}; FPR of this verdict <= "
                f"{r['model_fpr_bound']:.2g} under any dependence between views")
        if "adjusted_pvalue" in r:
            line += f"; {report['multiple_testing']['correction']}-adjusted p {_fmt_p(r['adjusted_pvalue'])}"
        lines.append(line)
    if report.get("commitment"):
        c = report["commitment"]
        lines.append(f"  commitment {c['given'][:16]}... matches the key: it existed when this commitment was "
                     "published")
    if report.get("multiple_testing"):
        mt = report["multiple_testing"]
        lines.append(f"  {mt['keys']} keys tested, {mt['correction']} correction; family-wise FPR <= "
                     f"{mt['family_wise_fpr']:.2g}")
    for f in report.get("files", []):
        lines.append(f"  wrote {f}")
    return "\n".join(lines)


def write_figure(path: Path, report: Dict[str, Any], views: Views, key: Optional[OwnerKey]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = min(report["keys"], key=lambda x: x["model_pvalue"])  # the most significant key
    k = r["num_bits"]
    n_thumbs = min(4, len(views.views))
    fig = plt.figure(figsize=(12, 7.5))
    gs = fig.add_gridspec(2, max(1, n_thumbs), height_ratios=[1.25, 1.0])
    ax = fig.add_subplot(gs[0, :])
    xs = list(range(k + 1))
    matches = [v["matches"] for v in r["per_view"]]
    ax.hist(matches, bins=[x - 0.5 for x in range(k + 2)], density=True, color="tab:blue", alpha=0.7,
            label=f"suspect views (n={len(matches)})")
    pmf = [math.exp(metrics.log_binomial_tail_pvalue(x, k)) - math.exp(metrics.log_binomial_tail_pvalue(x + 1, k))
           for x in xs]
    ax.plot(xs, pmf, "k-", lw=1.5, label=f"theoretical null Binomial({k}, 1/2)")
    if r["empirical_null"] and key is not None and decoder_null(key, r.get("decoder", "extractor")):
        nm = [int(x) for x in decoder_null(key, r.get("decoder", "extractor"))["matches"]]
        ax.hist(nm, bins=[x - 0.5 for x in range(k + 2)], density=True, histtype="step", color="tab:orange", lw=2,
                label=f"empirical null (n={len(nm)})")
    t = r["thresholds"]
    ax.axvline(t["theoretical"] - 0.5, color="tab:red", ls="--", label=f"theoretical threshold {t['theoretical']}")
    if t["empirical"] is not None:
        ax.axvline(t["empirical"] - 0.5, color="tab:orange", ls=":", label=f"empirical threshold {t['empirical']}")
    ax.set_xlim(-0.5, k + 0.5)
    ax.set_xlabel(f"matching bits (of {k})")
    ax.set_ylabel("share of views")
    ax.set_title(f"{report['verdict'].upper()} - key {r['owner_id']}: {r['views_passing']}/{r['views']} views pass "
                 f">= {t['used']}/{k}; model p = {_fmt_p(r['model_pvalue'])}")
    ax.legend(fontsize=8, loc="upper left")
    order = sorted(range(len(views.views)), key=lambda i: -r["per_view"][i]["matches"])
    picks = order[:n_thumbs]
    for j, i in enumerate(picks):
        a = fig.add_subplot(gs[1, j])
        img = views.views[i].image
        s = THUMB_SIDE / max(img.shape[-2:])
        if s < 1:
            img = torch.nn.functional.interpolate(img[None], scale_factor=s, mode="area")[0]
        a.imshow(img.permute(1, 2, 0).clamp(0, 1).numpy())
        v = r["per_view"][i]
        score = f"score={v['score']:.2f}" if v["score"] is not None else r.get("decoder", "geometry")
        a.set_title(f"{v['name'][-24:]}\n{v['matches']}/{k}  p={_fmt_p(v['pvalue'])}  {score}\n"
                    f"{'PASS' if v['passed'] else 'fail'}", fontsize=8)
        a.axis("off")
    fig.tight_layout()
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    os.replace(tmp, path)


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, allow_nan=False))
    os.replace(tmp, path)


# ================================================================================================================
# commands
# ================================================================================================================


def _load_keys(key: Optional[Path], keys: Optional[Path]) -> List[Tuple[Path, OwnerKey]]:
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
    return [(p, OwnerKey.load(p)) for p in paths]


def _check_stats(fpr: float, min_share: float) -> None:
    if not 0.0 < fpr < 0.5:
        raise GStickerError(f"--fpr must be in (0, 0.5), got {fpr}; e.g. 1e-6")
    if not 0.0 < min_share <= 1.0:
        raise GStickerError(f"--min-share must be in (0, 1], got {min_share}")


def choose_decoder(config: VerifyConfig, keys: List[Tuple[Path, OwnerKey]]) -> Tuple[str, List[str]]:
    """``--decode``: geometry or extractor, and why (auto); one-line errors for impossible choices."""
    from gsticker_plugin import geometry

    if config.cameras is not None and config.images is None:
        raise GStickerError("--cameras gives the cameras of --images; a model (--load-config) is rendered at its own "
                            "cameras: drop --cameras")
    if config.decode in ("geometry", "image"):
        if config.decode == "geometry" and config.load_config is None:
            raise GStickerError("--decode geometry reads a model's geometry, not images: pass --load-config "
                                "SUSPECT/config.yml, or use --decode image --cameras CAMERAS.json with --images")
        if config.decode == "image" and (config.images is None or config.cameras is None):
            raise GStickerError("--decode image reads images at known cameras: pass --images DIR and --cameras "
                                "transforms.json (for a model use --decode geometry)")
        for path, key in keys:
            if not key.geometry:
                raise GStickerError(geometry.missing_geometry_message(path))
        return config.decode, []
    if config.decode == "extractor":
        return "extractor", []
    if config.load_config is None and config.cameras is None:
        return "extractor", ["auto: images without cameras can only be decoded by the extractor (pass --cameras "
                             "transforms.json for the informed image decoder)"]
    kind, what = ("geometry", "geometric") if config.load_config is not None else ("image", "image")
    for path, key in keys:
        if not key.geometry:
            return "extractor", [f"auto: {path} has no geometry reference (version-1 key), so the extractor decodes; "
                                 "add it with `ns-verify-owner export-key`"]
        cfg = Path(config.base_config) if config.base_config is not None else geometry.recorded_base_config(key)
        if cfg is None or not cfg.exists():
            return "extractor", [f"auto: the owner's base run {cfg} is not reachable from here, so the extractor "
                                 f"decodes; pass --base-config BASE_RUN/config.yml for {what} decoding"]
    return kind, []


def _informed_result(key: OwnerKey, path: Path, dec: Dict[str, Any], views: Views, config: VerifyConfig,
                     decoder: str, ref, notes: List[str], bases: List[str]) -> Dict[str, Any]:
    """:func:`key_result` of an informed decoder, with the owner's base run it read against (its notes and path
    are added to ``notes`` and ``bases``)."""
    r = key_result(key, path, dec, views, config.fpr, config.min_share, decoder=decoder)
    r["base"] = {"config": str(ref.config_path), "checkpoint": str(ref.checkpoint), "method": ref.method}
    notes += ref.notes
    bases.append(str(ref.config_path))
    return r


def _verify_geometry(config: VerifyConfig, keys: List[Tuple[Path, OwnerKey]], device: torch.device):
    """Geometric decoding of the suspect run for every key (each against its own base run)."""
    import contextlib
    import warnings

    from gsticker_plugin import geometry

    with contextlib.redirect_stdout(sys.stderr):
        run_cfg, pipeline, ckpt = load_run(config.load_config, data=config.data, device=device)
    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
    model = pipeline.model
    results, views, bases, notes = [], None, [], []
    for path, key in keys:
        ref = geometry.load_base_reference(key, path, config.base_config, config.base_data or config.data, device)
        dec, vlist = geometry.decode_suspect(key, ref, model, config.num_views, config.sampled_share, config.seed,
                                             progress=config.progress)
        kv = Views(kind="model", source=str(config.load_config), views=vlist,
                   details={"method": run_cfg.method_name, "model": type(model).__name__, "checkpoint": str(ckpt),
                            "sticker": "on" if hasattr(model, "sticker_enabled") else None,
                            "own_cameras": sum(1 for v in vlist if not v.name.startswith("sampled/")),
                            "sampled_poses": sum(1 for v in vlist if v.name.startswith("sampled/")),
                            "cameras_of": f"the owner's base run {ref.config_path}"})
        results.append(_informed_result(key, path, dec, kv, config, "geometry", ref, notes, bases))
        views = views or kv
        del ref
    signals = sorted({tuple(g["signals"]) for r in results for g in (v["geometry"] for v in r["per_view"])})
    return results, views, {"bases": bases, "signals": [list(s) for s in signals], "notes": notes}


def posed_views(views: Views, frames: Dict[str, Dict[str, Any]], scale_factor: float) -> Tuple[Views, List[Tuple[str, Any]]]:
    """The images that have a camera in ``frames`` (:func:`gsticker_plugin.image_decoder.read_cameras_file`), each
    with a camera of its own size; the others are added to ``skipped``."""
    from gsticker_plugin.image_decoder import camera_for_image, match_frame

    out = Views(kind=views.kind, source=views.source, skipped=list(views.skipped), details=dict(views.details))
    cams: List[Tuple[str, Any]] = []
    for v in views.views:
        f = match_frame(v.name, frames)
        if f is None:
            out.skipped.append({"name": v.name, "reason": "no camera for it in --cameras (frames are matched by file "
                                                          "name without extension)"})
            continue
        h, w = v.image.shape[-2:]
        try:
            cam = camera_for_image(frames[f], int(h), int(w), scale_factor)
        except GStickerError as e:
            out.skipped.append({"name": v.name, "reason": str(e)})
            continue
        note = f"camera {f}" + (f"; {v.note}" if v.note else "")
        out.views.append(View(name=v.name, image=v.image, note=note))
        cams.append((f"image/{f}/{int(h)}x{int(w)}", cam))
    if not out.views:
        raise GStickerError(f"none of the {len(views.views)} images has a camera in --cameras (frames are matched by "
                            "file name without extension, e.g. r_0.png <-> ./test/r_0); pass the transforms JSON "
                            "of these images")
    out.details["cameras"] = len(cams)
    return out, cams


def decode_images_at_cameras(key: OwnerKey, ref, views: Views, frames: Dict[str, Dict[str, Any]], seed: int,
                             progress: bool) -> Tuple[Views, Dict[str, Any]]:
    """The informed image decoder on the images of ``views`` that have a camera in ``frames``, against the owner's
    base ``ref`` (:func:`gsticker_plugin.geometry.load_base_reference`): the posed views and the decoded bits."""
    import contextlib

    from gsticker_plugin.image_decoder import base_pose_scale, decode_posed_images

    posed, cams = posed_views(views, frames, base_pose_scale(ref))
    with contextlib.redirect_stdout(sys.stderr):
        dec = decode_posed_images(key, ref, [v.image.permute(1, 2, 0) for v in posed.views], cams, seed,
                                  progress=progress)
    return posed, dec


def _verify_images_informed(config: VerifyConfig, keys: List[Tuple[Path, OwnerKey]], views: Views,
                            device: torch.device):
    """The informed image decoder on the images that have a camera in --cameras, for every key (each against its own
    base run)."""
    from gsticker_plugin import geometry
    from gsticker_plugin.image_decoder import read_cameras_file

    frames = read_cameras_file(config.cameras)
    results, used, bases, notes = [], None, [], []
    for path, key in keys:
        ref = geometry.load_base_reference(key, path, config.base_config, config.base_data or config.data, device)
        posed, dec = decode_images_at_cameras(key, ref, views, frames, config.seed, config.progress)
        posed.details["cameras_of"] = str(config.cameras)
        results.append(_informed_result(key, path, dec, posed, config, "image", ref, notes, bases))
        used = used or posed
        del ref
    return results, used, {"bases": bases, "cameras": str(config.cameras), "notes": notes}


def verify(config: VerifyConfig) -> Tuple[int, Dict[str, Any]]:
    """Run ``verify``; returns (exit status, report). Raises GStickerError for bad input."""
    _check_stats(config.fpr, config.min_share)
    if (config.load_config is None) == (config.images is None):
        raise GStickerError("pass exactly one input: --load-config RUN/config.yml or --images DIR")
    if config.max_side < config.min_side or config.min_side < 1:
        raise GStickerError(f"need 1 <= --min-side <= --max-side, got {config.min_side} and {config.max_side}")
    if config.attack.strip():  # fail early on a bad spec, before rendering
        from gsticker_plugin.attacks import parse_attack_spec

        try:
            parse_attack_spec(config.attack)
        except ValueError as e:
            raise GStickerError(f"--attack: {e}") from None
    keys = _load_keys(config.key, config.keys)
    committed = check_commitment(config.commitment, keys)
    device = _device(config.device)
    decoder, notes = choose_decoder(config, keys)
    if decoder == "extractor":
        leaning = [str(p) for p, k in keys if k.owner_message_prob > 0]
        if leaning:
            raise GStickerError(f"{', '.join(leaning)}: its extractor was trained on the owner's message "
                                "(--pipeline.owner-message-prob > 0) and decodes it from unmarked images too; its "
                                "binomial null does not hold: use --decode geometry or --decode image")
    if decoder == "geometry":
        results, views, info = _verify_geometry(config, keys, device)
        notes += info.pop("notes")
        if config.attack.strip():
            notes.append(f"--attack {config.attack!r} not applied: attacks are image-level distortions, and the "
                         "geometric decoder reads the model's geometry, not images")
        decoder_info = {"kind": "geometry", "informed": True, **info,
                        "description": "informed: fits the key's sticker to the suspect's geometry ("
                                       + " + ".join(sorted({n.replace("_", " ") for sig in info["signals"] for n in sig}))
                                       + ") against the owner's unwatermarked base run; model-level only"}
    elif decoder == "image":
        views = images_views(config.images, config.max_side, config.min_side, config.max_pixels, config.progress)
        apply_attack(views, config.attack, config.seed)
        results, views, info = _verify_images_informed(config, keys, views, device)
        notes += info.pop("notes")
        decoder_info = {"kind": "image", "informed": True, **info,
                        "description": "informed: fits the key's sticker to each image's colour change from the "
                                       "owner's unwatermarked base rendered at the image's camera (--cameras)"}
    else:
        if config.load_config is not None:
            views = model_views(config.load_config, config.num_views, config.sampled_share, config.seed, config.data,
                                device, progress=config.progress)
        else:
            views = images_views(config.images, config.max_side, config.min_side, config.max_pixels, config.progress)
        if not views.views:
            raise GStickerError("no view to decode; nothing to base a verdict on")
        apply_attack(views, config.attack, config.seed)
        results = []
        for path, key in _tqdm(keys, "decoding", config.progress and len(keys) > 1):
            dec = decode_views(key, views, device)
            results.append(key_result(key, path, dec, views, config.fpr, config.min_share))
        decoder_info = {"kind": "extractor", "informed": False,
                        "description": "blind: the key's extractor reads the message from RGB "
                                       + ("renders" if views.kind == "model" else "images")}
    decoder_info["notes"] = notes
    report: Dict[str, Any] = {
        "tool": "ns-verify-owner", "created": time.time(),
        "input": {"kind": views.kind, "source": views.source, "views": len(views.views),
                  "skipped": views.skipped, "details": views.details},
        "settings": {"fpr": config.fpr, "min_share": config.min_share, "attack": config.attack,
                     "num_views": config.num_views if views.kind == "model" else None, "seed": config.seed,
                     "correction": config.correction if len(keys) > 1 else None},
        "decoder": decoder_info,
        "commitment": committed,
        "keys": results,
        "multiple_testing": correct_keys(results, config.fpr, config.min_share, config.correction)
        if len(keys) > 1 else None,
    }
    owned = [r["owner_id"] for r in results if r["owned"]]
    report["verdict"] = "owned" if owned else "not shown"
    report["owned_by"] = owned
    report["exit_status"] = EXIT_OWNED if owned else EXIT_NOT_SHOWN
    out = Path(config.output)
    try:
        out.mkdir(parents=True, exist_ok=True)
        files = [str(out / "report.json")]
        if config.figure:
            best = min(range(len(results)), key=lambda i: results[i]["model_pvalue"])
            write_figure(out / "report.png", report, views, keys[best][1])
            files.append(str(out / "report.png"))
        report["files"] = files
        _write_json(out / "report.json", report)
    except OSError as e:
        raise GStickerError(f"cannot write the report to {out} ({e.strerror or e}); pass --output with a "
                            "writable folder") from None
    return report["exit_status"], report


def check_commitment(given: Optional[str], keys: List[Tuple[Path, OwnerKey]]) -> Optional[Dict[str, Any]]:
    """``--commitment HEX`` against the one key given: None without it; a mismatch is an error."""
    if given is None:
        return None
    hex_ = given.strip().lower()
    if len(keys) != 1:
        raise GStickerError("--commitment checks one key: pass it with --key KEY.gskey, not --keys")
    path, key = keys[0]
    if len(hex_) != 64 or set(hex_) - set("0123456789abcdef"):
        raise GStickerError(f"--commitment must be the 64 hex digits printed by `ns-verify-owner commit`, got {given!r}")
    own = commitment(key)
    if own != hex_:
        raise GStickerError(f"{path} does not match the commitment {hex_[:16]}... (its own is {own[:16]}...): this is "
                            "not the key that was committed to; pass the committed key")
    return {"given": hex_, "matches": True, "key": str(path),
            "meaning": "sha256 over a secret salt and the key's message, sticker, heads and base checksum: the key "
                       "existed when this value was published or timestamped"}


@dataclass
class CommitConfig:
    """Print the commitment of an owner key: 64 hex digits to publish or timestamp when the model is released.
    Later, `ns-verify-owner --commitment HEX --key KEY` shows this key existed then (see docs/verify.md)."""

    key: Path
    """The owner key (.gskey) to commit to."""


def commit(config: CommitConfig) -> Dict[str, Any]:
    key = OwnerKey.load(Path(config.key))
    return {"key": str(config.key), "commitment": commitment(key), "message_source": key.message_source,
            "null_caveats": key.null_caveats()}


def calibrate(config: CalibrateConfig) -> Dict[str, Any]:
    """Run ``calibrate``: decode unmarked views with the key and store their match counts in the key."""
    key_path = Path(config.key)
    key = OwnerKey.load(key_path)
    device = _device(config.device)
    if config.decode == "geometry":
        return _calibrate_geometry(config, key_path, key, device)
    if config.decode == "image":
        return _calibrate_image(config, key_path, key, device)
    sources: List[Views] = []
    notes: List[str] = []
    if config.base:
        base_cfg = (key.base or {}).get("config")
        if base_cfg and Path(base_cfg).is_file():
            sources.append(model_views(Path(base_cfg), config.num_views, config.sampled_share, config.seed, None,
                                       device, sticker=False, progress=config.progress))
        else:
            notes.append(f"base run skipped: its config {base_cfg!r} recorded in the key does not exist here "
                         "(pass it with --load-config, or --no-base)")
    for cfg in config.load_config:
        sources.append(model_views(Path(cfg), config.num_views, config.sampled_share, config.seed, None, device,
                                   sticker=False, progress=config.progress))
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
        src_info.append({"kind": s.kind, "source": s.source, "n": len(m), "mean_matches": sum(m) / len(m),
                         "max_matches": max(m), "skipped": len(s.skipped), **({"details": s.details} if s.details else {})})
    return _store_null(config, key_path, key, "extractor", matches, src_info, notes)


def _store_null(config: CalibrateConfig, key_path: Path, key: OwnerKey, decoder: str, matches: List[int],
                src_info: List[Dict[str, Any]], notes: List[str]) -> Dict[str, Any]:
    old = decoder_null(key, decoder) if config.append else None
    if old:
        matches = [int(x) for x in old.get("matches", [])] + matches
        src_info = list(old.get("sources", [])) + src_info
    null = {"version": NULL_FORMAT_VERSION, "num_bits": key.num_bits, "matches": matches, "sources": src_info,
            "created": time.time(), "decoder": decoder}
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
    OwnerKey.load(key_path)  # the rewritten key passes its own fingerprint check
    k = key.num_bits
    return {"key": str(key_path), "backup": str(backup) if backup else None, "null_views": len(matches),
            "decoder": decoder, "sources": src_info, "notes": notes, **distinct_sources(src_info),
            "mean_matches": sum(matches) / len(matches), "max_matches": max(matches),
            "thresholds": {f"{a:g}": {"theoretical": metrics.min_matches_for_fpr(k, a),
                                      "empirical": metrics.empirical_threshold(matches, a, k)}
                           for a in (1e-3, 1e-6, 1e-9)}}


def distinct_sources(src_info: List[Dict[str, Any]]) -> Dict[str, int]:
    """How many *distinct* unmarked models, image folders and synthetic random images a null holds (views of one
    model are not independent samples of the null)."""
    def count(kind: str) -> int:
        return len({str(Path(x["source"]).resolve()) for x in src_info if x["kind"] == kind})

    return {"distinct_models": count("model"), "distinct_image_sources": count("images"),
            "synthetic_views": sum(int(x["n"]) for x in src_info if x["kind"] == "random")}


def _calibrate_geometry(config: CalibrateConfig, key_path: Path, key: OwnerKey, device: torch.device) -> Dict[str, Any]:
    """The geometric decoder's null: decode the unwatermarked base itself and the given (unmarked) runs."""
    import contextlib

    from gsticker_plugin import geometry

    if not key.geometry:
        raise GStickerError(geometry.missing_geometry_message(key_path))
    notes = []
    if config.images or config.random_images:
        notes.append("images skipped: the geometric decoder reads models, not images")
    ref = geometry.load_base_reference(key, key_path, config.base_config, config.data, device)
    runs = ([ref.config_path] if config.base else []) + [Path(c) for c in config.load_config]
    if not runs:
        raise GStickerError("no unmarked run to calibrate the geometric decoder on; keep the base (drop --no-base) "
                            "or pass --load-config OTHER_RUN/config.yml")
    matches: List[int] = []
    src_info = []
    for i, cfg in enumerate(runs):
        with contextlib.redirect_stdout(sys.stderr):
            run_cfg, pipeline, _ = load_run(cfg, data=geometry.data_if_missing(cfg, config.data), device=device)
        dec, _ = geometry.decode_suspect(key, ref, pipeline.model, config.num_views, config.sampled_share,
                                         config.seed + i, sticker=False, progress=config.progress, full_renders=False)
        m = [int(x) for x in dec["matches"].tolist()]
        matches += m
        src_info.append({"kind": "model", "source": str(cfg), "n": len(m), "mean_matches": sum(m) / len(m),
                         "max_matches": max(m), "skipped": 0,
                         "details": {"method": run_cfg.method_name, "sticker": "off",
                                     "undetermined_bits_mean": sum(g["undetermined"] for g in dec["geometry"]) / len(m)}})
    return _store_null(config, key_path, key, "geometry", matches, src_info, notes)


def _calibrate_image(config: CalibrateConfig, key_path: Path, key: OwnerKey, device: torch.device) -> Dict[str, Any]:
    """The image decoder's null: decode unmarked images at their known cameras (--images with --cameras, e.g. the
    base dataset's own photos and its transforms_test.json)."""
    from gsticker_plugin import geometry
    from gsticker_plugin.image_decoder import read_cameras_file

    if not key.geometry:
        raise GStickerError(geometry.missing_geometry_message(key_path))
    if not config.images or config.cameras is None:
        raise GStickerError("--decode image calibrates on unmarked images at known cameras: pass --images DIR "
                            "(e.g. the base dataset's test photos) and --cameras transforms.json")
    notes = []
    if config.load_config:
        notes.append("--load-config runs skipped: the image decoder reads images (render them, e.g. with ns-render "
                     "dataset, and pass them with --images)")
    frames = read_cameras_file(config.cameras)
    ref = geometry.load_base_reference(key, key_path, config.base_config, config.data, device)
    matches: List[int] = []
    src_info = []
    for d in config.images:
        views = images_views(Path(d), config.max_side, config.min_side, config.max_pixels, config.progress)
        posed, dec = decode_images_at_cameras(key, ref, views, frames, config.seed + len(src_info), config.progress)
        m = [int(x) for x in dec["matches"].tolist()]
        matches += m
        src_info.append({"kind": "images", "source": str(d), "n": len(m), "mean_matches": sum(m) / len(m),
                         "max_matches": max(m), "skipped": len(posed.skipped),
                         "details": {"cameras": str(config.cameras)}})
    return _store_null(config, key_path, key, "image", matches, src_info, notes)


@dataclass
class ExportKeyConfig:
    """Add the geometry reference (the sticker, the gates) of a watermarked run to its owner key: a version-1 key
    becomes a version-2 key that `ns-verify-owner --decode geometry` can use. The run must carry the key's
    message and be made on the key's base."""

    load_config: Path
    """The watermarked run (RUN/config.yml written by ns-train geometrysticker) the key belongs to."""
    key: Path
    """The owner key (.gskey) to extend."""
    output: Optional[Path] = None
    """Where the extended key is written (default: the key itself, the previous file kept as KEY.gskey.bak)."""
    data: Optional[Path] = None
    """Dataset folder of the run, when the path recorded in its config.yml does not exist from here."""
    backup: bool = True
    """Keep the previous key file as KEY.gskey.bak when rewriting it in place."""


def export_key(config: ExportKeyConfig) -> Dict[str, Any]:
    import contextlib

    from gsticker_plugin.geometry import geometry_reference

    key_path = Path(config.key)
    key = OwnerKey.load(key_path)
    with contextlib.redirect_stdout(sys.stderr):
        run_cfg, pipeline, ckpt = load_run(config.load_config, data=config.data, device=torch.device("cpu"))
    model = pipeline.model
    if not hasattr(model, "sticker") or not hasattr(model, "final_wrap"):
        raise GStickerError(f"{config.load_config} is a {run_cfg.method_name} run without a sticker; pass the "
                            "watermarked run (ns-train geometrysticker) the key was written for")
    if bool(getattr(model, "folded", False)):
        raise GStickerError(f"{config.load_config} is a shared run (its sticker is folded, it holds no message); its "
                            "owner key already carries the geometry reference: nothing to export")
    if not torch.equal(model.message.cpu().long(), key.message.long()):
        raise GStickerError(f"the run {config.load_config} carries a different message than the key {key_path}; "
                            "pass the watermarked run this key was written for")
    run_sha = dict(run_cfg.pipeline.base_run).get("checkpoint_sha256")
    key_sha = (key.base or {}).get("checkpoint_sha256")
    if run_sha != key_sha:
        raise GStickerError(f"the run {config.load_config} was made on another base than the key {key_path} "
                            "(base checkpoint sha256 differs); pass the watermarked run this key was written for")
    old = key.geometry or {}
    key.geometry = {**geometry_reference(model), "null": old.get("null"),
                    **({"image_null": old["image_null"]} if old.get("image_null") else {})}
    out = Path(config.output) if config.output is not None else key_path
    backup = None
    if out.resolve() == key_path.resolve() and config.backup:
        backup = key_path.with_name(key_path.name + ".bak")
        shutil.copy2(key_path, backup)
    key.save(out)
    OwnerKey.load(out)
    return {"key": str(out), "backup": str(backup) if backup else None, "run": str(config.load_config),
            "checkpoint": str(ckpt), "fields": key.geometry["fields"]}


def calibrate_text(res: Dict[str, Any]) -> str:
    lines = [f"calibrated {res['key']} ({res['decoder']} decoder): {res['null_views']} unmarked views in its null "
             f"(mean {res['mean_matches']:.1f}, max {res['max_matches']} matches; chance mean 24 of 48), from "
             f"{res['distinct_models']} distinct models, {res['distinct_image_sources']} image folders and "
             f"{res['synthetic_views']} synthetic random images"]
    for s in res["sources"]:
        lines.append(f"  {s['kind']} {s['source']}: {s['n']} views, mean {s['mean_matches']:.1f}, max {s['max_matches']}")
    for n in res["notes"]:
        lines.append(f"  note: {n}")
    for a, t in res["thresholds"].items():
        lines.append(f"  per-view FPR {a}: threshold theoretical {t['theoretical']}, empirical {t['empirical']} "
                     f"-> verify uses {max(t['theoretical'], t['empirical'])}")
    if res["backup"]:
        lines.append(f"  previous key kept as {res['backup']}")
    return "\n".join(lines)


def _error(message: str) -> int:
    print("error: " + " ".join(str(message).split()), file=sys.stderr)
    return EXIT_ERROR


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``), run, and return the exit status (0 owned, 1 not shown, 2 error)."""
    import tyro

    from gsticker_plugin import compat

    # numpy scalars in keys/checkpoints (optimizer lr) under weights_only=True; offline-safe LPIPS for stock models
    compat.apply()
    argv = list(sys.argv[1:] if argv is None else argv)
    sub = "verify"
    if argv and argv[0] in ("verify", "calibrate", "export-key", "commit"):
        sub, argv = argv[0], argv[1:]
    try:
        if sub == "calibrate":
            cfg = tyro.cli(CalibrateConfig, args=argv, prog="ns-verify-owner calibrate")
        elif sub == "export-key":
            cfg = tyro.cli(ExportKeyConfig, args=argv, prog="ns-verify-owner export-key")
        elif sub == "commit":
            cfg = tyro.cli(CommitConfig, args=argv, prog="ns-verify-owner commit")
        else:
            cfg = tyro.cli(VerifyConfig, args=argv, prog="ns-verify-owner [verify]",
                           description=(VerifyConfig.__doc__ or "") + "\n\nSubcommands: verify (default), calibrate "
                           "(ns-verify-owner calibrate --help), export-key (adds the geometry reference to a "
                           "version-1 key), commit (prints the key's commitment to publish at release).")
    except SystemExit as e:  # --help (0) or a parse error (tyro prints it; status 2)
        return int(e.code) if isinstance(e.code, int) else EXIT_ERROR
    try:
        if sub == "calibrate":
            res = calibrate(cfg)
            print(calibrate_text(res))
            return 0
        if sub == "commit":
            res = commit(cfg)
            print(res["commitment"])
            print(f"commitment of {res['key']}: publish or timestamp it when you release the model; later "
                  f"`ns-verify-owner --key {res['key']} --commitment HEX ...` shows this key existed then",
                  file=sys.stderr)
            for c in res["null_caveats"]:
                print(f"note: weaker claim: {c}", file=sys.stderr)
            return 0
        if sub == "export-key":
            res = export_key(cfg)
            print(f"wrote {res['key']}: geometry reference of {res['run']} (fields {', '.join(res['fields'])})"
                  + (f"; previous key kept as {res['backup']}" if res["backup"] else ""))
            return 0
        status, report = verify(cfg)
        print(summary_text(report))
        return status
    except GStickerError as e:
        return _error(str(e))
    except KeyboardInterrupt:
        return _error("interrupted; no verdict")
    except MemoryError:
        return _error("out of memory while decoding; lower --max-side or --num-views")
    except Exception as e:  # a crash is never a verdict: one line, exit 2
        import traceback

        frames = traceback.extract_tb(e.__traceback__)
        where = f" at {Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else ""
        return _error(f"no verdict: {type(e).__name__}: {e}{where} (a failure inside ns-verify-owner, not a "
                      "negative verdict; rerun with the same inputs to reproduce and report it)")


def entrypoint() -> None:
    """Console script ``ns-verify-owner``."""
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
