"""Recolor edits of any Nerfstudio run as library functions (``ns-recolor``'s subcommands call them).

Each ``*Args`` dataclass is one edit; :func:`apply_edit` writes its run (or images) and returns 0. Bad input raises
:class:`gsticker_plugin.errors.GStickerError`. See docs/recolor.md.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import List, Tuple, Union

import numpy as np
import torch
from nerfstudio.utils.rich_utils import CONSOLE

from gsticker_plugin.attacks import hue_shift
from gsticker_plugin.background import background_of
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.recolor import palette as P
from gsticker_plugin.recolor import runs
from gsticker_plugin.recolor.configs import HUE_METHOD, PALETTE_METHOD, FinetuneArgs, HueArgs, PaletteArgs, PaletteEdit
from gsticker_plugin.recolor.finetune import finetune_color, ray_schedule, render_ray_targets, split_color_parameters
from gsticker_plugin.recolor.model import ColorWrap, require_color_fields, unwrap


def say(msg: str) -> None:
    CONSOLE.print(f"\\[ns-recolor] {msg}", highlight=False)


# ---------------------------------------------------------------------------------------------- palette


def extract_palette_of(args: PaletteEdit, model, dataset, seed: int):
    """The palette ``ns-recolor palette`` extracts for ``args`` (training images' foreground, or the model's renders)."""
    P.check_k(args.k)
    n = min(args.max_views, len(dataset))
    if args.source == "images":
        px = runs.foreground_pixels(runs.training_images(dataset, n))
    else:
        r = runs.render_views(
            model, dataset.cameras, range(n), desc="rendering for the palette", outputs=("rgb", "accumulation")
        )
        px = torch_cat([rgb[acc[..., 0] > 0.5] for rgb, acc in zip(r["rgb"], r["accumulation"])])
    return P.extract_palette(px, k=args.k, seed=seed)


def torch_cat(items):
    return torch.cat(items)


def edited_palette(args: PaletteEdit, pal) -> List[Tuple[float, float, float]]:
    """The palette ``pal`` with ``args``' edits (``--set`` / ``--palette``) applied, as RGB triples."""
    edits = P.parse_edits(args.set_, args.palette, pal.k)
    src = [tuple(c) for c in pal.rgb.tolist()]
    return [edits.get(i, src[i]) for i in range(pal.k)]


def cmd_palette(args: PaletteArgs) -> int:
    P.check_k(args.k)
    run_cfg, run_dir, _ = runs.check_input_config(args.load_config)
    if not args.list_:
        out = runs.check_output_dir(args.output_dir, run_dir, args.overwrite)
        if not args.set_ and not args.palette:
            raise GStickerError(
                "no edit given; pass --set INDEX=COLOR (e.g. --set 0=blue) or --palette C0 C1 ..., "
                "or --list to see the palette first"
            )
        for spec in args.set_:  # malformed colors stop here, before any model is built
            if "=" in spec:
                P.parse_color(spec.split("=", 1)[1])
        for c in args.palette:
            if c.strip().lower() not in P.KEEP:
                P.parse_color(c)
    config, pipeline, run_dir, ckpt, step = runs.build_recolor_run(args.load_config, args.data, PALETTE_METHOD)
    model = pipeline.model
    pal = extract_palette_of(args, model, pipeline.datamanager.train_dataset, args.seed)
    say(
        f"palette of {pal.k} colors ({'chosen per scene' if args.k is None else '--k'}) from the training "
        f"{args.source} of {run_dir}:"
    )
    for line in pal.describe():
        print(f"  {line}")
    if args.list_:
        swatch = Path(args.swatch) if args.swatch is not None else Path("palette.png")
        swatch.parent.mkdir(parents=True, exist_ok=True)
        P.write_png(swatch, P.swatch_image([pal.rgb.tolist()]))
        say(f"swatch: {swatch}")
        return 0
    target = edited_palette(args, pal)
    model.config.palette_source = [P.to_hex(c) for c in pal.rgb.tolist()]
    model.config.palette_target = [P.to_hex(c) for c in target]
    model.config.softness = float(args.softness)
    set_model_palette(model)
    say(f"edit: {model.edit_summary()}")
    cfg_path = runs.write_run(
        config,
        model,
        step,
        out,
        "palette",
        run_dir,
        extra_files={
            "palette.png": lambda p: P.write_png(
                p, P.swatch_image([model.palette_source.tolist(), model.palette_target.tolist()])
            )
        },
    )
    _done(cfg_path)
    return 0


def set_model_palette(model) -> None:
    """Buffers from the model's config (hex lists), so that config.yml and checkpoint agree."""

    src = torch.tensor([P.parse_color(c) for c in model.config.palette_source], dtype=torch.float32).reshape(-1, 3)
    tgt = torch.tensor([P.parse_color(c) for c in model.config.palette_target], dtype=torch.float32).reshape(-1, 3)
    model.palette_source = src.to(model.device)  # registered buffers: assignment replaces them
    model.palette_target = tgt.to(model.device)
    model.softness.fill_(float(model.config.softness))
    model.hue_shift.fill_(float(model.config.hue_shift))


