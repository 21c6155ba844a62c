"""Evaluation stage ``wild``: pictures found in the wild, read without cameras, under the registered protocol
(docs/experiments/images-wild-protocol.md; the draws: :mod:`gsticker_plugin.evaluation.wild`).

The suspects are the shared run of ``ns-train geometrysticker`` on the primary base (the field mark; its message
drawn with ``secrets`` by ``ns-train``) and its ``ns-recolor`` copies (the recolor protocol's palettes and model-level
hue turns, and one colour fine-tune). Each is rendered at the drawn test cameras (base intrinsics), framed, put
through each row's attack, saved as 8-bit PNG (JPEG where the row says) and read back from the file by
:func:`gsticker_plugin.decoders.fieldimage.decode_images` with no camera. The null: the unmarked base's pictures
(framed and JPEG 50 rows), the scene's ground-truth test photographs framed the same way, and random pictures of the
drawn sizes; each decoded once.

Every decode is one line of ``wild/rows.jsonl``, written as it is measured: an interrupted stage goes on where it
stopped; the stage's JSON sums the lines when all are there.
"""

from __future__ import annotations

import contextlib
import json
import math
import shutil
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Tuple

import numpy as np
import torch
from PIL import Image

from gsticker_plugin import metrics
from gsticker_plugin.evaluation import wild as W
from gsticker_plugin.evaluation.workspace import Workspace

NULL_ROWS = ("framed", "JPEG 50")
"""The rows of the base's own pictures in the null."""


def shared_run(ws: Workspace) -> Tuple[Path, Path]:
    """``ns-train geometrysticker`` on the primary base (skipped when done): the shared run's config and owner key."""
    from gsticker_plugin.machine import config_under, console_script
    from gsticker_plugin.runs import latest_checkpoint

    work = ws.out / "wild" / "shared"
    key = work / "owner.gskey"
    if not key.is_file() or not list((work / "runs").glob("**/config.yml")):
        if work.exists():
            shutil.rmtree(work)
        work.mkdir(parents=True)
        base = ws.base_config(ws.primary)
        ckpt = latest_checkpoint(base.parent / "nerfstudio_models")
        cmd = [
            console_script("ns-train"),
            "geometrysticker",
            "--load-checkpoint",
            str(ckpt),
            "--data",
            str(ws.scene_dir),
        ]
        cmd += ["--machine.device-type", ws.p.device, "--vis", "tensorboard", "--output-dir", str(work / "runs")]
        cmd += ["--experiment-name", "wild", "--timestamp", "shared", "--pipeline.key-path", str(key)]
        ws.run_cmd(cmd, "wild-shared")
    return config_under(work / "runs"), key


def null_bases(ws: Workspace) -> List[Tuple[str, Path, Path]]:
    """The null's independently trained bases (``(name, config, data)``): the scene trained again with each of the
    stage's ``null_seeds``, and with ``other_scene`` a base of the generated scene; each trained once."""
    from gsticker_plugin.machine import config_under, console_script

    spec = ws.p.wild
    work = ws.out / "wild" / "nulls"
    jobs = [(f"independent base seed {s}", ws.scene_dir, ["--machine.seed", str(s)]) for s in spec.null_seeds]
    if spec.other_scene:
        scene = work / "scene"
        if not (scene / "transforms_test.json").is_file():
            cmd = [console_script("ns-gsticker-scene"), "--output-dir", str(scene), "--resolution", "100"]
            ws.run_cmd(cmd + ["--num-train", "100", "--num-val", "10", "--num-test", "30"], "wild-null-scene")
        jobs.append(("other scene base", scene, []))
    out = []
    for name, data, extra in jobs:
        runs = work / name.replace(" ", "-")
        if not list(runs.glob("**/nerfstudio_models/step-*.ckpt")):
            cmd = [console_script("ns-train"), spec.null_preset, "--data", str(data), "--output-dir", str(runs)]
            cmd += ["--machine.device-type", ws.p.device, "--vis", "tensorboard", "--timestamp", "base"]
            cmd += ["--max-num-iterations", str(spec.null_steps), *extra]
            ws.run_cmd(cmd, f"wild-null-{name.replace(' ', '-')}")
        out.append((name, config_under(runs), Path(data)))
    return out


