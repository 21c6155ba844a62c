"""How well the informed image decoder can separate a run's bits: the Gram of the render's per-bit change.

    python -m gsticker_plugin.bench.conditioning --runs outputs/amp30m36 outputs/cond1m39 --data ../shared/data/lego100

For each watermarked run (``RUN/bench/geometrysticker/watermarked/config.yml`` and its ``.gskey`` beside it, as
``bench.targets`` writes them), at held-out orbit views (the camera seed of ``bench.unposed``): the eigenvalues of
``J^T J`` (J: the render's change per bit at the owner's corner, the columns of the image fit), the standard deviation
of each bit's least-squares estimate under white image noise of std ``--noise``, and the matches the informed image
decoder reads given the true camera (posed) under each attack. Writes a Markdown page and a JSON beside it.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch
import tyro

from gsticker_plugin import compat, metrics
from gsticker_plugin.decoders.image import decode_posed_images, image_change_jacobian, image_reference
from gsticker_plugin.decoders.reference import any_reference_view, cpu_sticker, load_base_reference
from gsticker_plugin.evaluation.held_out import renders_8_bit, view_attack
from gsticker_plugin.fastpath import novel_cameras
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.machine import machine_info
from gsticker_plugin.runs import load_run
from gsticker_plugin.sticker import message_to_signs
from gsticker_plugin.views import progress_bar


@dataclass
class BenchConditioningConfig:
    """Gram statistics and posed readings of watermarked runs under image attacks."""

    runs: Tuple[Path, ...]
    """Output folders of ``bench.targets`` (or ``ns-train geometrysticker --experiment-name bench --timestamp
    watermarked``) runs."""
    data: Optional[Path] = None
    """The dataset, when the recorded path does not exist from here."""
    views: Tuple[int, ...] = (0, 1)
    """Held-out orbit views (indices among ``bench.unposed``'s 24)."""
    attacks: Tuple[str, ...] = ("noise=0.1", "jpeg=50", "blur=1")
    """Attack specs read posed."""
    noise: float = 0.1
    """Image noise std of the bits' estimate deviation."""
    camera_seed: int = 12345
    num_views: int = 24
    output: Path = Path("docs/experiments/bench-conditioning.md")


def gram_stats(jac: torch.Tensor, noise: float) -> Dict[str, float]:
    """Trace and eigenvalues of ``J^T J`` and the bits' least-squares standard deviation at white noise ``noise``."""
    g = jac.double().T @ jac.double()
    ev = torch.linalg.eigvalsh(g)
    std = noise * torch.sqrt(torch.diagonal(torch.linalg.inv(g + 1e-12 * float(ev[-1]) * torch.eye(g.shape[0]))))
    return {
        "trace": float(ev.sum()),
        "eig_min": float(ev[0]),
        "eig_median": float(ev.median()),
        "eig_max": float(ev[-1]),
        "bit_std_median": float(std.median()),
        "bits_std_below_0.4": int((std < 0.4).sum()),
    }


def bench_run(cfg: BenchConditioningConfig, run: Path) -> Dict[str, Any]:
    config = run / "bench/geometrysticker/watermarked/config.yml"
    key_path = run / "bench/geometrysticker/watermarked.gskey"
    if not config.exists() or not key_path.exists():
        raise SystemExit(
            f"error: {run} holds no {config.relative_to(run)} and {key_path.relative_to(run)}: pass the "
            "--output-dir of a bench.targets run"
        )
    key = OwnerKey.load(key_path)
    with contextlib.redirect_stdout(sys.stderr):
        _, pipe, _ = load_run(config, data=cfg.data, device=torch.device("cpu"))
        ref = load_base_reference(key, key_path, None, cfg.data, torch.device("cpu"))
    cams = novel_cameras(
        pipe.datamanager.train_dataset.cameras, cfg.num_views, torch.Generator().manual_seed(cfg.camera_seed)
    )
    sticker, background = cpu_sticker(ref.model), ref.model.background_color()
    signs = message_to_signs(key.message).float()
    out: Dict[str, Any] = {"run": str(run), "views": []}
    for i in progress_bar(list(cfg.views), f"views of {run}", True):
        cam = cams[i : i + 1]
        with pipe.model.sticker_enabled(True):
            marked = renders_8_bit(pipe.model, cam)[0]
        with pipe.model.sticker_enabled(False):
            clean = renders_8_bit(pipe.model, cam)[0]
        r = image_reference(any_reference_view(ref, f"view{i}", cam, {}), background)
        row: Dict[str, Any] = {
            "view": i,
            "psnr_db": float(metrics.psnr(marked.permute(2, 0, 1)[None], clean.permute(2, 0, 1)[None])[0]),
            "gram": gram_stats(image_change_jacobian(r, sticker, signs), cfg.noise),
            "posed_matches": {},
        }
        for spec in cfg.attacks:
            img, _ = view_attack(marked, spec, i, clean)  # bench.unposed's draw for view i (its seed 0)
            d = decode_posed_images(key, ref, [img], [(f"view{i}", cam)], 0)
            row["posed_matches"][spec] = int(d["matches"][0])
        out["views"].append(row)
        print(f"{run} view {i}: {json.dumps(row)}", file=sys.stderr)
    return out


def main(cfg: BenchConditioningConfig) -> Dict[str, Any]:
    compat.apply()
    warnings.filterwarnings("ignore")
    t0 = time.time()
    res = {
        "command": "python -m gsticker_plugin.bench.conditioning " + " ".join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_info(),
        "noise": cfg.noise,
        "runs": [bench_run(cfg, Path(run)) for run in cfg.runs],
    }
    res["seconds"] = round(time.time() - t0, 1)
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    js = cfg.output.with_suffix(".json")
    js.write_text(json.dumps(res, indent=1))
    lines: List[str] = [
        "# How separable are the bits? The Gram of the render's per-bit change",
        "",
        f"Command ({res['date']}, {res['machine'].get('cpu', '')}; numbers in [{js.name}]({js.name})):",
        "",
        "```bash",
        res["command"],
        "```",
        "",
        "J: the render's change per bit at the owner's corner at a held-out orbit view (the image fit's columns); "
        f"bit std: the standard deviation of each bit's least-squares estimate under white noise of std {cfg.noise} "
        "(1 is a bit's size); posed: the informed image decoder's matches given the true camera.",
        "",
        "| run | view | PSNR (dB) | trace | eigenvalues min / median / max | bit std median | "
        + " | ".join(f"posed {a}" for a in cfg.attacks)
        + " |",
        "|---|---|---|---|---|---|" + "---|" * len(cfg.attacks),
    ]
    for run in res["runs"]:
        for v in run["views"]:
            gm = v["gram"]
            lines.append(
                f"| {run['run']} | {v['view']} | {v['psnr_db']:.2f} | {gm['trace']:.2f} | {gm['eig_min']:.1e} / "
                f"{gm['eig_median']:.1e} / {gm['eig_max']:.2f} | {gm['bit_std_median']:.2f} | "
                + " | ".join(str(v["posed_matches"][a]) for a in cfg.attacks)
                + " |"
            )
    cfg.output.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main(tyro.cli(BenchConditioningConfig))
