"""The evaluation workspace: paths, resumable stages, cached renders and the decoders every stage calls.

Runs the evaluation protocol stage by stage; every stage is skipped when its output exists (resumable).

Layout of ``output_dir``::

    scene/                      generated scene (when the protocol generates one)
    runs/<base>/<method>/base/  bases trained here;  runs/<base>/geometrysticker/watermarked/ (+ .gskey)
    recolored/<base>/<edit>/    ns-recolor runs (deleted once rendered unless recolor.keep_runs)
    cache/*.pt                  rendered views (so stages can be re-run without re-rendering)
    stages/<stage>.json         each stage's numbers; results.json is their union
    logs/                       ns-train / ns-gsticker-scene logs
    results.json, results.md, charts/*.png
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import json
import math
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from gsticker_plugin import attacks, metrics
from gsticker_plugin.attacks import apply_attacks
from gsticker_plugin.decoders.geometric import decode_suspect
from gsticker_plugin.decoders.image import decode_posed_images
from gsticker_plugin.decoders.reference import load_base_reference
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.evaluate import decode_images
from gsticker_plugin.evaluation.baselines.colormark import decode_color_suspect
from gsticker_plugin.evaluation.config import Protocol
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.machine import console_script
from gsticker_plugin.runs import final_rgb, latest_checkpoint, load_run
from gsticker_plugin.views import progress_bar


def finite_or_none(x: float) -> Any:
    """JSON has no inf/nan: inf -> "inf", nan -> None."""
    x = float(x)
    if math.isnan(x):
        return None
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return x


class Workspace:
    """An evaluation's output folder and the services its stages share: resumable stages, caches, runs, decoders."""

    def __init__(
        self, protocol: Protocol, progress: bool = True, redo: Sequence[str] = (), log: Callable[[str], None] = print
    ):
        self.p = protocol
        self.out = Path(protocol.output_dir)
        self.progress = progress
        self.redo = set(redo)
        self.say = log
        self.device = torch.device(protocol.device)
        for d in ("stages", "cache", "logs", "charts", "runs"):
            (self.out / d).mkdir(parents=True, exist_ok=True)
        self.timings: Dict[str, float] = {}

        self.threshold = metrics.min_matches_for_fpr(48, protocol.fpr)

    # ------------------------------------------------------------------------------------------ plumbing

    def stage_path(self, name: str) -> Path:
        return self.out / "stages" / f"{name}.json"

    def stage(self, name: str, fn: Callable[[], Dict[str, Any]]) -> Dict[str, Any]:
        path = self.stage_path(name)
        if path.is_file() and name not in self.redo:
            self.say(f"[eval] {name}: done earlier ({path})")
            return json.loads(path.read_text())
        self.say(f"[eval] {name} ...")
        t0 = time.time()
        res = fn()
        res = dict(res)
        res["seconds"] = round(time.time() - t0, 2)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(res, indent=1, default=str))
        os.replace(tmp, path)
        self.say(f"[eval] {name}: {res['seconds']:.0f} s")
        return res

    def run_cmd(self, cmd: List[str], log_name: str) -> None:
        log = self.out / "logs" / f"{log_name}.log"
        self.say("  $ " + " ".join(cmd))
        env = dict(os.environ, PYTHONWARNINGS="ignore", COLUMNS="250")
        t0 = time.time()
        with open(log, "w") as f:
            proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env)
        if proc.returncode != 0:
            sys.stderr.write("\n".join(log.read_text(errors="replace").splitlines()[-15:]) + "\n")
            raise GStickerError(
                f"{Path(cmd[0]).name} {' '.join(cmd[1:2])} failed (exit {proc.returncode}); "
                f"its last lines are above, the full log is {log}"
            )
        self.say(f"    done in {time.time() - t0:.0f} s (log: {log})")

    def cached(self, name: str, fn: Callable[[], Dict[str, Tensor]]) -> Dict[str, Tensor]:
        path = self.out / "cache" / f"{name}.pt"
        if path.is_file():
            return torch.load(path, map_location="cpu", weights_only=True)
        res = fn()
        tmp = path.with_suffix(".tmp")
        torch.save(res, tmp)
        os.replace(tmp, path)
        return res

    # ------------------------------------------------------------------------------------------ paths
    @property
    def scene_dir(self) -> Path:
        return Path(self.p.scene.data) if self.p.scene.data is not None else self.out / "scene"

    def base_config(self, name: str) -> Path:
        spec = next(b for b in self.p.bases if b.name == name)
        if spec.config is not None:
            return Path(spec.config)
        return self.out / "runs" / name / spec.preset / "base" / "config.yml"

    def wm_dir(self, name: str) -> Path:
        return self.out / "runs" / name / "geometrysticker" / "watermarked"

    def key_path(self, name: str) -> Path:
        return self.wm_dir(name).with_name("watermarked.gskey")

    @staticmethod
    def latest_ckpt(run_dir: Path) -> Optional[Path]:
        return latest_checkpoint(run_dir / "nerfstudio_models")

    # ------------------------------------------------------------------------------------------ models
    def load(self, config: Path):

        with contextlib.redirect_stdout(sys.stderr):
            _, pipeline, _ = load_run(Path(config), data=self.scene_dir, device=self.device)
        return pipeline

    @torch.no_grad()
    def render(self, pipeline, desc: str, sticker: Optional[bool] = None) -> Dict[str, Tensor]:
        """``num_views`` test views, evenly spaced over the test split: rgb and ground truth (on white), [N H W 3]."""
        warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
        dataset = pipeline.datamanager.eval_dataset
        n = len(dataset)
        idx = sorted({int(round(j * (n - 1) / max(1, self.p.num_views - 1))) for j in range(min(self.p.num_views, n))})
        model = pipeline.model
        ctx = (
            model.sticker_enabled(sticker)
            if (sticker is not None and hasattr(model, "sticker_enabled"))
            else contextlib.nullcontext()
        )
        rgbs, gts = [], []
        with ctx:
            for i in progress_bar(idx, f"rendering {desc}", self.progress):
                cam = dataset.cameras[i : i + 1].to(model.device)
                rgbs.append(final_rgb(model.get_outputs_for_camera(cam)).float().clamp(0, 1).cpu())
                img = dataset.get_image_float32(i)
                if img.shape[-1] == 4:
                    img = img[..., :3] * img[..., 3:] + (1.0 - img[..., 3:])
                gts.append(img[..., :3].float())
        return {"rgb": torch.stack(rgbs), "gt": torch.stack(gts), "indices": torch.tensor(idx)}

    def key(self, name: str):
        return OwnerKey.load(self.key_path(name))

    def geo_reference(self, name: str):
        """The owner's base ``name`` rebuilt with its key's sticker (once per invocation) and its reference views."""
        if not hasattr(self, "_geo"):
            self._geo: Dict[str, Any] = {}
        if name not in self._geo:
            ref = load_base_reference(
                self.key(name), self.key_path(name), self.base_config(name), self.scene_dir, self.device
            )
            self._geo[name] = (ref, {})
        return self._geo[name]

    def informed_decode(self, name: str, decode, suspect_model, **options) -> Tuple[Dict[str, Any], float]:
        """Run an informed decoder (``decode_suspect`` or ``decode_color_suspect``) with the owner key and reference
        views of base ``name``; the summary and the seconds it took."""
        g = self.p.geometry
        ref, views = self.geo_reference(name)
        key = self.key(name)
        t0 = time.time()
        with contextlib.redirect_stdout(sys.stderr):
            dec, _ = decode(
                key,
                ref,
                suspect_model,
                g.num_views,
                g.sampled_share,
                self.p.seeds[0],
                progress=self.progress,
                ref_cache=views,
                full_renders=False,
                **options,
            )
        return self.summarize(dec["matches"], dec["bit_acc"], key.num_bits), time.time() - t0

    def geo_decode(self, name: str, suspect_model, sticker: Optional[bool] = None, desc: str = "") -> Dict[str, Any]:
        """Informed geometric decoding of a suspect model with the owner key of base ``name``."""
        res, seconds = self.informed_decode(name, decode_suspect, suspect_model, sticker=sticker)
        res["seconds_per_view"] = round(seconds / max(1, res["views"]), 2)
        if desc:
            self.say(f"    geometry {desc}: matches {res['matches']} -> {'OWNED' if res['verdict'] else 'not shown'}")
        return res

    def color_decode(self, suspect_model, amplitude: float, desc: str = "") -> Dict[str, Any]:
        """The color-branch baseline's informed decoder (primary base's key and the reference views geo_decode uses)."""
        res, _ = self.informed_decode(self.primary, decode_color_suspect, suspect_model, amplitude=amplitude)
        if desc:
            self.say(
                f"    color baseline {desc}: matches {res['matches']} -> {'OWNED' if res['verdict'] else 'not shown'}"
            )
        return res

    @property
    def reads_images(self) -> bool:
        """Whether the image-level tables are read by the informed image decoder too."""
        return self.p.geometry is not None and self.p.geometry.image_decoder

    @property
    def test_hw(self) -> Tuple[int, int]:
        return tuple(self.views(self.primary)["watermarked"].shape[1:3])

    def test_cameras(self, name: str) -> List[Tuple[str, Any]]:
        """``(name, camera)`` of the protocol's test views (the renders stage's ``indices``), from the owner's base run.
        Named as the geometric decoder names eval cameras, so both decoders share one reference cache."""
        if not hasattr(self, "_test_cams"):
            self._test_cams: Dict[str, List[Tuple[str, Any]]] = {}
        if name not in self._test_cams:
            ref, _ = self.geo_reference(name)
            ds = ref.pipeline.datamanager.eval_dataset
            self._test_cams[name] = [
                (f"eval/{int(i):03d}", ds.cameras[int(i) : int(i) + 1]) for i in self.views(name)["indices"].tolist()
            ]
        return self._test_cams[name]

    def image_decode(self, images_nhw3: Tensor) -> Dict[str, Any]:
        """The informed image decoder on images of the primary base's test views, quantized to 8 bits first (as
        saved image files are). Image ``j`` is read as if taken at test view ``j mod num_views``: for unmarked
        images (false positives) any image of that size is a valid null, the decoder never uses the message."""

        images = metrics.as_8_bit(images_nhw3)
        digest = hashlib.sha1((images * 255.0).to(torch.uint8).numpy().tobytes()).hexdigest()
        if not hasattr(self, "_image_decoded"):
            self._image_decoded: Dict[str, Dict[str, Any]] = {}
        if digest in self._image_decoded:  # the same 8-bit images (a deterministic attack, another seed): same fit
            return dict(self._image_decoded[digest])
        ref, cache = self.geo_reference(self.primary)
        key = self.key(self.primary)
        cams = self.test_cameras(self.primary)
        cams = [cams[j % len(cams)] for j in range(images.shape[0])]  # more images than views (nulls): cycle
        with contextlib.redirect_stdout(sys.stderr):
            dec = decode_posed_images(key, ref, images, cams, self.p.seeds[0], ref_cache=cache)
        res = self.summarize(dec["matches"], dec["bit_acc"], key.num_bits)
        res["explained"] = [round(float(d["explained"]), 4) for d in dec["image"]]
        res["degradation"] = [d["degradation"] for d in dec["image"]]
        self._image_decoded[digest] = res
        return dict(res)

    @staticmethod
    def _as_tensors(d: Dict[str, Any], prefix: str) -> Dict[str, Tensor]:
        return {
            f"{prefix}_matches": torch.tensor(d["matches"]),
            f"{prefix}_bit_acc": torch.tensor([float(d["bit_acc"])]),
        }

    def _from_tensors(self, c: Dict[str, Tensor], prefix: str, num_bits: int = 48) -> Optional[Dict[str, Any]]:
        if f"{prefix}_matches" not in c:
            return None
        m = c[f"{prefix}_matches"]
        return self.summarize(m, m.float() / num_bits, num_bits)

    def decode(self, key, images_nhw3: Tensor) -> Dict[str, Any]:
        """Per-view numbers and their summary for one set of views (the blind extractor)."""
        d = decode_images(key, images_nhw3.float().clamp(0, 1))
        return self.summarize(d.matches, d.bit_acc, key.num_bits)

    def summarize(self, matches: Tensor, bit_acc: Tensor, num_bits: int) -> Dict[str, Any]:
        """Per-view matches -> views passing the threshold, the model-level vote and its p-value."""
        m = [int(x) for x in matches.tolist()]
        passing = [x >= self.threshold for x in m]
        vote = metrics.combine_view_decisions(passing, self.p.min_share)
        acc = bit_acc.float()
        return {
            "views": len(m),
            "bit_acc": float(acc.mean()),
            "bit_acc_std": float(acc.std(unbiased=False)) if len(m) > 1 else 0.0,
            "matches": m,
            "views_passing": sum(passing),
            "share_passing": sum(passing) / len(m),
            "verdict": bool(vote.passed),
            "vote_pvalue": float(metrics.vote_pvalue(m, num_bits, self.p.min_share)),
        }

    @staticmethod
    def image_metrics(a: Tensor, b: Tensor, lpips=None) -> Dict[str, Any]:
        a4, b4 = a.permute(0, 3, 1, 2).float(), b.permute(0, 3, 1, 2).float()
        psnr = metrics.psnr(a4, b4)
        res = {
            "psnr": finite_or_none(psnr.mean()),
            "psnr_min": finite_or_none(psnr.min()),
            "ssim": float(metrics.ssim(a4, b4).mean()),
        }
        if lpips is not None:
            res["lpips"] = lpips(a4, b4)
        return res

    # ------------------------------------------------------------------------------------------ stages

    def train_sticker(self, base: str, experiment: str, extra: Sequence[str] = ()) -> Optional[float]:
        """``ns-train geometrysticker`` on base ``base`` into runs/<experiment>/geometrysticker/watermarked (skipped,
        returning None, when its checkpoint and key exist); returns the wall seconds."""
        s = self.p.sticker
        wm = self.out / "runs" / experiment / "geometrysticker" / "watermarked"
        if wm.with_name("watermarked.gskey").is_file() and self.latest_ckpt(wm) is not None:
            return None
        t0 = time.time()
        self.run_cmd(
            [
                console_script("ns-train"),
                "geometrysticker",
                "--pipeline.mark",
                "sticker",
                "--pipeline.train-heads",
                "True",
                "--machine.device-type",
                self.p.device,
                "--vis",
                "tensorboard",
                "--output-dir",
                str(self.out / "runs"),
                "--experiment-name",
                experiment,
                "--timestamp",
                "watermarked",
                "--max-num-iterations",
                str(s.steps),
                "--pipeline.owner-id",
                s.owner_id,
                "--pipeline.key-path",
                str(wm.with_name("watermarked.gskey")),
                *[str(a) for a in s.args],
                *extra,
                "--load-checkpoint",
                str(self.latest_ckpt(self.base_config(base).parent)),
                "--data",
                str(self.scene_dir),
            ],
            f"sticker-{experiment}",
        )
        return round(time.time() - t0, 1)

    def views(self, name: str) -> Dict[str, Tensor]:
        paths = [self.out / "cache" / f"{name}-wm.pt", self.out / "cache" / f"{name}-base.pt"]
        if not all(p.is_file() for p in paths):
            raise GStickerError(f"the renders of base {name} are missing ({paths[0]}); run the renders stage first")
        w = torch.load(paths[0], map_location="cpu", weights_only=True)
        w["base"] = torch.load(paths[1], map_location="cpu", weights_only=True)["rgb"]
        return w

    def color_run(self) -> Optional[Path]:
        """The color-branch baseline run of the primary base (written by the geometry stage), or None."""
        cfg = self.out / "runs" / self.primary / "colormark" / "config.yml"
        return cfg if cfg.is_file() else None

    @property
    def primary(self) -> str:
        return self.p.bases[0].name

    def attacked(self, wm: Tensor, clean: Tensor, spec, seed: int) -> Tensor:
        if isinstance(spec, str) and not spec.strip():
            return wm
        g = torch.Generator().manual_seed(seed)
        x = apply_attacks(wm.permute(0, 3, 1, 2).float(), spec, generator=g, cover=clean.permute(0, 3, 1, 2).float())
        return x.permute(0, 2, 3, 1).clamp(0, 1)

    # ------------------------------------------------------------------------------------------ all


