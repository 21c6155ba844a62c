"""Pictures framed unlike the base's cameras, read without cameras (``python -m gsticker_plugin.bench.framed``).

The shared run of ``bench.shared`` rendered at a few test views (8-bit PNG at the base's size), then framed the way a
re-poster would (Pillow): as rendered, a 16:9 crop, a portrait crop, a letterbox into a 16:9 frame, a 1.3x zoomed
16:9 crop (also saved as JPEG 50), a 2x upscaled 4:3 crop saved as JPEG 85, the square saved as JPEG 50 and blurred by
a 1 px Gaussian. Each picture is read by
:func:`gsticker_plugin.decoders.fieldimage.decode_images` with no camera (``ns-verify-owner --images``'s path); the
unmarked base's picture of the same view and framing beside it. Rows go to ``WORK/rows.jsonl`` as they are measured
(a rerun continues). The default views are the image decoder's development views, none of the frozen evaluation's.
"""

from __future__ import annotations

import io
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Tuple

import torch

from gsticker_plugin.bench import bench_main, command_lines, provenance
from gsticker_plugin.bench.shared_images import write_png
from gsticker_plugin.machine import config_under


@dataclass
class Args:
    data: Path
    """The base's dataset folder."""
    shared_dir: Path = Path("outputs/bench-shared")
    """bench.shared's work folder: its owner.gskey and shared run (runs/)."""
    work_dir: Path = Path("outputs/bench-framed")
    views: Tuple[int, ...] = (1, 2)
    """Test views rendered, framed and read."""
    seed: int = 20261207
    """Decoding seed."""
    framings: Tuple[str, ...] = ()
    """Only these framings (names as on the page); all by default."""
    recolored: Tuple[str, ...] = ()
    """Recolored copies of the shared run read beside it, as ``NAME=CONFIG`` (``ns-recolor``'s config.yml)."""
    output: Path = Path("docs/experiments/bench-framed.md")
    page_only: bool = False
    """Rewrite the page from OUTPUT's JSON (no measuring)."""
    note: str = ""
    """A line for the page under the table (e.g. what else ran on the machine)."""


def _jpeg(image, quality: int):
    from PIL import Image

    buf = io.BytesIO()
    image.save(buf, "JPEG", quality=quality)
    buf.seek(0)
    return Image.open(buf).convert("RGB")