def _done(cfg_path: Path) -> None:
    say(f"recolored run: {cfg_path}")
    say(f"open it with: ns-viewer --load-config {cfg_path}   (or ns-render ..., ns-verify-owner ...)")


# ---------------------------------------------------------------------------------------------- hue


def cmd_hue(args: HueArgs) -> int:
    P.check_hue_shift(args.shift)
    run_cfg, run_dir, _ = runs.check_input_config(args.load_config)
    out = runs.check_output_dir(args.output_dir, run_dir, args.overwrite)
    if args.image_level:
        return _hue_images(args, out)
    config, pipeline, run_dir, ckpt, step = runs.build_recolor_run(args.load_config, args.data, HUE_METHOD)
    model = pipeline.model
    model.config.hue_shift = float(args.shift)
    set_model_palette(model)
    say(f"edit: {model.edit_summary()}")
    cfg_path = runs.write_run(config, model, step, out, "hue", run_dir)
    _done(cfg_path)
    return 0


def _hue_images(args: HueArgs, out: Path) -> int:
    loaded = runs.load_run(args.load_config, args.data)
    dm = loaded.pipeline.datamanager
    if args.split == "train":
        cameras = dm.train_dataset.cameras
    else:
        parser = dm.dataparser  # the run's own dataparser, for the eval split asked for
        cameras = parser.get_dataparser_outputs(split=args.split).cameras
    n = cameras.shape[0] if args.limit is None else min(args.limit, cameras.shape[0])
    g = torch.Generator().manual_seed(args.seed)
    if args.fixed:
        shifts = torch.full((n,), float(args.shift))
    else:
        shifts = (torch.rand(n, generator=g) * 2.0 - 1.0) * abs(float(args.shift))
    rendered = runs.render_views(loaded.pipeline.model, cameras, range(n), desc=f"rendering {args.split}")["rgb"]
    staged = runs.StagedDir(out)
    try:
        record = []
        for i, (img, s) in enumerate(zip(rendered, shifts.tolist())):
            jittered = hue_shift(img.permute(2, 0, 1)[None].float(), float(s))[0].permute(1, 2, 0)
            name = f"{args.split}_{i:04d}.png"
            P.write_png(staged.tmp / name, (jittered * 255).round().to(torch.uint8))
            record.append({"image": name, "camera_index": i, "hue_shift_turns": round(float(s), 6)})
        (staged.tmp / "hue_jitter.json").write_text(
            json.dumps(
                {
                    "run": str(Path(args.load_config).resolve()),
                    "split": args.split,
                    "seed": args.seed,
                    "max_shift": abs(float(args.shift)),
                    "fixed": args.fixed,
                    "images": record,
                },
                indent=1,
            )
        )
        staged.commit()
    except BaseException:
        staged.abort()
        raise
    say(f"{n} hue-jittered renders ({'shift' if args.fixed else 'jitter +-'}{abs(args.shift):g} turns) in {out}")
    return 0


# ---------------------------------------------------------------------------------------------- finetune


def _target_images(folder: Path, dataset, size) -> List:

    folder = Path(folder)
    if not folder.is_dir():
        raise GStickerError(
            f"--targets {folder} is not a folder; pass a folder of edited images, one per training view"
        )
    suffixes = {".png", ".jpg", ".jpeg"}
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in suffixes)
    names = [Path(f).stem for f in dataset._dataparser_outputs.image_filenames]
    by_stem = {p.stem: p for p in files}
    if all(n in by_stem for n in names):
        chosen = [by_stem[n] for n in names]
    elif len(files) == len(names):
        chosen = files
    else:
        raise GStickerError(
            f"--targets {folder} has {len(files)} images, not one per training view ({len(names)}, named "
            f"like {names[0]}.png); name them like the training images or give one per view in order"
        )
    # deferred: only PNG writing needs it
    from PIL import Image

    out = []
    for p in chosen:
        im = torch.from_numpy(
            np.asarray(Image.open(p).convert("RGBA" if Image.open(p).mode in ("RGBA", "LA") else "RGB"))
        )
        im = im.float() / 255.0
        if tuple(im.shape[:2]) != tuple(size):
            raise GStickerError(
                f"target image {p.name} is {im.shape[1]}x{im.shape[0]} but the training views are "
                f"{size[1]}x{size[0]}; give targets at the training resolution"
            )
        out.append(im)
    return out