def over_seeds(per_seed: List[Dict[str, Any]]) -> Dict[str, Any]:
    """A decoder's per-seed summaries -> mean bit accuracy, its spread over seeds, views passing and verdict rate.
    A deterministic attack gives the same images for every seed: identical entries, spread 0."""
    accs = torch.tensor([s["bit_acc"] for s in per_seed])
    return {
        "bit_acc": float(accs.mean()),
        "bit_acc_seed_std": float(accs.std(unbiased=False)),
        "share_passing": float(sum(s["share_passing"] for s in per_seed) / len(per_seed)),
        "verdict_rate": float(sum(s["verdict"] for s in per_seed) / len(per_seed)),
        "per_seed": per_seed,
    }


def describe_spec(spec: str) -> str:
    """The exact definition of each attack of a spec, from gsticker_plugin.attacks' docstrings."""

    fns = {
        "noise": attacks.gaussian_noise,
        "rotate": attacks.rotate,
        "crop": attacks.cropout,
        "blur": attacks.gaussian_blur,
        "hue": attacks.hue_shift,
        "jpeg": attacks.jpeg,
        "resize": attacks.resize,
    }
    if not spec.strip():
        return "no attack"
    parts = []
    for name, _ in attacks.parse_attack_spec(spec):
        doc = inspect.getdoc(fns[name]) or ""
        first = " ".join(doc.split("\n\n")[0].split())
        parts.append(f"{name}: {first}")
    extra = (
        " (cropout: the rectangle is replaced by the unwatermarked render of the same view)" if "crop" in spec else ""
    )
    return "; ".join(parts) + extra