def framings() -> Dict[str, Callable]:
    """Name -> what a re-poster does to a square render (a Pillow image): its framing, or a filter."""
    from PIL import Image, ImageFilter

    def letterbox(im):
        w, h = im.size
        out = Image.new("RGB", (round(h * 16 / 9), h), (0, 0, 0))
        out.paste(im, ((out.size[0] - w) // 2, 0))
        return out

    def zoomed(im):
        w, h = im.size
        z = im.resize((round(1.3 * w), round(1.3 * h)), Image.BICUBIC)
        zh = round(z.size[0] * 9 / 16)
        return z.crop((0, (z.size[1] - zh) // 2, z.size[0], (z.size[1] - zh) // 2 + zh))

    def upscaled(im):
        w, h = im.size
        u = im.resize((2 * w, 2 * h), Image.BICUBIC)
        uh = round(2 * w * 3 / 4)
        return _jpeg(u.crop((0, (2 * h - uh) // 2, 2 * w, (2 * h - uh) // 2 + uh)), 85)

    def crop(aspect: float):
        def f(im):
            w, h = im.size
            if aspect >= 1:
                ch = round(w / aspect)
                return im.crop((0, (h - ch) // 2, w, (h - ch) // 2 + ch))
            cw = round(h * aspect)
            return im.crop(((w - cw) // 2, 0, (w - cw) // 2 + cw, h))

        return f

    return {
        "as rendered": lambda im: im,
        "16:9 crop": crop(16 / 9),
        "9:16 crop": crop(9 / 16),
        "16:9 letterbox": letterbox,
        "1.3x zoom, 16:9 crop": zoomed,
        "2x upscale, 4:3 crop, JPEG 85": upscaled,
        "1.3x zoom, 16:9 crop, JPEG 50": lambda im: _jpeg(zoomed(im), 50),
        "JPEG 50": lambda im: _jpeg(im, 50),
        "blur 1 px": lambda im: im.filter(ImageFilter.GaussianBlur(1.0)),
    }


def measure(args: Args) -> Dict[str, Any]:
    import numpy as np
    from PIL import Image

    from gsticker_plugin.decoders.fieldimage import decode_images
    from gsticker_plugin.decoders.fieldmark import load_field_reference
    from gsticker_plugin.decoders.pose import PoseSearch, search_renders
    from gsticker_plugin.key import OwnerKey
    from gsticker_plugin.runs import load_run

    dev = torch.device("cpu")
    key_path = args.shared_dir / "owner.gskey"
    key = OwnerKey.load(key_path)
    ref = load_field_reference(key, key_path, None, args.data, dev)
    cameras = ref.pipeline.datamanager.eval_dataset.cameras
    models = {
        "shared": load_run(config_under(args.shared_dir / "runs"), data=args.data, device=dev)[1].model.eval(),
        "base": ref.model,
    }
    for entry in args.recolored:
        name, sep, config = entry.partition("=")
        if not sep or not Path(config).is_file():
            raise SystemExit(f"--recolored takes NAME=CONFIG with an existing config.yml, got {entry!r}")
        models[name] = load_run(Path(config), data=args.data, device=dev)[1].model.eval()
    args.work_dir.mkdir(parents=True, exist_ok=True)
    rows_path = args.work_dir / "rows.jsonl"
    rows = [json.loads(line) for line in rows_path.read_text().splitlines()] if rows_path.is_file() else []
    done = {(r["view"], r["framing"], r["model"]) for r in rows}
    h0, w0 = int(cameras.height[0]), int(cameras.width[0])
    t0 = time.time()
    renders = {(h0, w0): search_renders(ref, PoseSearch(), (h0, w0), value=True)}
    bank_seconds = time.time() - t0
    for vi in args.views:
        for model_name, model in models.items():
            png = args.work_dir / f"{model_name}-{vi:03d}.png"
            if not png.is_file():
                with torch.no_grad():
                    write_png(png, model.get_outputs_for_camera(cameras[vi : vi + 1].to(dev))["rgb"].float().cpu())
            square = Image.open(png).convert("RGB")
            for name, frame in framings().items():
                if (vi, name, model_name) in done or (args.framings and name not in args.framings):
                    continue
                framed = frame(square)
                framed.save(args.work_dir / f"{model_name}-{vi:03d}-{len(rows):03d}.png")
                picture = torch.from_numpy(np.asarray(framed, dtype=np.float32) / 255.0)
                t1 = time.time()
                dec = decode_images(key, ref, [picture], args.seed, renders=renders)
                d = dec["image"][0]
                rows.append(
                    {
                        "view": vi,
                        "framing": name,
                        "model": model_name,
                        "size": [int(picture.shape[1]), int(picture.shape[0])],
                        "matches": int(dec["matches"][0]),
                        "read": d.get("read", "render"),
                        "color_map": d.get("color_map", False),
                        "pose_rms": d["pose_rms"],
                        "seconds": time.time() - t1,
                    }
                )
                with rows_path.open("a") as f:
                    f.write(json.dumps(rows[-1]) + "\n")
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    rows = [r for r in rows if r["view"] in args.views and r["model"] in models]
    return {
        "views": list(args.views),
        "models": list(models),
        "rows": rows,
        "view_bank_seconds": bank_seconds,
        "note": args.note,
        **provenance("gsticker_plugin.bench.framed"),
    }


def page(res: Dict[str, Any]) -> str:
    models = res.get("models", ["shared", "base"])
    headers = [{"shared": "shared run", "base": "base"}.get(m, f"{m} (recolored)") for m in models]
    lines = command_lines(
        "Pictures framed unlike the base's cameras, read without cameras",
        f"{res['date']}, {res['machine']['cpu']}",
        res["json"],
        res["command"],
    )
    lines += [
        f"The lego100 shared run (field mark) and its unmarked base, rendered at test views "
        f"{', '.join(map(str, res['views']))} (the image decoder's development views: development evidence, not the "
        "frozen evaluation), framed as a re-poster would and read with no camera. Read: how the fit that left the "
        "least modelled the picture (`render`: the base rendered at the picture's camera; `framing`: rendered at the "
        "base's own intrinsics and resized like the picture). Recolored: `ns-recolor` copies of the shared run, read "
        "through a colour map of the base's sample colours where one explains the picture. OWNED needs 41/48. "
        "Each cell: matches, and wall-clock seconds per picture "
        f"(the view bank, {res['view_bank_seconds']:.0f} s, built beforehand).",
        "",
        "| view | framing | size | " + " | ".join(headers) + " | read (shared) |",
        "|---|---|---|" + "---|" * (len(headers) + 1),
    ]
    by = {(r["view"], r["framing"], r["model"]): r for r in res["rows"]}
    for (view, name, model), r in by.items():
        if model != "shared":
            continue
        cells = []
        for m in models:
            o = by.get((view, name, m))
            cells.append(f"{o['matches']}/48, {o['seconds']:.0f} s" if o else "-")
        lines.append(f"| {view} | {name} | {r['size'][0]}x{r['size'][1]} | {' | '.join(cells)} | {r['read']} |")
    lines.append("")
    if res.get("note"):
        lines += [res["note"], ""]
    return "\n".join(lines)


def main() -> None:
    bench_main(Args, measure, page)


if __name__ == "__main__":
    main()