def recolor_edits(ws: Workspace) -> List[Dict[str, Any]]:
    """The recolored copies: the recolor protocol's palette edits and model-level hue turns, and one colour
    fine-tune of its length (no snapshots)."""
    from gsticker_plugin.recolor.configs import FinetuneArgs, HueArgs, PaletteArgs

    rc = ws.p.recolor
    if rc is None:
        return []
    out = [
        {"name": f"palette-{c.replace(' ', '')}", "edit": (PaletteArgs, {"set_": (f"{rc.palette_entry}={c}",)})}
        for c in rc.colors
    ]
    out += [{"name": f"hue-{h:+g}", "edit": (HueArgs, {"shift": float(h)})} for h in rc.model_hue]
    ft = rc.finetune
    if ft is not None:
        tgt = {"set_": (f"{rc.palette_entry}={ft.color}",)} if ft.color is not None else {"hue_shift": ft.hue_shift}
        fields = {**tgt, "steps": int(ft.steps), "rays_per_step": int(ft.rays_per_step)}
        if ft.max_views is not None:
            fields["max_views"] = int(ft.max_views)
        out.append({"name": f"finetune-{ft.steps}steps", "edit": (FinetuneArgs, fields)})
    return out


def recolored_run(ws: Workspace, shared: Path, edit: Dict[str, Any]) -> Path:
    """The ``ns-recolor`` copy ``edit`` of the shared run (made once, kept under wild/recolored/)."""
    from gsticker_plugin.recolor.edits import apply_edit

    dest = ws.out / "wild" / "recolored" / edit["name"]
    found = list(dest.glob("*/*/*/config.yml"))
    if found:
        return found[0]
    if dest.exists():
        shutil.rmtree(dest)
    kind, fields = edit["edit"]
    ws.say(f"  recolor {edit['name']}: {shared} -> {dest}")
    with contextlib.redirect_stdout(sys.stderr):
        apply_edit(kind(load_config=shared, output_dir=dest, data=ws.scene_dir, **fields))
    (cfg,) = list(dest.glob("*/*/*/config.yml"))
    return cfg


