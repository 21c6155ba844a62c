"""Pictures of the shared run read without cameras (``python -m gsticker_plugin.bench.shared_images``).

Fixed before any of these images was read: the test views ``--views`` (default every 8th from 4, 25 views; the image
decoder was developed on test views 1 to 3 only), each suspect rendered there by its own model (stock Nerfstudio
render, 8-bit PNG), and every PNG read back from the file alone, with the decoder's defaults
(:func:`gsticker_plugin.decoders.fieldimage.decode_images`: camera search, two rounds of the fit with the pose
Jacobian). Suspects: the shared run and owner key of ``bench.shared`` (``--shared-dir``), the unmarked base and each
``--null`` (independently trained bases): distinct images, each counted once.

The views go in turn, every suspect at each, so a partial run holds marked and unmarked images alike. Rows go to
``WORK/rows.jsonl`` as they are measured (a rerun continues); writes a Markdown page and its JSON.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Tuple

import numpy as np
import torch

from gsticker_plugin.bench import bench_main, command_lines, provenance, suspect_summary
from gsticker_plugin.machine import config_under

FROZEN_REFINE = "render"
"""The camera search's refinement as it was when the run was frozen (a Gauss-Newton step renders the base)."""


@dataclass
class Args:
    base: Path
    """The base run's config.yml."""
    data: Path
    """Its dataset folder."""
    shared_dir: Path = Path("outputs/bench-shared")
    """bench.shared's work folder: its owner.gskey and shared run (runs/)."""
    work_dir: Path = Path("outputs/bench-shared-images")
    views: Tuple[int, ...] = tuple(range(4, 200, 8))
    """Test views rendered and read (fixed before the run)."""
    null: Tuple[Path, ...] = ()
    """Independently trained bases of the same scene (config.yml)."""
    seed: int = 20261208
    """Decoding seed."""
    output: Path = Path("docs/experiments/bench-shared-images.md")
    page_only: bool = False
    """Rewrite the page from OUTPUT's JSON (no measuring)."""
    rows_only: bool = False
    """Write the page from the rows measured so far (no measuring): a partial run's page says how far it got."""
    refine: str = FROZEN_REFINE
    """The camera search's refinement (:attr:`gsticker_plugin.decoders.pose.PoseSearch.refine`; ``auto`` is the
    decoder's default now)."""
    note: str = ""
    """A line for the page (e.g. that nothing else ran on the machine: the page then quotes the seconds)."""


def write_png(path: Path, rgb: torch.Tensor) -> None:
    """``rgb`` [H W 3] in [0, 1] as an 8-bit PNG."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((rgb.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)).save(path)


def read_png(path: Path) -> torch.Tensor:
    """An 8-bit PNG as [H W 3] in [0, 1]."""
    from PIL import Image

    return torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0)


def measure(args: Args) -> Dict[str, Any]:
    from gsticker_plugin.decoders.fieldimage import decode_images
    from gsticker_plugin.decoders.fieldmark import load_field_reference
    from gsticker_plugin.decoders.pose import PoseSearch
    from gsticker_plugin.key import OwnerKey
    from gsticker_plugin.runs import load_run

    dev = torch.device("cpu")
    search = PoseSearch(refine=args.refine)  # type: ignore[arg-type]
    key_path = args.shared_dir / "owner.gskey"
    key = OwnerKey.load(key_path)
    suspects = [("shared run", config_under(args.shared_dir / "runs")), ("unmarked base", args.base)]
    suspects += [(f"independent base {n.parent.parent.parent.name}", n) for n in args.null]
    rows_path = args.work_dir / "rows.jsonl"
    if args.rows_only:
        return result(args, key, suspects, rows_path)
    ref = load_field_reference(key, key_path, None, args.data, dev)
    args.work_dir.mkdir(parents=True, exist_ok=True)
    done = (
        {(r["suspect"], r["view"]) for r in map(json.loads, rows_path.read_text().splitlines())}
        if (rows_path.is_file())
        else set()
    )
    models: Dict[str, Any] = {}
    cameras = ref.pipeline.datamanager.eval_dataset.cameras
    renders: Dict[Tuple[int, int], Any] = {}
    for vi in args.views:
        for s, (label, cfg) in enumerate(suspects):
            if (label, vi) in done:
                continue
            png = args.work_dir / "images" / str(s) / f"test-{vi:03d}.png"
            if not png.is_file():
                if label not in models:
                    with contextlib.redirect_stdout(sys.stderr):
                        models[label] = load_run(cfg, data=args.data, device=dev)[1].model.eval()
                with torch.no_grad():
                    out = models[label].get_outputs_for_camera(cameras[vi : vi + 1].to(dev))
                write_png(png, out["rgb"].float().cpu())
            t0 = time.time()
            dec = decode_images(key, ref, [read_png(png)], args.seed, search=search, renders=renders)
            d = dec["image"][0]
            row = {
                "suspect": label,
                "view": vi,
                "image": str(png),
                "matches": int(dec["matches"][0]),
                "explained": d["explained"],
                "round": d["round"],
                "pose_rms": d["pose_rms"],
                "camera_error": float((torch.tensor(d["c2w"]) - cameras.camera_to_worlds[vi].float()).abs().max()),
                "seconds": time.time() - t0 - d.get("view_bank_seconds", 0.0),
                "view_bank_seconds": d.get("view_bank_seconds", 0.0),
            }
            with rows_path.open("a") as f:
                f.write(json.dumps(row) + "\n")
            print(f"test view {vi} {label}: {row['matches']}/48", file=sys.stderr, flush=True)
    return result(args, key, suspects, rows_path)


def result(args: Args, key, suspects, rows_path: Path) -> Dict[str, Any]:
    """The bench's JSON from the rows measured (all of them, or so far)."""
    from gsticker_plugin import metrics

    rows = [json.loads(line) for line in rows_path.read_text().splitlines()] if rows_path.is_file() else []
    return {
        "shared_dir": str(args.shared_dir),
        "views": list(args.views),
        "suspects": [s[0] for s in suspects],
        "rows": rows,
        "complete": len(rows) == len(args.views) * len(suspects),
        "refine": args.refine,
        "note": args.note,
        "threshold": metrics.min_matches_for_fpr(key.num_bits, 1e-6),
        **provenance("gsticker_plugin.bench.shared_images"),
    }


