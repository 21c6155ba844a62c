"""Runs the evaluation protocol stage by stage; every stage is skipped when its output exists (resumable).

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
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from gsticker_plugin.decoders.geometric import decode_suspect
from gsticker_plugin.decoders.image import decode_posed_images, image_reference, leaked_key_attack
from gsticker_plugin.decoders.reference import any_reference_view, cpu_sticker, load_base_reference
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.evaluation.config import LEAKED_KEY, Protocol, to_plain
from gsticker_plugin.runs import final_rgb, load_run
from gsticker_plugin.views import images_views, random_views


def _bin(name: str) -> str:
    cand = Path(sys.executable).with_name(name)
    return str(cand) if cand.exists() else (shutil.which(name) or name)


def progress_bar(iterable, desc: str, enabled: bool, total: Optional[int] = None):
    if not enabled:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, desc=desc, total=total, leave=False, file=sys.stderr)


def finite_or_none(x: float) -> Any:
    """JSON has no inf/nan: inf -> "inf", nan -> None."""
    x = float(x)
    if math.isnan(x):
        return None
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return x


class Runner:
    def __init__(self, protocol: Protocol, progress: bool = True, redo: Sequence[str] = (), log: Callable[[str], None] = print):
        self.p = protocol
        self.out = Path(protocol.output_dir)
        self.progress = progress
        self.redo = set(redo)
        self.say = log
        self.device = torch.device(protocol.device)
        for d in ("stages", "cache", "logs", "charts", "runs"):
            (self.out / d).mkdir(parents=True, exist_ok=True)
        self.timings: Dict[str, float] = {}
        from gsticker_plugin import metrics

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
            raise GStickerError(f"{Path(cmd[0]).name} {' '.join(cmd[1:2])} failed (exit {proc.returncode}); "
                                f"its last lines are above, the full log is {log}")
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
        ckpts = sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
        return ckpts[-1] if ckpts else None

    # ------------------------------------------------------------------------------------------ models
    def load(self, config: Path):

        with contextlib.redirect_stdout(sys.stderr):
            _, pipeline, _ = load_run(Path(config), data=self.scene_dir, device=self.device)
        return pipeline

    @torch.no_grad()
    def render(self, pipeline, desc: str, sticker: Optional[bool] = None) -> Dict[str, Tensor]:
        """``num_views`` test views, evenly spaced over the test split: rgb and ground truth (on white), [N H W 3]."""
        import warnings

        warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
        dataset = pipeline.datamanager.eval_dataset
        n = len(dataset)
        idx = sorted({int(round(j * (n - 1) / max(1, self.p.num_views - 1))) for j in range(min(self.p.num_views, n))})
        model = pipeline.model
        ctx = model.sticker_enabled(sticker) if (sticker is not None and hasattr(model, "sticker_enabled")) else contextlib.nullcontext()
        rgbs, gts = [], []
        with ctx:
            for i in progress_bar(idx, f"rendering {desc}", self.progress):
                cam = dataset.cameras[i: i + 1].to(model.device)
                rgbs.append(final_rgb(model.get_outputs_for_camera(cam)).float().clamp(0, 1).cpu())
                img = dataset.get_image_float32(i)
                if img.shape[-1] == 4:
                    img = img[..., :3] * img[..., 3:] + (1.0 - img[..., 3:])
                gts.append(img[..., :3].float())
        return {"rgb": torch.stack(rgbs), "gt": torch.stack(gts), "indices": torch.tensor(idx)}

    def key(self, name: str):
        from gsticker_plugin.key import OwnerKey

        return OwnerKey.load(self.key_path(name))

    def geo_reference(self, name: str):
        """The owner's base ``name`` rebuilt with its key's sticker (once per invocation) and its reference views."""
        if not hasattr(self, "_geo"):
            self._geo: Dict[str, Any] = {}
        if name not in self._geo:

            ref = load_base_reference(self.key(name), self.key_path(name), self.base_config(name), self.scene_dir,
                                      self.device)
            self._geo[name] = (ref, {})
        return self._geo[name]

    def geo_decode(self, name: str, suspect_model, sticker: Optional[bool] = None, desc: str = "") -> Dict[str, Any]:
        """Informed geometric decoding of a suspect model with the owner key of base ``name``."""
        g = self.p.geometry
        ref, views = self.geo_reference(name)
        key = self.key(name)
        t0 = time.time()
        with contextlib.redirect_stdout(sys.stderr):
            dec, _ = decode_suspect(key, ref, suspect_model, g.num_views, g.sampled_share, self.p.seeds[0],
                                    sticker=sticker, progress=self.progress, ref_cache=views, full_renders=False)
        res = self.summarize(dec["matches"], dec["bit_acc"], key.num_bits)
        res["seconds_per_view"] = round((time.time() - t0) / max(1, res["views"]), 2)
        if desc:
            self.say(f"    geometry {desc}: matches {res['matches']} -> {'OWNED' if res['verdict'] else 'not shown'}")
        return res

    def color_decode(self, suspect_model, amplitude: float, desc: str = "") -> Dict[str, Any]:
        """The color-branch baseline's informed decoder (primary base's key and reference)."""
        from gsticker_plugin.colormark import decode_color_suspect

        g = self.p.geometry
        ref, views = self.geo_reference(self.primary)  # the same cameras as geo_decode's: its reference views serve
        key = self.key(self.primary)
        with contextlib.redirect_stdout(sys.stderr):
            dec, _ = decode_color_suspect(key, ref, suspect_model, g.num_views, g.sampled_share, self.p.seeds[0],
                                          amplitude=amplitude, progress=self.progress, ref_cache=views,
                                          full_renders=False)
        res = self.summarize(dec["matches"], dec["bit_acc"], key.num_bits)
        if desc:
            self.say(f"    color baseline {desc}: matches {res['matches']} -> {'OWNED' if res['verdict'] else 'not shown'}")
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
            self._test_cams[name] = [(f"eval/{int(i):03d}", ds.cameras[int(i): int(i) + 1])
                                     for i in self.views(name)["indices"].tolist()]
        return self._test_cams[name]

    def image_decode(self, images_nhw3: Tensor) -> Dict[str, Any]:
        """The informed image decoder on images of the primary base's test views, quantized to 8 bits first (as
        saved image files are). Image ``j`` is read as if taken at test view ``j mod num_views``: for unmarked
        images (false positives) any image of that size is a valid null, the decoder never uses the message."""

        import hashlib

        images = _as_8_bit(images_nhw3)
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
        return {f"{prefix}_matches": torch.tensor(d["matches"]), f"{prefix}_bit_acc": torch.tensor([float(d["bit_acc"])])}

    def _from_tensors(self, c: Dict[str, Tensor], prefix: str, num_bits: int = 48) -> Optional[Dict[str, Any]]:
        if f"{prefix}_matches" not in c:
            return None
        m = c[f"{prefix}_matches"]
        return self.summarize(m, m.float() / num_bits, num_bits)

    def decode(self, key, images_nhw3: Tensor) -> Dict[str, Any]:
        """Per-view numbers and their summary for one set of views (the blind extractor)."""
        from gsticker_plugin.evaluate import decode_images

        d = decode_images(key, images_nhw3.float().clamp(0, 1))
        return self.summarize(d.matches, d.bit_acc, key.num_bits)

    def summarize(self, matches: Tensor, bit_acc: Tensor, num_bits: int) -> Dict[str, Any]:
        """Per-view matches -> views passing the threshold, the model-level vote and its p-value."""
        from gsticker_plugin import metrics

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
        from gsticker_plugin import metrics

        a4, b4 = a.permute(0, 3, 1, 2).float(), b.permute(0, 3, 1, 2).float()
        psnr = metrics.psnr(a4, b4)
        res = {"psnr": finite_or_none(psnr.mean()), "psnr_min": finite_or_none(psnr.min()),
               "ssim": float(metrics.ssim(a4, b4).mean())}
        if lpips is not None:
            res["lpips"] = lpips(a4, b4)
        return res

    # ------------------------------------------------------------------------------------------ stages
    def stage_scene(self) -> Dict[str, Any]:
        if self.p.scene.data is not None:
            return {"data": str(self.p.scene.data), "generated": False}
        g = dict(self.p.scene.generate or {})
        scene = self.out / "scene"
        if not (scene / "transforms_test.json").is_file():
            cmd = [_bin("ns-gsticker-scene"), "--output-dir", str(scene)]
            for k, v in g.items():
                cmd += [f"--{k.replace('_', '-')}", str(v)]
            if scene.exists():
                cmd.append("--overwrite")
            self.run_cmd(cmd, "scene")
        return {"data": str(scene), "generated": True, "settings": g}

    def stage_bases(self) -> Dict[str, Any]:
        res = {}
        for b in self.p.bases:
            cfg = self.base_config(b.name)
            if b.config is None and self.latest_ckpt(cfg.parent) is None:
                t0 = time.time()
                self.run_cmd([_bin("ns-train"), b.preset, "--machine.device-type", self.p.device, "--vis", "tensorboard",
                              "--output-dir", str(self.out / "runs"), "--experiment-name", b.name, "--timestamp", "base",
                              "--max-num-iterations", str(b.steps), "--steps-per-save", str(b.steps),
                              *[str(a) for a in b.args], "--data", str(self.scene_dir)], f"base-{b.name}")
                res[b.name] = {"config": str(cfg), "trained_here": True, "steps": b.steps,
                               "train_seconds": round(time.time() - t0, 1)}
            else:
                res[b.name] = {"config": str(cfg), "trained_here": b.config is None}
            if self.latest_ckpt(cfg.parent) is None:
                raise GStickerError(f"base {b.name}: no checkpoint in {cfg.parent / 'nerfstudio_models'}")
            res[b.name]["checkpoint"] = str(self.latest_ckpt(cfg.parent))
        return res

    def train_sticker(self, base: str, experiment: str, extra: Sequence[str] = ()) -> Optional[float]:
        """``ns-train geometrysticker`` on base ``base`` into runs/<experiment>/geometrysticker/watermarked (skipped,
        returning None, when its checkpoint and key exist); returns the wall seconds."""
        s = self.p.sticker
        wm = self.out / "runs" / experiment / "geometrysticker" / "watermarked"
        if wm.with_name("watermarked.gskey").is_file() and self.latest_ckpt(wm) is not None:
            return None
        t0 = time.time()
        self.run_cmd([_bin("ns-train"), "geometrysticker", "--machine.device-type", self.p.device, "--vis",
                      "tensorboard", "--output-dir", str(self.out / "runs"), "--experiment-name", experiment,
                      "--timestamp", "watermarked", "--max-num-iterations", str(s.steps),
                      "--pipeline.owner-id", s.owner_id, "--pipeline.key-path", str(wm.with_name("watermarked.gskey")),
                      *[str(a) for a in s.args], *extra,
                      "--load-checkpoint", str(self.latest_ckpt(self.base_config(base).parent)),
                      "--data", str(self.scene_dir)], f"sticker-{experiment}")
        return round(time.time() - t0, 1)

    def stage_sticker(self) -> Dict[str, Any]:
        res = {}
        for b in self.p.bases:
            secs = self.train_sticker(b.name, b.name)
            res[b.name] = {"config": str(self.wm_dir(b.name) / "config.yml"), "key": str(self.key_path(b.name)),
                           "steps": self.p.sticker.steps, "train_seconds": secs,
                           "monitor": parse_monitor_log(self.out / "logs" / f"sticker-{b.name}.log")}
        return res

    def stage_renders(self) -> Dict[str, Any]:
        res = {}
        for b in self.p.bases:
            def wm_views(b=b):
                pipe = self.load(self.wm_dir(b.name) / "config.yml")
                on = self.render(pipe, f"{b.name} watermarked", sticker=True)
                off = self.render(pipe, f"{b.name} sticker off", sticker=False)
                return {"watermarked": on["rgb"], "sticker_off": off["rgb"], "gt": on["gt"], "indices": on["indices"]}

            def base_views(b=b):
                t0 = time.time()
                r = self.render(self.load(self.base_config(b.name)), f"{b.name} base")
                return {"rgb": r["rgb"], "seconds_per_view": torch.tensor((time.time() - t0) / r["rgb"].shape[0])}

            w = self.cached(f"{b.name}-wm", wm_views)
            base = self.cached(f"{b.name}-base", base_views)
            res[b.name] = {"views": int(w["watermarked"].shape[0]), "size": list(w["watermarked"].shape[1:3]),
                           "indices": w["indices"].tolist(), "base_seconds_per_view": float(base["seconds_per_view"])}
        return res

    def views(self, name: str) -> Dict[str, Tensor]:
        paths = [self.out / "cache" / f"{name}-wm.pt", self.out / "cache" / f"{name}-base.pt"]
        if not all(p.is_file() for p in paths):
            raise GStickerError(f"the renders of base {name} are missing ({paths[0]}); run the renders stage first")
        w = torch.load(paths[0], map_location="cpu", weights_only=True)
        w["base"] = torch.load(paths[1], map_location="cpu", weights_only=True)["rgb"]
        return w

    def stage_quality(self) -> Dict[str, Any]:
        from gsticker_plugin import compat

        compat.apply()
        lp = lpips_fn()
        res = {"lpips": "available" if lp is not None else "unavailable (AlexNet weights not in the torch cache; offline)"}
        for b in self.p.bases:
            v = self.views(b.name)
            key = self.key(b.name)
            res[b.name] = {
                "wm_vs_gt": self.image_metrics(v["watermarked"], v["gt"], lp),
                "unwm_vs_gt": self.image_metrics(v["sticker_off"], v["gt"], lp),
                "base_vs_gt": self.image_metrics(v["base"], v["gt"], lp),
                "wm_vs_unwm": self.image_metrics(v["watermarked"], v["sticker_off"], lp),
                "base_vs_sticker_off": self.image_metrics(v["base"], v["sticker_off"]),
                "decode_watermarked": self.decode(key, v["watermarked"]),
                "decode_sticker_off": self.decode(key, v["sticker_off"]),
            }
        return res

    def color_run(self) -> Optional[Path]:
        """The color-branch baseline run of the primary base (written by the geometry stage), or None."""
        cfg = self.out / "runs" / self.primary / "colormark" / "config.yml"
        return cfg if cfg.is_file() else None

    def stage_geometry(self) -> Dict[str, Any]:
        """Model-level verdicts of the informed geometric decoder: watermarked, sticker off, the unwatermarked base
        (and other runs); plus the color-branch baseline (unedited) when enabled."""
        g = self.p.geometry
        res: Dict[str, Any] = {"num_views": g.num_views, "sampled_share": g.sampled_share, "seed": self.p.seeds[0],
                               "threshold": self.threshold, "bases": {}}
        for b in self.p.bases:
            self.say(f"  [geometry] {b.name}")
            wm = self.load(self.wm_dir(b.name) / "config.yml").model
            res["bases"][b.name] = {
                "watermarked": self.geo_decode(b.name, wm, sticker=True, desc="watermarked"),
                "sticker_off": self.geo_decode(b.name, wm, sticker=False, desc="sticker off"),
                "base_run": self.geo_decode(b.name, self.load(self.base_config(b.name)).model, desc="base run"),
            }
            del wm
        others = []
        for o in self.p.false_positives.other_runs:

            name, cfg = o.get("name", Path(o["config"]).parent.name), Path(o["config"])
            with contextlib.redirect_stdout(sys.stderr):
                _, pipe, _ = load_run(cfg, data=Path(o["data"]) if o.get("data") else None, device=self.device)
            others.append({"name": name, **self.geo_decode(self.primary, pipe.model, desc=name)})
        res["other_runs"] = others
        if g.color_baseline:
            res["color_baseline"] = self.color_baseline()
        return res

    def stage_seeds(self) -> Dict[str, Any]:
        """The primary base's sticker trained again with other training seeds: each run's model-level geometric
        decode (its own owner key) and its PSNRs on the protocol's test views; mean and spread with the main run."""
        from gsticker_plugin.key import OwnerKey

        g, b = self.p.geometry, self.primary
        q = json.loads(self.stage_path("quality").read_text())[b]
        main = json.loads(self.stage_path("geometry").read_text())["bases"][b]["watermarked"]
        st = json.loads(self.stage_path("sticker").read_text())[b]
        rows = [{"seed": 42, "main_run": True, "train_seconds": st.get("train_seconds"), "geometry": main,
                 "psnr_wm_vs_unwm": q["wm_vs_unwm"]["psnr"], "psnr_wm_vs_gt": q["wm_vs_gt"]["psnr"]}]
        for seed in self.p.sticker.seeds:
            name = f"{b}-seed{seed}"
            self.say(f"  [seeds] {name}")
            secs = self.train_sticker(b, name, ["--machine.seed", str(seed)])
            wm = self.out / "runs" / name / "geometrysticker" / "watermarked"
            key_path = wm.with_name("watermarked.gskey")
            pipe = self.load(wm / "config.yml")
            on, off = self.render(pipe, f"{name} watermarked", sticker=True), self.render(pipe, f"{name} sticker off", sticker=False)
            key = OwnerKey.load(key_path)
            ref = load_base_reference(key, key_path, self.base_config(b), self.scene_dir, self.device)
            t0 = time.time()
            with contextlib.redirect_stdout(sys.stderr):
                dec, _ = decode_suspect(key, ref, pipe.model, g.num_views, g.sampled_share, self.p.seeds[0], sticker=True,
                                        progress=self.progress, full_renders=False)
            geo = self.summarize(dec["matches"], dec["bit_acc"], key.num_bits)
            geo["seconds_per_view"] = round((time.time() - t0) / max(1, geo["views"]), 2)
            self.say(f"    geometry {name}: matches {geo['matches']} -> {'OWNED' if geo['verdict'] else 'not shown'}")
            rows.append({"seed": seed, "main_run": False, "train_seconds": secs, "geometry": geo,
                         "psnr_wm_vs_unwm": self.image_metrics(on["rgb"], off["rgb"])["psnr"],
                         "psnr_wm_vs_gt": self.image_metrics(on["rgb"], on["gt"])["psnr"]})
            del pipe, ref

        def spread(vals):
            v = torch.tensor([float(x) for x in vals if isinstance(x, (int, float))], dtype=torch.float64)
            return {"mean": float(v.mean()), "std": float(v.std(unbiased=False)), "min": float(v.min()),
                    "max": float(v.max())} if len(v) else None

        return {"base": b, "rows": rows,
                "bit_acc": spread(r["geometry"]["bit_acc"] for r in rows),
                "psnr_wm_vs_unwm": spread(r["psnr_wm_vs_unwm"] for r in rows),
                "psnr_wm_vs_gt": spread(r["psnr_wm_vs_gt"] for r in rows),
                "verdicts": sum(bool(r["geometry"]["verdict"]) for r in rows),
                "note": "the same protocol's sticker (steps, arguments, owner id) trained with other ns-train seeds on the "
                        "same frozen base; each run decoded with its own owner key (informed geometric decoder, the "
                        "geometry stage's cameras); std over runs (population)"}

    def color_baseline(self) -> Dict[str, Any]:
        """Write the color-marked run (amplitude matched to the sticker's PSNR) and decode it unedited."""
        from gsticker_plugin.colormark import match_amplitude, write_color_marked_run

        q = json.loads(self.stage_path("quality").read_text())
        target = q[self.primary]["wm_vs_unwm"]["psnr"]
        if not isinstance(target, (int, float)):
            target = 45.0
        dest = self.out / "runs" / self.primary / "colormark"
        if dest.exists():
            shutil.rmtree(dest)
        cfg = write_color_marked_run(self.wm_dir(self.primary) / "config.yml", dest, amplitude=0.05)
        pipe = self.load(cfg)
        amplitude = float(match_amplitude(pipe, target_psnr=float(target)))
        # refine on the reported test views (the clamp to [0, 1] makes the PSNR only nearly linear in log amplitude)
        for _ in range(3):
            pipe.model.config.color_amplitude = amplitude
            got = self.image_metrics(self.render(pipe, "color mark", sticker=True)["rgb"],
                                     self.render(pipe, "color mark off", sticker=False)["rgb"])["psnr"]
            if not isinstance(got, float) or abs(got - float(target)) < 0.1:
                break
            amplitude *= 10 ** ((got - float(target)) / 20)
        shutil.rmtree(dest)
        cfg = write_color_marked_run(self.wm_dir(self.primary) / "config.yml", dest, amplitude=amplitude)
        pipe = self.load(cfg)
        r_on = self.render(pipe, "color-marked", sticker=True)
        r_off = self.render(pipe, "color mark off", sticker=False)
        return {"config": str(cfg), "amplitude": amplitude, "target_psnr": float(target),
                "psnr_vs_unmarked": self.image_metrics(r_on["rgb"], r_off["rgb"])["psnr"],
                "color_decoder": self.color_decode(pipe.model, amplitude, desc="unedited"),
                "geometry_decoder": self.geo_decode(self.primary, pipe.model, desc="color-marked run"),
                "note": "the same sticker patterns and gate as the watermarked run, added to the final field's per-sample "
                        "color instead of its density (density identical to the base); built, not trained, in this "
                        "harness; decoded by the informed color decoder (the geometric decoder's fit on RGB)"}

    @property
    def primary(self) -> str:
        return self.p.bases[0].name

    def attacked(self, wm: Tensor, clean: Tensor, spec, seed: int) -> Tensor:
        from gsticker_plugin.attacks import apply_attacks

        if isinstance(spec, str) and not spec.strip():
            return wm
        g = torch.Generator().manual_seed(seed)
        x = apply_attacks(wm.permute(0, 3, 1, 2).float(), spec, generator=g, cover=clean.permute(0, 3, 1, 2).float())
        return x.permute(0, 2, 3, 1).clamp(0, 1)

    def leaked_key_attacked(self, wm: Tensor, psnr_budget: float) -> Tensor:
        """The primary base's watermarked test views (as 8-bit files) attacked by someone holding its owner key and
        the base: PGD on the informed image decoder at each view's camera, within ``psnr_budget`` dB."""

        ref, cache = self.geo_reference(self.primary)
        st = cpu_sticker(ref.model)
        bg = ref.model.background_color()
        out = []
        for (name, cam), image in zip(self.test_cameras(self.primary), _as_8_bit(wm)):
            with contextlib.redirect_stdout(sys.stderr):
                view = any_reference_view(ref, name, cam, cache)
            out.append(leaked_key_attack(image_reference(view, bg), st, image, psnr_budget))
        return torch.stack(out)

    def stage_distortions(self) -> Dict[str, Any]:
        v = self.views(self.primary)
        key = self.key(self.primary)
        rows = []
        for r in progress_bar(self.p.distortions, "distortions", self.progress):
            per_seed, image_per_seed = [], []
            for seed in self.p.seeds:
                x = self.attacked(v["watermarked"], v["sticker_off"], r.spec, seed)
                d = self.decode(key, x)
                d["attack_psnr"] = self.image_metrics(x, v["watermarked"])["psnr"]
                per_seed.append({"seed": seed, **d})
                if self.reads_images:
                    image_per_seed.append({"seed": seed, **self.image_decode(x)})
            row = {"label": r.label, "spec": r.spec, "paper": r.paper, "definition": describe_spec(r.spec),
                   **over_seeds(per_seed), "attack_psnr": per_seed[0]["attack_psnr"]}
            if image_per_seed:
                row["image_decoder"] = over_seeds(image_per_seed)
            rows.append(row)
        return {"base": self.primary, "rows": rows, "threshold": self.threshold,
                "image_decoder": self.reads_images}

    def stage_curves(self) -> Dict[str, Any]:

        v = self.views(self.primary)
        key = self.key(self.primary)
        curves = {}
        for name, strengths in self.p.curves.items():
            pts = []
            for s in progress_bar(strengths, f"curve {name}", self.progress):
                accs, shares, verdicts, image_per_seed = [], [], [], []
                leaked = self.leaked_key_attacked(v["watermarked"], float(s)) if name == LEAKED_KEY else None
                for seed in self.p.seeds:
                    x = leaked if leaked is not None else self.attacked(v["watermarked"], v["sticker_off"], [(name, float(s))], seed)
                    d = self.decode(key, x)
                    accs.append(d["bit_acc"])
                    shares.append(d["share_passing"])
                    verdicts.append(float(d["verdict"]))
                    if self.reads_images:
                        image_per_seed.append({"seed": seed, **self.image_decode(x)})
                a = torch.tensor(accs)
                pt = {"strength": float(s), "bit_acc_mean": float(a.mean()), "bit_acc_std": float(a.std(unbiased=False)),
                      "bit_acc_per_seed": accs, "share_passing_mean": sum(shares) / len(shares),
                      "verdict_rate": sum(verdicts) / len(verdicts)}
                if image_per_seed:
                    pt["image_decoder"] = over_seeds(image_per_seed)
                if leaked is not None:  # the PSNR the attack reached (8-bit image vs the 8-bit watermarked one)
                    pt["attack_psnr"] = self.image_metrics(_as_8_bit(leaked), _as_8_bit(v["watermarked"]))["psnr"]
                pts.append(pt)
            below = next((p["strength"] for p in pts if p["bit_acc_mean"] < 0.9), None)
            fails = next((p["strength"] for p in pts if p["verdict_rate"] < 0.5), None)
            curves[name] = {"points": pts, "bit_acc_below_90_at": below, "verdict_fails_at": fails,
                            "randomized": name in ("noise", "crop"),
                            "definition": describe_leaked_key() if name == LEAKED_KEY else describe_spec(f"{name}={strengths[-1]}")}
            if self.reads_images:
                curves[name]["image_decoder"] = {
                    "bit_acc_below_90_at": next((p["strength"] for p in pts if p["image_decoder"]["bit_acc"] < 0.9), None),
                    "verdict_fails_at": next((p["strength"] for p in pts if p["image_decoder"]["verdict_rate"] < 0.5), None)}
        return {"base": self.primary, "seeds": list(self.p.seeds), "curves": curves, "image_decoder": self.reads_images,
                "note": "seeds change the distortions' randomness only (noise samples, cropout rectangle); rotation, "
                        "blur, JPEG, resize and a fixed hue shift are deterministic, so their spread over seeds is 0. "
                        "The models are trained once."}

    def recolor_variants(self) -> List[Dict[str, Any]]:
        rc = self.p.recolor
        out = []
        for c in rc.colors:
            out.append({"name": f"palette-{c.replace(' ', '')}", "kind": "palette", "color": c,
                        "label": f"palette {rc.palette_entry} -> {c}",
                        "argv": ["palette", "--set", f"{rc.palette_entry}={c}"]})
        for h in rc.model_hue:
            out.append({"name": f"hue-{h:+g}", "kind": "model_hue", "label": f"model-level hue {h:+g}",
                        "argv": ["hue", "--shift", str(h)]})
        ft = rc.finetune
        if ft is not None:
            tgt = ["--set", f"{rc.palette_entry}={ft.color}"] if ft.color is not None else ["--hue-shift", str(ft.hue_shift)]
            what = f"palette {rc.palette_entry} -> {ft.color}" if ft.color is not None else f"hue {ft.hue_shift:+g}"
            # one fine-tune per model to the longest step count; the shorter ones are its snapshots (--save-at)
            counts = sorted({ft.steps, *ft.steps_curve})
            views = [] if ft.max_views is None else ["--max-views", str(ft.max_views)]
            argv = ["finetune", *tgt, *views, "--steps", str(counts[-1]), "--rays-per-step", str(ft.rays_per_step)]
            if len(counts) > 1:
                argv += ["--save-at", *map(str, counts[:-1])]
            for n in counts:
                out.append({"name": "finetune" if n == ft.steps else f"finetune-{n}steps", "kind": "finetune", "steps": n,
                            "label": f"attacker's color fine-tune ({what}, {n} steps)", "argv": argv,
                            "snapshot": n != counts[-1]})
        return out

    def palette_source(self) -> Optional[List[float]]:
        """The color of the palette entry the palette edits replace, extracted as ``ns-recolor palette`` does
        (training images' foreground, k-means with its default k and seed 0)."""
        from gsticker_plugin.recolor import cli

        pipe = self.load(self.base_config(self.primary))
        pal = cli._extract(cli._PaletteEdit(), pipe.model, pipe.datamanager.train_dataset, seed=0)
        e = self.p.recolor.palette_entry
        return [float(x) for x in pal.rgb[e].tolist()] if e < pal.k else None

    def recolored_views(self, variant: Dict[str, Any], which: str) -> Tensor:
        return self.recolored(variant, which)["rgb"]

    def recolored(self, variant: Dict[str, Any], which: str) -> Dict[str, Tensor]:
        """One ns-recolor edit of the watermarked run (``wm``), the base run (``base``) or the color-branch baseline
        (``color``): its renders and, with ``geometry`` on, its model-level decodes (geometric; color for ``color``)."""
        def make():
            from gsticker_plugin.recolor import cli

            src = {"wm": self.wm_dir(self.primary) / "config.yml", "base": self.base_config(self.primary),
                   "color": self.color_run()}[which]
            base_dir = self.out / "recolored" / self.primary
            if variant["kind"] == "finetune":  # the curve's variants share one ns-recolor run: OUT, OUT-stepN
                out_dir = base_dir / "finetune" / which
                dest = out_dir.with_name(f"{which}-step{variant['steps']}") if variant["snapshot"] else out_dir
            else:
                out_dir = dest = base_dir / variant["name"] / which
            if not list(dest.glob("*/*/*/config.yml")):
                for old in [out_dir, *out_dir.parent.glob(f"{which}-step*")]:
                    if old.exists():
                        shutil.rmtree(old)
                argv = [variant["argv"][0], "--load-config", str(src), "--output-dir", str(out_dir), "--data",
                        str(self.scene_dir), *variant["argv"][1:]]
                self.say("  $ ns-recolor " + " ".join(argv))
                with contextlib.redirect_stdout(sys.stderr):
                    rc = cli.run(argv)
                if rc != 0:
                    raise GStickerError(f"ns-recolor {' '.join(argv)} failed (exit {rc})")
            (cfg,) = list(dest.glob("*/*/*/config.yml"))
            pipe = self.load(cfg)
            label = f"{variant['name']} ({which})"
            out = {}
            if which != "color":  # the baseline is only decoded (its renders enter no table)
                out["rgb"] = self.render(pipe, label)["rgb"]
            g = self.p.geometry
            if g is not None and (which == "wm" or (which == "base" and g.recolor_null)):
                out.update(self._as_tensors(self.geo_decode(self.primary, pipe.model, desc=label), "geo"))
            if g is not None and which == "color":
                amp = json.loads(self.stage_path("geometry").read_text())["color_baseline"]["amplitude"]
                out.update(self._as_tensors(self.color_decode(pipe.model, amp, desc=label), "color"))
            if not self.p.recolor.keep_runs:
                shutil.rmtree(dest)
            return out

        return self.cached(f"recolor-{self.primary}-{variant['name']}-{which}", make)

    def stage_recolor(self) -> Dict[str, Any]:
        from gsticker_plugin.attacks import hue_shift

        key = self.key(self.primary)
        v = self.views(self.primary)
        rows = []
        jitter = self.p.recolor.image_hue_jitter
        if jitter is not None:
            per_seed, null_seed, quality, image_seed, image_null = [], [], [], [], []
            for seed in self.p.seeds:
                g = torch.Generator().manual_seed(seed)
                shifts = (torch.rand(v["watermarked"].shape[0], generator=g) * 2 - 1) * abs(float(jitter))

                def jit(x):  # as ns-recolor hue --image-level: per-image shift, written as 8-bit PNG
                    y = hue_shift(x.permute(0, 3, 1, 2).float(), shifts).permute(0, 2, 3, 1)
                    return (y * 255).round() / 255

                a, b = jit(v["watermarked"]), jit(v["base"])
                per_seed.append(self.decode(key, a))
                null_seed.append(self.decode(key, b))
                quality.append(self.image_metrics(a, b))
                if self.reads_images:
                    image_seed.append({"seed": seed, **self.image_decode(a)})
                    image_null.append({"seed": seed, **self.image_decode(b)})
            row = self._recolor_row({"name": "image-hue-jitter", "kind": "image_hue",
                                     "label": f"image-level hue jitter U(-{abs(jitter):g}, {abs(jitter):g})"},
                                    per_seed, null_seed, quality, paper=99.33)
            if image_seed:
                row["image_decoder"], row["image_decoder_null"] = over_seeds(image_seed), over_seeds(image_null)
            rows.append(row)
        with_color = self.p.geometry is not None and self.p.geometry.color_baseline and self.color_run() is not None
        source = self.palette_source() if self.p.recolor.colors else None
        for var in progress_bar(self.recolor_variants(), "recolor", self.progress):
            wm, base = self.recolored(var, "wm"), self.recolored(var, "base")
            a, b = wm["rgb"], base["rgb"]
            paper = 99.40 if var["kind"] == "palette" else None
            row = self._recolor_row(var, [self.decode(key, a)], [self.decode(key, b)], [self.image_metrics(a, b)], paper)
            row["geometry"] = self._from_tensors(wm, "geo", key.num_bits)
            row["geometry_null"] = self._from_tensors(base, "geo", key.num_bits)
            if with_color:
                row["color_baseline"] = self._from_tensors(self.recolored(var, "color"), "color", key.num_bits)
            if var["kind"] == "finetune":
                row["steps"] = var["steps"]
            if var["kind"] == "palette" and source is not None:
                row["delta_e"] = palette_distance(source, var["color"])
            rows.append(row)
        return {"base": self.primary, "rows": rows, "palette_entry": self.p.recolor.palette_entry,
                "palette_source": source,
                "note": "bit accuracy of the watermarked run after the edit; 'null' = the same edit of the unwatermarked base "
                        "decoded with the owner key; PSNR/SSIM = watermarked-recolored vs unwatermarked-recolored render; "
                        "bit_acc/null_* = the blind extractor on the renders; 'geometry' = the informed geometric decoder on "
                        "the edited model (geometry_null: on the edited base); 'color_baseline' = the color-branch "
                        "baseline after the same edit, read by the informed color decoder"}

    @staticmethod
    def _recolor_row(var, per_seed, null_seed, quality, paper) -> Dict[str, Any]:
        def mean(xs, k):
            vals = [x[k] for x in xs if isinstance(x[k], (int, float))]
            return float(sum(vals) / len(vals)) if vals else (xs[0][k] if xs else None)

        return {"name": var["name"], "kind": var["kind"], "label": var["label"], "paper": paper,
                "bit_acc": mean(per_seed, "bit_acc"), "share_passing": mean(per_seed, "share_passing"),
                "verdict_rate": sum(float(s["verdict"]) for s in per_seed) / len(per_seed),
                "null_bit_acc": mean(null_seed, "bit_acc"), "null_share_passing": mean(null_seed, "share_passing"),
                "psnr": mean(quality, "psnr"), "ssim": mean(quality, "ssim"),
                "per_seed": per_seed, "null_per_seed": null_seed}

    def stage_purify(self) -> Dict[str, Any]:
        """Model purification: fine-tune every parameter of the watermarked run (density, color, sticker) on clean
        training images (MSE, Adam); geometric decoding and test PSNR after each cumulative step count."""
        from gsticker_plugin.recolor.finetune import finetune_color
        from gsticker_plugin.recolor.runs import background_of, composite_on, training_images

        g = self.p.geometry
        pipe = self.load(self.wm_dir(self.primary) / "config.yml")
        model = pipe.model
        ds = pipe.datamanager.train_dataset
        bg = background_of(model)
        targets = [composite_on(t, bg) for t in training_images(ds)]
        params = {n: p for n, p in model.named_parameters() if p.is_floating_point() and n.rsplit(".", 1)[-1] != "aabb"
                  and not n.startswith(("extractor", "classifier"))}
        points, done, t_train = [], 0, 0.0
        for steps in g.purify_steps:
            if steps > done:
                t0 = time.time()
                hist = finetune_color(model, ds.cameras, targets, steps - done, lr=g.purify_lr,
                                      rays_per_step=g.purify_rays_per_step, seed=done, progress=self.progress,
                                      color_params=params)
                t_train += time.time() - t0
                done = steps
                loss = float(sum(hist["loss"][-20:]) / len(hist["loss"][-20:]))
            else:
                loss = None
            model.eval()
            r = self.render(pipe, f"purified {steps} steps")
            d = self.geo_decode(self.primary, model, desc=f"purified {steps} steps")
            points.append({"steps": steps, "train_seconds": round(t_train, 1), "loss": loss,
                           "psnr_vs_gt": self.image_metrics(r["rgb"], r["gt"])["psnr"],
                           "bit_acc": d["bit_acc"], "share_passing": d["share_passing"], "verdict": d["verdict"],
                           "matches": d["matches"]})
        below = next((p["steps"] for p in points if p["bit_acc"] < 0.9), None)
        fails = next((p["steps"] for p in points if not p["verdict"]), None)
        return {"base": self.primary, "lr": g.purify_lr, "rays_per_step": g.purify_rays_per_step,
                "parameters": len(params), "points": points, "bit_acc_below_90_at": below, "verdict_fails_at": fails,
                "note": "the attacker holds the shareable model and the clean training images and fine-tunes every "
                        "parameter (the base's density and color, the sticker, the gate width) to fit the images; "
                        "decoded with the informed geometric decoder against the owner's untouched base"}

    def stage_false_positives(self) -> Dict[str, Any]:
        from gsticker_plugin import metrics

        key = self.key(self.primary)
        fp = self.p.false_positives
        sources: List[Dict[str, Any]] = []

        def add(name: str, kind: str, images: Tensor, note: str = "") -> None:
            """The blind extractor on ``images``, and the image decoder too when they have the test views' size."""
            d = self.decode(key, images)
            src = {"name": name, "kind": kind, "note": note, "views": d["views"],
                   "passing": d["views_passing"], "fpr": d["views_passing"] / d["views"],
                   "max_matches": max(d["matches"]), "bit_acc": d["bit_acc"], "verdict": d["verdict"],
                   "matches": d["matches"]}
            if self.reads_images and tuple(images.shape[1:3]) == self.test_hw:
                e = self.image_decode(images)
                src["image_decoder"] = {"views": e["views"], "passing": e["views_passing"], "max_matches": max(e["matches"]),
                                        "bit_acc": e["bit_acc"], "verdict": e["verdict"], "matches": e["matches"]}
            sources.append(src)

        for b in self.p.bases:
            v = self.views(b.name)
            add(f"{b.name} base run", "unwatermarked model", v["base"])
            add(f"{b.name} watermarked run, sticker off", "unwatermarked model", v["sticker_off"])
        if fp.ground_truth:
            add("ground-truth test images", "images", self.views(self.primary)["gt"], "photos of the same scene")
        for o in fp.other_runs:
            name, cfg = o.get("name", Path(o["config"]).parent.name), Path(o["config"])
            data = Path(o["data"]) if o.get("data") else None

            def render_other(cfg=cfg, data=data, name=name):

                with contextlib.redirect_stdout(sys.stderr):
                    _, pipe, _ = load_run(cfg, data=data, device=self.device)
                return {"rgb": self.render(pipe, name)["rgb"]}

            add(name, "unwatermarked model", self.cached(f"other-{re.sub(r'[^A-Za-z0-9_.-]', '_', name)}", render_other)["rgb"],
                str(cfg))
        for folder in fp.other_images:
            vs = images_views(Path(folder), 400, 16, 10**9, progress=False)
            if vs.views:
                ims = [x.image for x in vs.views]
                same = all(i.shape == ims[0].shape for i in ims)
                if same:
                    add(f"images {folder}", "images", torch.stack(ims).permute(0, 2, 3, 1))
                else:
                    for i, im in enumerate(ims):
                        add(f"images {folder} #{i}", "images", im.permute(1, 2, 0)[None])
        recolor = self.stage_path("recolor")
        if recolor.is_file():
            for row in json.loads(recolor.read_text())["rows"]:
                for s in row["null_per_seed"][:1]:
                    m = s["matches"]
                    sources.append({"name": f"base recolored: {row['label']}", "kind": "unwatermarked model",
                                    "note": "from the recolor stage", "views": len(m),
                                    "passing": sum(x >= self.threshold for x in m),
                                    "fpr": sum(x >= self.threshold for x in m) / len(m), "max_matches": max(m),
                                    "bit_acc": s["bit_acc"], "verdict": s["verdict"], "matches": m})
        if fp.random_images > 0:
            size = int(self.views(self.primary)["watermarked"].shape[1])
            rv = random_views(fp.random_images, size, seed=self.p.seeds[0])
            add(f"{fp.random_images} random images", "random images", torch.stack([x.image for x in rv.views]).permute(0, 2, 3, 1),
                "noise, smooth noise, flat colors, gradients")
        n = sum(s["views"] for s in sources)
        x = sum(s["passing"] for s in sources)
        models = [s for s in sources if s["kind"] == "unwatermarked model"]
        return {"threshold": self.threshold, "fpr_target": self.p.fpr, "sources": sources,
                "views": n, "passing": x, "empirical_fpr": x / n if n else None,
                "fpr_upper_95": metrics.clopper_pearson_upper(x, n) if n else None,
                "models": len(models), "models_flagged": sum(bool(s["verdict"]) for s in models),
                "note": "views of one model are not independent; the Clopper-Pearson bound treats them as if they "
                        "were and is therefore optimistic; the model-level count is the honest one"}

    def stage_speed(self) -> Dict[str, Any]:
        st = json.loads(self.stage_path("sticker").read_text())
        q = json.loads(self.stage_path("quality").read_text()) if self.stage_path("quality").is_file() else {}
        res = {}
        for b in self.p.bases:
            mon = st.get(b.name, {}).get("monitor", [])
            res[b.name] = {"train_seconds": st.get(b.name, {}).get("train_seconds"), "steps": st.get(b.name, {}).get("steps"),
                           "monitor": mon,
                           "final_bit_acc": q.get(b.name, {}).get("decode_watermarked", {}).get("bit_acc"),
                           "final_psnr_wm_vs_unwm": q.get(b.name, {}).get("wm_vs_unwm", {}).get("psnr")}
        usable = any(r["monitor"] for r in res.values())
        res["note"] = ("held-out history: the '[gsticker] step N: held-out bit acc ...' lines ns-train geometrysticker prints "
                       "every --pipeline.steps-per-monitor steps (fast-path renders of held-out novel views, owner message, "
                       "no attack); final = real renders of the test views") if usable else (
            "no held-out history in the sticker logs (the monitor did not run: fewer steps than "
            "--pipeline.steps-per-monitor, or the run was trained elsewhere); only the final point is plotted")
        return res

    # ------------------------------------------------------------------------------------------ all
    def run(self, stages: Sequence[str]) -> Dict[str, Any]:
        from gsticker_plugin.evaluation import report

        t0 = time.time()
        fns = {"scene": self.stage_scene, "bases": self.stage_bases, "sticker": self.stage_sticker,
               "renders": self.stage_renders, "quality": self.stage_quality, "geometry": self.stage_geometry,
               "seeds": self.stage_seeds,
               "distortions": self.stage_distortions, "curves": self.stage_curves, "recolor": self.stage_recolor,
               "purify": self.stage_purify, "false_positives": self.stage_false_positives, "speed": self.stage_speed}
        want = [s for s in fns if s in stages]
        if self.p.geometry is None:
            want = [s for s in want if s not in ("geometry", "purify", "seeds")]
        if not self.p.sticker.seeds and "seeds" in want:
            want.remove("seeds")
        if self.p.geometry is not None and not self.p.geometry.purify_steps and "purify" in want:
            want.remove("purify")
        if self.p.recolor is None and "recolor" in want:
            want.remove("recolor")
        if not self.p.curves and "curves" in want:
            want.remove("curves")
        if not self.p.distortions and "distortions" in want:
            want.remove("distortions")
        for i, s in enumerate(want):
            self.say(f"[eval] stage {i + 1}/{len(want)}: {s}")
            self.stage(s, fns[s])
        results = {"protocol": to_plain(self.p), "threshold": self.threshold, "machine": machine_info(),
                   "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "paper": report.paper_numbers()}
        for s in fns:
            if self.stage_path(s).is_file():
                results[s] = json.loads(self.stage_path(s).read_text())
        results["wall_seconds_this_invocation"] = round(time.time() - t0, 1)
        (self.out / "results.json").write_text(json.dumps(results, indent=1, default=str))
        if "report" in stages:
            report.write_all(results, self.out)
        return results


def over_seeds(per_seed: List[Dict[str, Any]]) -> Dict[str, Any]:
    """A decoder's per-seed summaries -> mean bit accuracy, its spread over seeds, views passing and verdict rate.
    A deterministic attack gives the same images for every seed: identical entries, spread 0."""
    accs = torch.tensor([s["bit_acc"] for s in per_seed])
    return {"bit_acc": float(accs.mean()), "bit_acc_seed_std": float(accs.std(unbiased=False)),
            "share_passing": float(sum(s["share_passing"] for s in per_seed) / len(per_seed)),
            "verdict_rate": float(sum(s["verdict"] for s in per_seed) / len(per_seed)), "per_seed": per_seed}


def palette_distance(source_rgb: Sequence[float], color: str) -> float:
    """CIE76 distance (Lab Delta E) between a palette entry and the color an edit gives it."""
    from gsticker_plugin.recolor.palette import parse_color, rgb_to_lab

    lab = rgb_to_lab(torch.tensor([list(source_rgb), list(parse_color(color))], dtype=torch.float32))
    return float((lab[0] - lab[1]).norm())


def lpips_fn():
    """LPIPS(a, b) on [B 3 H W] in [0, 1], or None when its AlexNet weights are unavailable (offline)."""
    from gsticker_plugin import compat

    if not compat.lpips_backbone_available("alex"):
        return None
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    m = LearnedPerceptualImagePatchSimilarity(net_type="alex", normalize=True)
    if not compat.lpips_is_available(m):
        return None
    return lambda a, b: float(m(a.clamp(0, 1), b.clamp(0, 1)))


_MONITOR = re.compile(r"step (\d+): held-out bit acc ([\d.]+) \(clean renders: ([\d.]+)\), PSNR marked/clean ([\d.inf-]+) dB, (\d+) s")


def parse_monitor_log(log: Path) -> List[Dict[str, float]]:
    """The held-out monitor lines of an ``ns-train geometrysticker`` log."""
    if not log.is_file():
        return []
    text = re.sub(r"\x1b\[[0-9;]*m", "", log.read_text(errors="replace"))
    out = []
    for m in _MONITOR.finditer(text):
        out.append({"step": int(m.group(1)), "heldout_bit_acc": float(m.group(2)), "clean_bit_acc": float(m.group(3)),
                    "psnr": float(m.group(4)), "seconds": float(m.group(5))})
    return out


def _as_8_bit(images: Tensor) -> Tensor:
    return torch.round(images.float().clamp(0, 1) * 255.0) / 255.0


def describe_leaked_key() -> str:
    import inspect


    doc = inspect.getdoc(leaked_key_attack) or ""
    return "leaked_key (strength: PSNR budget in dB): " + " ".join(doc.split("\n\n")[0].split())


def describe_spec(spec: str) -> str:
    """The exact definition of each attack of a spec, from gsticker_plugin.attacks' docstrings."""
    import inspect

    from gsticker_plugin import attacks

    fns = {"noise": attacks.gaussian_noise, "rotate": attacks.rotate, "crop": attacks.cropout,
           "blur": attacks.gaussian_blur, "hue": attacks.hue_shift, "jpeg": attacks.jpeg, "resize": attacks.resize}
    if not spec.strip():
        return "no attack"
    parts = []
    for name, _ in attacks.parse_attack_spec(spec):
        doc = inspect.getdoc(fns[name]) or ""
        first = " ".join(doc.split("\n\n")[0].split())
        parts.append(f"{name}: {first}")
    extra = " (cropout: the rectangle is replaced by the unwatermarked render of the same view)" if "crop" in spec else ""
    return "; ".join(parts) + extra


def machine_info() -> Dict[str, Any]:
    import platform

    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        from importlib.metadata import version

        import nerfstudio  # noqa: F401

        ns = version("nerfstudio")
    except Exception:
        ns = "?"
    return {"cpu": cpu, "cores": os.cpu_count(), "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "nerfstudio": ns, "python": platform.python_version(), "cuda": torch.cuda.is_available(),
            "omp_num_threads": os.environ.get("OMP_NUM_THREADS")}