def random_picture(i: int, size: Tuple[int, int]) -> Image.Image:
    """The ``i``-th random null picture of ``size`` (width, height): noise, smooth noise, a flat colour or a
    gradient in turn, from a generator seeded with the registered seed and ``i``."""
    g = np.random.default_rng([W.REGISTERED_SEED, i])
    w, h = size
    kind = i % 4
    if kind == 0:
        x = g.random((h, w, 3))
    elif kind == 1:
        small = g.random((max(2, h // 8), max(2, w // 8), 3))
        return Image.fromarray((small * 255).astype(np.uint8)).resize((w, h), Image.BICUBIC)
    elif kind == 2:
        x = np.broadcast_to(g.random(3), (h, w, 3))
    else:
        t = np.linspace(0.0, 1.0, w)[None, :, None]
        x = g.random(3) * (1 - t) + g.random(3) * t
        x = np.broadcast_to(x, (h, w, 3))
    return Image.fromarray((np.asarray(x) * 255 + 0.5).astype(np.uint8))


def save_png(rgb: torch.Tensor, path: Path) -> None:
    """A render ``[H W 3]`` in [0, 1] as an 8-bit PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((rgb.float().cpu().clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)).save(path)


def _picture(path: Path, make) -> torch.Tensor:
    """The picture at ``path`` (made by ``make`` and saved as a PNG first when missing; a JPEG row's picture is
    already the decoded JPEG), read back from the file."""
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.stem + ".tmp.png")
        make().save(tmp)
        tmp.replace(path)
    return torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0)


def rotation_error_degrees(a: torch.Tensor, b: torch.Tensor) -> float:
    """The angle between two camera-to-world rotations ``[3 4]`` (degrees)."""
    r = a[:3, :3].double().T @ b[:3, :3].double()
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(r)) - 1.0) / 2.0))))


def run(ws: Workspace) -> Dict[str, Any]:
    from gsticker_plugin.decoders.fieldimage import decode_images
    from gsticker_plugin.decoders.fieldmark import load_field_reference
    from gsticker_plugin.decoders.viewbank import bank_folder
    from gsticker_plugin.key import OwnerKey
    from gsticker_plugin.runs import load_run

    spec = ws.p.wild
    work = ws.out / "wild"
    work.mkdir(parents=True, exist_ok=True)
    shared, key_path = shared_run(ws)
    key = OwnerKey.load(key_path)
    ref = load_field_reference(key, key_path, None, ws.scene_dir, ws.device)
    test = ref.pipeline.datamanager.eval_dataset
    cameras = test.cameras
    base_hw = (int(cameras.height[0]), int(cameras.width[0]))
    views = [v for v in range(len(cameras)) if v not in spec.development_views]
    framings = W.draw_framings(views, base_hw, spec.seed, spec.views)
    (work / "framings.json").write_text(json.dumps([f.as_dict() for f in framings], indent=1))
    rows_path = work / "rows.jsonl"
    done = (
        {(r["suspect"], r["row"], r["i"]) for r in map(json.loads, rows_path.read_text().splitlines())}
        if (rows_path.is_file())
        else set()
    )
    renders: Dict[Tuple[int, int], Any] = {}
    bank = bank_folder(key_path)

    def render_of(name: str, config: Path, f: W.Framing, data: Optional[Path] = None) -> Image.Image:
        """The suspect's render at the framing's test camera (for another scene's run, its own test camera
        ``f.view`` modulo their count); a suspect's first call loads it once and renders every drawn view."""
        folder = work / "renders" / name.replace(" ", "-")
        path = folder / f"view-{f.view:03d}.png"
        if not path.is_file():
            with contextlib.redirect_stdout(sys.stderr):
                pipe = load_run(config, data=data or ws.scene_dir, device=ws.device)[1]
            cams = pipe.datamanager.eval_dataset.cameras if data is not None else cameras
            for v in sorted({g.view for g in framings}):
                c = v % len(cams)
                with torch.no_grad():
                    rgb = pipe.model.eval().get_outputs_for_camera(cams[c : c + 1].to(ws.device))["rgb"]
                save_png(rgb, folder / f"view-{v:03d}.png")
        return Image.open(path).convert("RGB")

    def framed_row(name: str, config: Path, f: W.Framing, row: str, i: int) -> Image.Image:
        return W.ROWS[row](W.frame(render_of(name, config, f), f), i)

    nulls = null_bases(ws)
    same_scene = [n for n in nulls if n[2] == ws.scene_dir]
    other = [n for n in nulls if n[2] != ws.scene_dir]

    def ground_truth(f: W.Framing) -> Image.Image:
        img = test.get_image_float32(f.view)
        if img.shape[-1] == 4:
            img = img[..., :3] * img[..., 3:] + (1.0 - img[..., 3:])
        return Image.fromarray((img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))

    def jobs() -> Iterator[Tuple[str, str, int, str, Any]]:
        """(suspect, row, i, marked|null, picture maker), in the order they are measured: view by view the shared
        run's rows and the null's pictures of that view, then the recolored copies, then the random pictures."""
        same = [("base", ws.base_config(ws.primary))] + [(n, c) for n, c, d in same_scene]
        for i, f in enumerate(framings):
            for row in spec.rows:
                yield "shared", row, i, "marked", partial(framed_row, "shared", shared, f, row, i)
            for name, config in same:
                for row in NULL_ROWS:
                    yield name, row, i, "null", partial(framed_row, name, config, f, row, i)
            yield "ground truth", "framed", i, "null", partial(lambda f: W.frame(ground_truth(f), f), f)
            for name, config, data in other:
                yield (
                    name,
                    "framed",
                    i,
                    "null",
                    partial(lambda n, c, d, f: W.frame(render_of(n, c, f, d), f), name, config, data, f),
                )
        for edit in recolor_edits(ws):
            for i, f in enumerate(framings):
                make = partial(
                    lambda e, f, i: framed_row(e["name"], recolored_run(ws, shared, e), f, "framed", i), edit, f, i
                )
                yield edit["name"], "framed", i, "marked", make
        for i in range(spec.random_pictures):
            f = framings[i % len(framings)]
            yield "random", "random", i, "null", (lambda i=i, f=f: random_picture(i, (f.width, f.height)))

    for suspect, row, i, kind, make in jobs():
        if (suspect, row, i) in done:
            continue
        path = work / "pictures" / suspect.replace(" ", "-") / row.replace(" ", "_").replace("%", "pc") / f"{i:02d}.png"
        picture = _picture(path, make)
        t0 = time.time()
        dec = decode_images(key, ref, [picture], spec.decode_seed, renders=renders, bank=bank)
        d = dec["image"][0]
        f = framings[i % len(framings)]
        truth = cameras.camera_to_worlds[f.view]
        on_scene = suspect not in ("random",) and suspect not in {n for n, c, d in other}
        line = {
            "suspect": suspect,
            "row": row,
            "i": i,
            "kind": kind,
            "view": f.view if suspect != "random" else None,
            "size": [int(picture.shape[1]), int(picture.shape[0])],
            "matches": int(dec["matches"][0]),
            "camera": d.get("camera"),
            "color_map": d.get("color_map"),
            "degradation": d.get("degradation"),
            "rotation_error_deg": rotation_error_degrees(torch.tensor(d["c2w"]), truth) if on_scene else None,
            "seconds": time.time() - t0 - float(d.get("view_bank_seconds") or 0.0),
            "view_bank_seconds": d.get("view_bank_seconds"),
        }
        with rows_path.open("a") as fh:
            fh.write(json.dumps(line) + "\n")
        ws.say(f"  wild {suspect} / {row} / {i}: {line['matches']}/48 ({line['seconds']:.0f} s)")
    lines = [json.loads(x) for x in rows_path.read_text().splitlines()]
    return summary(lines, ws.threshold, framings)


def summary(lines: List[Dict[str, Any]], threshold: int, framings: List[W.Framing]) -> Dict[str, Any]:
    """Per (suspect, row): bit accuracy, views passing, seconds; the null's spread and false-positive rate."""
    groups: Dict[Tuple[str, str], List[Dict[str, Any]]] = {}
    for r in lines:
        groups.setdefault((r["suspect"], r["row"]), []).append(r)
    rows = []
    for (suspect, row), rs in groups.items():
        m = np.array([r["matches"] for r in rs])
        s = np.array([r["seconds"] for r in rs])
        rows.append(
            {
                "suspect": suspect,
                "row": row,
                "kind": rs[0]["kind"],
                "pictures": len(rs),
                "bit_acc": float(m.mean() / 48),
                "passing": float((m >= threshold).mean()),
                "min_matches": int(m.min()),
                "seconds_median": float(np.median(s)),
                "seconds_p90": float(np.percentile(s, 90)),
            }
        )
    null = np.array([r["matches"] for r in lines if r["kind"] == "null"])
    fp = int((null >= threshold).sum()) if null.size else 0
    return {
        "framings": [f.as_dict() for f in framings],
        "threshold": threshold,
        "rows": rows,
        "null": {
            "pictures": int(null.size),
            "mean": float(null.mean()) if null.size else None,
            "std": float(null.std()) if null.size else None,
            "max": int(null.max()) if null.size else None,
            "at_least_36": int((null >= 36).sum()),
            "false_positives": fp,
            "fpr_upper_95": metrics.clopper_pearson_upper(fp, int(null.size)) if null.size else None,
        },
        "seconds_all": [r["seconds"] for r in lines],
    }