def summary(res: Dict[str, Any], label: str) -> Dict[str, Any]:
    rows = [r for r in res["rows"] if r["suspect"] == label]
    out = suspect_summary(rows, res["threshold"])
    if rows:
        out["camera_error_max"] = max(r["camera_error"] for r in rows)
        seconds = torch.tensor([float(r["seconds"]) for r in rows])
        out["seconds_median"] = float(seconds.median())
        out["seconds_p90"] = float(torch.quantile(seconds, 0.9))
    return out


def page(res: Dict[str, Any]) -> str:
    lines = command_lines(
        "Pictures of the shared run, read without cameras",
        f"{res['date']}, {res['machine']['cpu']}",
        res["json"],
        res["command"],
    )
    if not res.get("complete", True):
        lines += [
            f"**Partial**: {len(res['rows'])} of {len(res['views']) * len(res['suspects'])} images read so far (the same "
            "command without --rows-only continues from its rows).",
            "",
        ]
    lines += [
        f"Test views {res['views'][0]}, {res['views'][1]}, ..., {res['views'][-1]} ({len(res['views'])}, fixed before "
        "the run; the decoder was developed on test views 1 to 3). Each suspect rendered at them by its own model, "
        "saved as an 8-bit PNG and read from the file alone: the camera found against the owner's base, then the "
        f"field-mark image fit. A view passes at >= {res['threshold']}/48 (per-view FPR 1e-6); a suspect is OWNED "
        "when half its views pass. Camera error: the largest entry of found minus true camera-to-world matrix. "
        f"Camera search refinement: `{res.get('refine', FROZEN_REFINE)}`.",
        "",
    ]
    timed = bool(res.get("note"))
    head = "| suspect | images | passing | bit accuracy | matches min / median / max | verdict | camera error (max) |"
    lines += [head + (" seconds median / p90 |" if timed else ""), "|---" * (8 if timed else 7) + "|"]
    for label in res["suspects"]:
        s = summary(res, label)
        if not s["views"]:
            lines.append(f"| {label} | 0 | | | | not read yet | |")
            continue
        lines.append(
            f"| {label} | {s['views']} | {s['passing']} | {100 * s['bit_acc']:.2f} % | {s['min']} / "
            f"{s['median']:g} / {s['max']} | {s['verdict']} | {s['camera_error_max']:.1e} |"
            + (f" {s['seconds_median']:.0f} / {s['seconds_p90']:.0f} |" if timed else "")
        )
    if timed:
        lines += [
            "",
            f"{res['note']} Seconds: the whole decode of a picture (camera search and fit); the view bank (built on the first picture) apart.",
            "",
        ]
    else:
        lines += [
            "",
            "Each image's seconds (camera search and fit) are in the JSON; this page quotes none: time an image with the "
            "machine alone.",
            "",
        ]
    return "\n".join(lines)


def main() -> None:
    bench_main(Args, measure, page)


if __name__ == "__main__":
    main()