def cmd_finetune(args: FinetuneArgs) -> int:
    P.check_k(args.k)
    has_palette = bool(args.set_ or args.palette)
    chosen = [bool(args.targets), has_palette, args.hue_shift is not None]
    if sum(chosen) != 1:
        raise GStickerError(
            "finetune needs exactly one kind of target: --targets DIR (edited images), a palette edit "
            "(--set INDEX=COLOR / --palette ...), or --hue-shift S"
        )
    if args.hue_shift is not None:
        P.check_hue_shift(args.hue_shift, "--hue-shift")
    if args.steps < 1:
        raise GStickerError(f"--steps {args.steps} must be at least 1")
    run_cfg, run_dir, _ = runs.check_input_config(args.load_config)
    out = runs.check_output_dir(args.output_dir, run_dir, args.overwrite)
    snapshots = {}
    for n_at in sorted(set(args.save_at)):
        if not 1 <= n_at < args.steps:
            raise GStickerError(
                f"--save-at {n_at} must be between 1 and --steps - 1 ({args.steps - 1}); the run after "
                f"{args.steps} steps is --output-dir itself"
            )
        snapshots[n_at] = runs.check_output_dir(out.parent / f"{out.name}-step{n_at}", run_dir, args.overwrite)
    loaded = runs.load_run(args.load_config, args.data)
    model = loaded.pipeline.model
    dataset = loaded.pipeline.datamanager.train_dataset
    cameras = dataset.cameras
    n = min(args.max_views, len(dataset))
    require_color_fields(unwrap(model))
    bg = background_of(model).image_color()
    size = (int(cameras.height[0]), int(cameras.width[0]))
    if args.targets:
        targets = [runs.composite_on(t, bg) for t in _target_images(args.targets, dataset, size)][:n]
        what = f"the images in {args.targets}"
    else:
        if has_palette:
            pal = extract_palette_of(args, model, dataset, args.seed)
            target = edited_palette(args, pal)
            src = P.rgb_to_lab(pal.rgb)
            tgt = P.rgb_to_lab(torch.tensor(target, dtype=torch.float32))
            soft = float(args.softness)
            transform = lambda rgb: P.recolor(rgb, src.to(rgb), tgt.to(rgb), soft)  # noqa: E731
            what = (
                "palette-edited renders ("
                + ", ".join(
                    f"{i}: {P.to_hex(a)} -> {P.to_hex(b)}"
                    for i, (a, b) in enumerate(zip(pal.rgb.tolist(), target))
                    if P.to_hex(a) != P.to_hex(b)
                )
                + ")"
            )
        else:
            shift = float(args.hue_shift)
            transform = lambda rgb: P.hue_rotate(rgb, shift).to(rgb.dtype)  # noqa: E731
            what = f"hue-rotated renders ({shift:+g} turns)"
        # the edited model's colors at the pixels the fine-tune visits (its rays do not depend on the model)
        schedule = ray_schedule(n, size, args.steps, args.rays_per_step, args.seed)
        wraps = [ColorWrap(f, transform) for _, f in require_color_fields(unwrap(model))]
        try:
            targets = render_ray_targets(model, cameras[:n], schedule)
        finally:
            for w in reversed(wraps):
                w.remove()
    color, density = split_color_parameters(model, cameras)
    say(
        f"fine-tuning {sum(p.numel() for p in color.values())} color parameters ({len(color)} tensors: "
        f"{', '.join(sorted({k.rsplit('.', 1)[0] for k in color}))}); {len(density)} density tensors and everything "
        f"else frozen; toward {what}; {args.steps} steps"
    )
    cfg = loaded.config  # the run's own config: the output is a run of the same method

    def write(dest: Path, steps: int, loss: List[float]) -> Path:
        k = max(1, min(10, len(loss) // 5))
        return runs.write_run(
            cfg,
            model,
            loaded.step,
            dest,
            "finetune",
            run_dir,
            extra_files={
                "finetune.json": lambda p: p.write_text(
                    json.dumps(
                        {
                            "wrapped_run": str(Path(args.load_config).resolve()),
                            "targets": what,
                            "steps": steps,
                            "lr": args.lr,
                            "rays_per_step": args.rays_per_step,
                            "seed": args.seed,
                            "color_parameters": sorted(color),
                            "loss_first": loss[:k],
                            "loss_last": loss[-k:],
                        },
                        indent=1,
                    )
                )
            },
        )

    def on_step(step: int, loss: List[float]) -> None:
        if step in snapshots:
            say(f"after {step} steps: {write(snapshots[step], step, loss)}")

    t0 = time.time()
    hist = finetune_color(
        model,
        cameras[:n],
        targets,
        args.steps,
        lr=args.lr,
        rays_per_step=args.rays_per_step,
        seed=args.seed,
        color_params=color,
        on_step=on_step if snapshots else None,
    )
    k = max(1, min(10, len(hist["loss"]) // 5))
    say(f"loss {sum(hist['loss'][:k]) / k:.5f} -> {sum(hist['loss'][-k:]) / k:.5f} in {time.time() - t0:.0f} s")
    _done(write(out, args.steps, hist["loss"]))
    return 0


# ---------------------------------------------------------------------------------------------- entry point


def apply_edit(args: Union[PaletteArgs, HueArgs, FinetuneArgs]) -> int:
    """Run one edit (palette, hue or finetune); 0 when its output is written."""
    if isinstance(args, PaletteArgs):
        return cmd_palette(args)
    if isinstance(args, HueArgs):
        return cmd_hue(args)
    return cmd_finetune(args)
