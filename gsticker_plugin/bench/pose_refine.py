"""Seconds and renders per picture of the camera search's two refinements (``python -m gsticker_plugin.bench.pose_refine``).

The shared run of ``bench.shared`` rendered at a few test views of its scene (8-bit PNG), each read without cameras
by :func:`gsticker_plugin.decoders.fieldimage.decode_images` once per refinement of the camera search
(:attr:`gsticker_plugin.decoders.pose.PoseSearch.refine`): ``render`` (a base render per Gauss-Newton step),
``warp`` (the picture warped onto a held render) and ``mixed`` (warp, then the finest stage rendering per step).
Rows go to ``WORK/rows.jsonl`` as they are measured (a rerun continues). The candidates' renders are made once per size, before either is
timed. Per picture: matches, the camera's error, seconds and base renders. The default views are the decoder's
development views (test views 1 to 3, 5), none of the frozen evaluations' views.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Tuple

import torch

from gsticker_plugin.bench import bench_main, command_lines, provenance
from gsticker_plugin.bench.shared_images import read_png, write_png
from gsticker_plugin.machine import config_under


@dataclass
class Args:
    data: Path
    """The base's dataset folder."""
    shared_dir: Path = Path("outputs/bench-shared")
    """bench.shared's work folder: its owner.gskey and shared run (runs/)."""
    work_dir: Path = Path("outputs/bench-pose-refine")
    views: Tuple[int, ...] = (1, 2, 3, 5)
    """Test views rendered and read."""
    refines: Tuple[str, ...] = ("render", "warp", "mixed")
    seed: int = 20261207
    """Decoding seed."""
    output: Path = Path("docs/experiments/bench-pose-refine.md")
    page_only: bool = False
    """Rewrite the page from OUTPUT's JSON (no measuring)."""
    note: str = ""
    """A line for the page under the table (e.g. what else ran on the machine)."""


class RenderCount:
    """Counts the ray-bundle passes asked of ``model`` (``count``; a render is cut into passes of at most
    :data:`gsticker_plugin.decoders.geometric.RAY_CHUNK` rays) and the rays they rendered (``rays``)."""

    def __init__(self, model) -> None:
        self.count = 0
        self.rays = 0
        inner = model.get_outputs_for_camera_ray_bundle

        def counted(bundle):
            self.count += 1
            self.rays += int(bundle.shape[0])
            return inner(bundle)

        model.get_outputs_for_camera_ray_bundle = counted


def measure(args: Args) -> Dict[str, Any]:
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
    shared = load_run(config_under(args.shared_dir / "runs"), data=args.data, device=dev)[1].model.eval()
    counter = RenderCount(ref.model)
    args.work_dir.mkdir(parents=True, exist_ok=True)
    rows_path = args.work_dir / "rows.jsonl"
    rows = [json.loads(line) for line in rows_path.read_text().splitlines()] if rows_path.is_file() else []
    done = {(r["view"], r["refine"]) for r in rows}
    renders: Dict[Tuple[int, int], Any] = {}
    for vi in args.views:
        if all((vi, refine) in done for refine in args.refines):
            continue
        png = args.work_dir / f"test-{vi:03d}.png"
        if not png.is_file():
            with torch.no_grad():
                write_png(png, shared.get_outputs_for_camera(cameras[vi : vi + 1].to(dev))["rgb"].float().cpu())
        image = read_png(png)
        hw = (int(image.shape[0]), int(image.shape[1]))
        if hw not in renders:
            renders[hw] = search_renders(ref, PoseSearch(), hw, value=True)
        for refine in args.refines:
            if (vi, refine) in done:
                continue
            counter.count = counter.rays = 0
            t0 = time.time()
            dec = decode_images(key, ref, [image], args.seed, search=PoseSearch(refine=refine), renders=renders)
            d = dec["image"][0]
            true = cameras.camera_to_worlds[vi].float()
            rows.append(
                {
                    "view": vi,
                    "refine": refine,
                    "matches": int(dec["matches"][0]),
                    "camera_error": float((torch.tensor(d["c2w"]) - true).abs().max()),
                    "pose_rms": d["pose_rms"],
                    "seconds": time.time() - t0,
                    "renders": counter.count,
                    "rays": counter.rays,
                }
            )
            with rows_path.open("a") as f:
                f.write(json.dumps(rows[-1]) + "\n")
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    rows = [r for r in rows if r["view"] in args.views and r["refine"] in args.refines]
    return {
        "views": list(args.views),
        "rows": rows,
        "note": args.note,
        **provenance("gsticker_plugin.bench.pose_refine"),
    }


def page(res: Dict[str, Any]) -> str:
    lines = command_lines(
        "The camera search's refinements: seconds and renders per picture",
        f"{res['date']}, {res['machine']['cpu']}",
        res["json"],
        res["command"],
    )
    lines += [
        f"Pictures of the shared run at test views {', '.join(map(str, res['views']))} (the decoder's development "
        "views), read without cameras once per refinement; the candidates' renders made beforehand. Camera error: the "
        "largest entry of found minus true camera-to-world matrix. Renders: batched base renders after the candidates' "
        "(they do not depend on the machine's load). Seconds: wall clock, compare them within a view.",
        "",
        "| view | refine | matches | camera error | seconds | renders |",
        "|---|---|---|---|---|---|",
    ]
    for r in res["rows"]:
        lines.append(
            f"| {r['view']} | {r['refine']} | {r['matches']}/48 | {r['camera_error']:.1e} | {r['seconds']:.0f} | "
            f"{r['renders']} |"
        )
    lines.append("")
    if res.get("note"):
        lines += [res["note"], ""]
    return "\n".join(lines)


def main() -> None:
    bench_main(Args, measure, page)


if __name__ == "__main__":
    main()
