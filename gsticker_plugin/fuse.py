"""Fused export: a run of the base's *own* method whose field reproduces the watermarked (marked) density.

Over 600 lines on purpose: the distillation, its sample cache and the export command share one configuration.

A GeometrySticker run shares the frozen base plus a separable sticker (``sigma~ = relu(sigma + psi * scale * m)``)
and needs this plugin to open. The fused export distils the marked model back into a plain run of the base's
method (e.g. a stock ``nerfacto`` run):

1. the watermarked run is rebuilt (teacher: base + sticker with the owner's message), and the base run it was made
   on is rebuilt a second time as the student (its own method, its own weights, strictly loaded);
2. for a pool of cameras (the run's training cameras and sampled orbit poses) the teacher renders each view once,
   and the final field's samples are cached per ray (ray origin, direction, sample intervals: the base's proposal
   sampler places them, so they are the samples the student draws too, as long as its proposal networks are the
   base's) with the teacher's marked density and colour at them;
3. the student's final field (hash grid and MLPs; the proposal networks stay the base's) is fine-tuned on the cached
   samples: render weights, accumulation, expected depth and colour of each ray against the teacher's (what the
   geometric decoder and the renders read), plus the log density at visible samples;
4. the student is saved as a stock Nerfstudio run of the base's method (its config.yml with a new output folder,
   ``nerfstudio_models/step-N.ckpt`` with ``step``, ``pipeline``, ``optimizers``, ``schedulers``, ``scalers``):
   stock ``ns-viewer``, ``ns-render``, ``ns-eval`` and ``ns-verify-owner --load-config`` open it without the
   plugin, and it has no sticker module to switch off.

The owner key is not touched and nothing about it enters the fused run (the key keeps referencing the *base*).

CLI (``ns-gsticker-export fuse`` once the entry point is registered, or ``python -m gsticker_plugin.fuse``)::

    ns-gsticker-export fuse --load-config WM_RUN/config.yml --output-dir outputs/fused
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
import os
import shutil
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple, Union

import torch
import tyro
import yaml
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.field_components.field_heads import FieldHeadNames
from torch import Tensor

from gsticker_plugin import compat, runs
from gsticker_plugin.background import Background
from gsticker_plugin.errors import GStickerError, run_command
from gsticker_plugin.fastpath import novel_cameras
from gsticker_plugin.runs import final_rgb, load_run, relocate
from gsticker_plugin.sticker import render_weights

# ================================================================================================================
# pure functions (small tensors; tested in tests/test_fuse.py)
# ================================================================================================================


def transmittance(density: Tensor, deltas: Tensor) -> Tensor:
    """T_i = exp(-sum_{j<i} sigma_j delta_j) per sample [R S 1] (the light that reaches sample i)."""
    dd = density * deltas
    excl = torch.cumsum(dd, dim=-2) - dd
    return torch.exp(-excl)


@dataclass
class LossWeights:
    """Weights of the distillation terms (each a mean over the batch's rays)."""

    weights: float = 1.0
    """sum over samples of (w_student - w_teacher)^2: the whole per-ray geometry."""
    accumulation: float = 1.0
    """(acc_student - acc_teacher)^2: the geometric decoder's first signal."""
    depth: float = 1.0
    """(sum w t - sum w t)^2 / depth_scale^2: its second signal (nerfacto's expected depth x accumulation)."""
    rgb: float = 1.0
    """Squared error of the composited colour (PSNR against the watermarked render)."""
    log_density: float = 1e-3
    """Transmittance-weighted squared error of log density (keeps hidden samples where the teacher has them)."""


def distill_losses(
    student_density: Tensor,
    student_rgb: Tensor,
    teacher_density: Tensor,
    teacher_rgb: Tensor,
    deltas: Tensor,
    steps: Tensor,
    background: Union[Tensor, Background],
    depth_scale: float,
    density_floor: float,
    w: LossWeights,
) -> Dict[str, Tensor]:
    """The distillation terms for a batch of rays, all [R S *] tensors on the same samples.

    ``steps``: distance of each sample from the ray origin (for the depth term), ``depth_scale`` divides it (so
    the depth term is O(1) per unit of weight, as the decoder normalizes it); ``density_floor``: densities below it
    count as it in the log term (the marked density is 0 where the sticker removed a surface).
    """
    ws = render_weights(student_density, deltas)
    with torch.no_grad():
        wt = render_weights(teacher_density, deltas)
        tt = transmittance(teacher_density, deltas)
        acc_t = wt.sum(dim=-2)
        depth_t = (wt * steps).sum(dim=-2) / depth_scale
        rgb_t = (wt * teacher_rgb).sum(dim=-2) + Background.of(background).fill(teacher_rgb) * (1.0 - acc_t)
        log_t = torch.log(teacher_density.clamp_min(density_floor))
    acc_s = ws.sum(dim=-2)
    depth_s = (ws * steps).sum(dim=-2) / depth_scale
    rgb_s = (ws * student_rgb).sum(dim=-2) + Background.of(background).fill(student_rgb) * (1.0 - acc_s)
    log_s = torch.log(student_density.clamp_min(density_floor))
    terms = {
        "weights": ((ws - wt) ** 2).sum(dim=-2).mean(),
        "accumulation": ((acc_s - acc_t) ** 2).mean(),
        "depth": ((depth_s - depth_t) ** 2).mean(),
        "rgb": ((rgb_s - rgb_t) ** 2).mean(),
        "log_density": (tt * (log_s - log_t) ** 2).sum(dim=-2).mean() / max(1, student_density.shape[-2]),
    }
    terms["total"] = sum(getattr(w, k) * v for k, v in terms.items())
    return terms


def visible_samples(teacher_density: Tensor, base_density: Tensor, deltas: Tensor, min_transmittance: float) -> Tensor:
    """[R S] bool: samples that some light reaches in the teacher or in the base (transmittance above
    ``min_transmittance``); behind them a density change does not change any render."""
    t = torch.maximum(transmittance(teacher_density, deltas), transmittance(base_density, deltas))
    return t[..., 0] > min_transmittance


def psnr(a: Tensor, b: Tensor) -> float:
    """PSNR in dB of two images in [0, 1] (inf when equal)."""
    mse = float(((a.float() - b.float()) ** 2).mean())
    return float("inf") if mse == 0.0 else -10.0 * math.log10(mse)


def select_rays(
    changed: Tensor, acc: Tensor, keep_other: float, generator: torch.Generator, acc_threshold: float = 1e-3
) -> Tensor:
    """Flat ray indices kept in the pool: every ray the sticker changes or that sees something
    (``acc > acc_threshold``), and a ``keep_other`` share of the rest (empty rays keep the student's empty space)."""
    seen = changed | (acc > acc_threshold)
    other = (~seen).nonzero().squeeze(-1)
    n = int(round(keep_other * other.numel()))
    pick = other[torch.randperm(other.numel(), generator=generator)[:n]]
    return torch.cat([seen.nonzero().squeeze(-1), pick]).sort().values


def fused_run_config(base_config, output_dir: Path, experiment_name: str, timestamp: str, data: Optional[Path] = None):
    """The base run's TrainerConfig (its own method and model) pointed at a new run folder; nothing of the
    watermark or of the plugin in it."""
    cfg = copy.deepcopy(base_config)
    relocate(cfg, output_dir, experiment_name, cfg.method_name, timestamp)
    if data is not None:
        cfg.data = None
        cfg.pipeline.datamanager.data = Path(data)
        if hasattr(cfg.pipeline.datamanager, "dataparser") and hasattr(cfg.pipeline.datamanager.dataparser, "data"):
            cfg.pipeline.datamanager.dataparser.data = Path(data)
    return cfg


def checkpoint_state(step: int, pipeline_state: Dict[str, Tensor], base_state: Dict[str, Any]) -> Dict[str, Any]:
    """A stock Nerfstudio checkpoint: the student's pipeline weights with the base checkpoint's optimizer, scheduler
    and scaler states (same parameter groups: a stock ``ns-train --load-dir`` can resume it)."""
    return {
        "step": int(step),
        "pipeline": {k: v.detach().cpu() for k, v in pipeline_state.items()},
        "optimizers": base_state.get("optimizers", {}),
        "schedulers": base_state.get("schedulers", {}),
        "scalers": base_state.get("scalers", {}),
    }


# ================================================================================================================
# the sample pool
# ================================================================================================================


@dataclass
class SamplePool:
    """Cached final-field samples of many rays with the teacher's marked density and colour at them."""

    origins: Tensor  # [R 3]
    directions: Tensor  # [R 3]
    pixel_area: Tensor  # [R 1]
    starts: Tensor  # [R S]
    ends: Tensor  # [R S]
    density: Tensor  # [R S] teacher (marked) density
    base_density: Tensor  # [R S] the base's (sticker off), for statistics
    rgb: Tensor  # [R S 3] (half) colour at the samples (the sticker does not change colour)
    changed: Tensor  # [R] bool: the sticker changes a sample of this ray

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in asdict_tensors(self))

    @staticmethod
    def cat(pools: List["SamplePool"]) -> "SamplePool":
        return SamplePool(*[torch.cat([getattr(p, f) for p in pools]) for f in SamplePool.__dataclass_fields__])

    def take(self, index: Tensor) -> "SamplePool":
        return SamplePool(*[getattr(self, f)[index] for f in SamplePool.__dataclass_fields__])


def asdict_tensors(pool: SamplePool) -> List[Tensor]:
    return [getattr(pool, f) for f in SamplePool.__dataclass_fields__]


@torch.no_grad()
def cache_view(wm_model, camera, keep_other: float, generator: torch.Generator) -> Tuple[SamplePool, Tensor]:
    """Render one camera with the watermarked model (sticker on) and cache its final samples' marked density and
    colour, and the base's density at them. Returns the pool of the kept rays and the marked render [H W 3]."""
    fld = wm_model.final_wrap.field
    records: List[Dict[str, Tensor]] = []
    original = fld.forward

    def forward(ray_samples, *args, **kwargs):
        out = original(ray_samples, *args, **kwargs)
        with wm_model.sticker_enabled(False):
            base_density, _ = fld.get_density(ray_samples)
        fr = ray_samples.frustums
        records.append(
            {
                "origins": fr.origins[:, 0].detach(),
                "directions": fr.directions[:, 0].detach(),
                "pixel_area": fr.pixel_area[:, 0].detach(),
                "starts": fr.starts[..., 0].detach(),
                "ends": fr.ends[..., 0].detach(),
                "density": out[FieldHeadNames.DENSITY][..., 0].detach().float(),
                "base_density": base_density[..., 0].detach().float(),
                "rgb": out[FieldHeadNames.RGB].detach().half(),
            }
        )
        return out

    object.__setattr__(fld, "forward", forward)
    try:
        with wm_model.sticker_enabled(True):
            outputs = wm_model.get_outputs_for_camera(camera.to(wm_model.device))
    finally:
        del fld.__dict__["forward"]
    cat = {k: torch.cat([r[k] for r in records]).cpu() for k in records[0]}
    acc = outputs["accumulation"].reshape(-1).float().cpu()
    if cat["origins"].shape[0] != acc.shape[0]:
        raise GStickerError(
            f"captured {cat['origins'].shape[0]} rays for {acc.shape[0]} pixels: the base renders in a "
            "way the fused export does not understand (nerfacto-style bases only)"
        )
    changed = (cat["density"] != cat["base_density"]).any(dim=-1)
    keep = select_rays(changed, acc, keep_other, generator)
    pool = SamplePool(
        origins=cat["origins"],
        directions=cat["directions"],
        pixel_area=cat["pixel_area"],
        starts=cat["starts"],
        ends=cat["ends"],
        density=cat["density"],
        base_density=cat["base_density"],
        rgb=cat["rgb"],
        changed=changed,
    ).take(keep)
    return pool, outputs["rgb"].detach().float().cpu()


def ray_samples_of(pool: SamplePool, device: torch.device):
    """Nerfstudio RaySamples of a pool batch (camera index 0: in eval mode nerfacto uses no appearance code)."""
    r, s = pool.starts.shape
    o = pool.origins.to(device)[:, None].expand(r, s, 3)
    d = pool.directions.to(device)[:, None].expand(r, s, 3)
    pa = pool.pixel_area.to(device)[:, None].expand(r, s, 1)
    starts = pool.starts.to(device)[..., None]
    ends = pool.ends.to(device)[..., None]
    fr = Frustums(origins=o, directions=d, starts=starts, ends=ends, pixel_area=pa)
    return RaySamples(
        frustums=fr, camera_indices=torch.zeros(r, s, 1, dtype=torch.long, device=device), deltas=ends - starts
    )


# ================================================================================================================
# the export
# ================================================================================================================


@dataclass
class FuseConfig:
    """Distil a watermarked run into a stock run of its base's method (no sticker module in the shared file)."""

    load_config: Path
    """The watermarked (ns-train geometrysticker) run's config.yml."""
    output_dir: Path = Path("outputs/fused")
    """Root of the fused run (OUTPUT_DIR/EXPERIMENT/METHOD/TIMESTAMP, as ns-train lays it out)."""
    experiment_name: str = "fused"
    timestamp: str = "fused"
    data: Optional[Path] = None
    """Dataset folder when the runs' recorded one does not exist here."""
    train_views: int = 24
    """Training cameras of the run in the pool (evenly spaced; all when larger)."""
    orbit_views: int = 12
    """Sampled novel poses in the pool (fastpath.novel_cameras: orbit or within a capture; seeded by --seed)."""
    keep_other: float = 0.1
    """Share of the empty rays (nothing seen, no sample changed) kept in the pool."""
    steps: int = 800
    """Distillation steps (defaults: the lego100 measurement of docs/experiments/bench-fuse.md)."""
    rays_per_step: int = 1024
    lr: float = 3e-4
    """Adam learning rate of the student's final field (hash grid and MLPs), decayed to lr_final."""
    lr_final: float = 3e-5
    marked_share: float = 0.5
    """Share of each batch drawn from the rays the sticker changes (the rest: uniform over the pool)."""
    losses: LossWeights = field(default_factory=LossWeights)
    seed: int = 1234
    """Pool cameras and batches (use another seed than ns-verify-owner's, 0, for an honest check)."""
    device: str = "cpu"
    log_every: int = 100
    min_transmittance: float = 1e-4
    """Samples behind this transmittance (teacher and base) are not evaluated during distillation."""
    pool_cache: Optional[Path] = None
    """Keep the sample pool in this file and reuse it when it exists (experiments)."""


def setup_runs(cfg: FuseConfig, device: torch.device):
    """Teacher (the watermarked run) and student (a fresh strict load of the base run it was made on)."""
    with contextlib.redirect_stdout(sys.stderr):
        wm_config, wm_pipeline, _ = load_run(cfg.load_config, data=cfg.data, device=device)
    wm_model = wm_pipeline.model
    if not hasattr(wm_model, "sticker_enabled"):
        raise GStickerError(
            f"{cfg.load_config} is not a watermarked (geometrysticker) run; pass the run "
            "`ns-train geometrysticker` wrote"
        )
    base_info = dict(getattr(wm_config.pipeline, "base_run", None) or {})
    base_cfg_path = Path(base_info.get("config", ""))
    if not base_cfg_path.is_file():
        raise GStickerError(
            f"the base run {base_cfg_path} the watermark was made on does not exist here; the fused "
            "export starts from it"
        )
    ckpt = Path(base_info["checkpoint"])
    base_config = runs.load_run_config(base_cfg_path)
    if base_config.method_name != base_info.get("method"):
        raise GStickerError(
            f"{base_cfg_path} is a {base_config.method_name} run, the watermark was made on a "
            f"{base_info.get('method')} run"
        )
    if not hasattr(wm_model.base, "proposal_sampler"):
        raise GStickerError(
            f"the fused export supports nerfacto-style bases (a proposal sampler that the sticker does "
            f"not mark); this base is {type(wm_model.base).__name__}"
        )
    with contextlib.redirect_stdout(sys.stderr):
        _, student_pipeline, _ = load_run(base_cfg_path, data=cfg.data, device=device)
    state = runs.load_checkpoint_state(ckpt)
    runs.strict_load(student_pipeline.model, runs.model_state_from_pipeline_state(state["pipeline"]))
    return wm_config, wm_pipeline, base_config, student_pipeline, ckpt, state


def pool_cameras(pipeline, train_views: int, orbit_views: int, seed: int) -> List[Tuple[str, Any]]:
    cams = pipeline.datamanager.train_dataset.cameras
    n = len(cams)
    k = min(train_views, n)
    idx = sorted({int(round(j * (n - 1) / max(1, k - 1))) for j in range(k)}) if k > 1 else ([0] if k else [])
    out = [(f"train/{i:03d}", cams[i : i + 1]) for i in idx]
    if orbit_views > 0:
        orbit = novel_cameras(cams, orbit_views, torch.Generator().manual_seed(seed))
        out += [(f"orbit/{i:03d}", orbit[i : i + 1]) for i in range(orbit_views)]
    return out


def build_pool(
    wm_model, cameras: List[Tuple[str, Any]], keep_other: float, seed: int, progress: bool = True
) -> SamplePool:
    gen = torch.Generator().manual_seed(seed + 1)
    pools = []
    t0 = time.time()
    for j, (_, cam) in enumerate(cameras):
        p, _ = cache_view(wm_model, cam, keep_other, gen)
        pools.append(p)
        if progress and (j + 1) % 20 == 0:
            print(
                f"[fuse] cached {j + 1}/{len(cameras)} views, {sum(len(q) for q in pools)} rays, "
                f"{time.time() - t0:.0f} s",
                file=sys.stderr,
                flush=True,
            )
    return SamplePool.cat(pools)


def student_params(model) -> List[torch.nn.Parameter]:
    """The final field's parameters (hash grid and MLPs); the proposal networks stay the base's (they place the
    samples the decoder and the renders read)."""
    return [p for p in model.field.parameters() if p.requires_grad]


def distill(
    student,
    pool: SamplePool,
    cfg: FuseConfig,
    background: Background,
    mu: float,
    device: torch.device,
    log: Optional[List[Dict[str, float]]] = None,
) -> Dict[str, float]:
    """Fine-tune the student's final field on the pool (student in eval mode: nerfacto then uses no appearance code,
    as when it renders)."""
    student.eval()
    for p in student.parameters():
        p.requires_grad_(False)
    params = [p for p in student.field.parameters()]
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=cfg.lr, eps=1e-15)
    gamma = (cfg.lr_final / cfg.lr) ** (1.0 / max(1, cfg.steps))
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
    gen = torch.Generator().manual_seed(cfg.seed + 2)
    marked = pool.changed.nonzero().squeeze(-1)
    n_marked = int(round(cfg.marked_share * cfg.rays_per_step)) if marked.numel() else 0
    steps_all = 0.5 * (pool.starts + pool.ends)
    wt = render_weights(pool.density[..., None], (pool.ends - pool.starts)[..., None])
    depth_scale = float((wt[..., 0] * steps_all).sum() / wt.sum().clamp_min(1e-12))
    floor = 1e-3 * mu
    bg = background.to(device)
    t0 = time.time()
    last: Dict[str, float] = {}
    for step in range(cfg.steps):
        idx = torch.cat(
            [
                marked[torch.randint(0, marked.numel(), (n_marked,), generator=gen)],
                torch.randint(0, len(pool), (cfg.rays_per_step - n_marked,), generator=gen),
            ]
        )
        b = pool.take(idx)
        rs = ray_samples_of(b, device)
        t_density = b.density.to(device)[..., None]
        t_rgb = b.rgb.to(device).float()
        # only samples some light reaches (teacher or base) can change a render: the field runs on those, the
        # hidden ones keep the teacher's values (no gradient)
        live = visible_samples(t_density, b.base_density.to(device)[..., None], rs.deltas, cfg.min_transmittance)
        out = student.field.forward(rs[live])
        s_density = t_density.masked_scatter(live[..., None], out[FieldHeadNames.DENSITY].reshape(-1, 1))
        s_rgb = t_rgb.masked_scatter(live[..., None].expand_as(t_rgb), out[FieldHeadNames.RGB].reshape(-1, 3))
        terms = distill_losses(
            s_density,
            s_rgb,
            t_density,
            t_rgb,
            rs.deltas,
            0.5 * (rs.frustums.starts + rs.frustums.ends),
            bg,
            depth_scale,
            floor,
            cfg.losses,
        )
        terms["live_share"] = live.float().mean()
        opt.zero_grad(set_to_none=True)
        terms["total"].backward()
        opt.step()
        sched.step()
        last = {k: float(v) for k, v in terms.items()}
        if log is not None and (step % cfg.log_every == 0 or step == cfg.steps - 1):
            row = {"step": step, "seconds": time.time() - t0, **last}
            log.append(row)
            print(
                f"[fuse] step {step}: " + " ".join(f"{k} {v:.3g}" for k, v in row.items() if k != "step"),
                file=sys.stderr,
                flush=True,
            )
    for p in student.parameters():
        p.requires_grad_(False)
    return last


def save_fused_run(
    fused_config, student_pipeline, base_state: Dict[str, Any], base_run_dir: Optional[Path] = None
) -> Path:
    """Write config.yml and nerfstudio_models/step-N.ckpt (atomic) of the fused run; returns its config.yml."""
    run_dir = Path(fused_config.get_base_dir())
    ckpt_dir = run_dir / fused_config.relative_model_dir
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yml").write_text(yaml.dump(fused_config), "utf8")
    step = int(base_state.get("step", 0))
    state = checkpoint_state(step, student_pipeline.state_dict(), base_state)
    path = ckpt_dir / f"step-{step:09d}.ckpt"
    tmp = path.with_suffix(".ckpt.tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    for f in ckpt_dir.glob("step-*.ckpt"):
        if f != path:
            f.unlink()
    if base_run_dir is not None and (Path(base_run_dir) / "dataparser_transforms.json").is_file():
        # the base's dataparser transforms travel with the run, as ns-train writes them (ns-export reads them)
        shutil.copyfile(Path(base_run_dir) / "dataparser_transforms.json", run_dir / "dataparser_transforms.json")
    return run_dir / "config.yml"


@torch.no_grad()
def compare_renders(wm_model, student, base_model_ctx, cameras: List[Tuple[str, Any]]) -> Dict[str, float]:
    """Mean PSNR of the student's renders against the watermarked and against the unwatermarked (sticker off)
    renders at ``cameras``."""

    vs_wm, vs_base, wm_vs_base = [], [], []
    for _, cam in cameras:
        cam = cam.to(wm_model.device)
        with wm_model.sticker_enabled(True):
            wm = final_rgb(wm_model.get_outputs_for_camera(cam)).cpu()
        with wm_model.sticker_enabled(False):
            base = final_rgb(wm_model.get_outputs_for_camera(cam)).cpu()
        st = final_rgb(student.get_outputs_for_camera(cam)).cpu()
        vs_wm.append(psnr(st, wm))
        vs_base.append(psnr(st, base))
        wm_vs_base.append(psnr(wm, base))
    mean = lambda xs: float(sum(xs) / len(xs))  # noqa: E731
    return {
        "fused_vs_watermarked_db": mean(vs_wm),
        "fused_vs_base_db": mean(vs_base),
        "watermarked_vs_base_db": mean(wm_vs_base),
        "views": len(cameras),
    }


def eval_cameras(pipeline, num: int) -> List[Tuple[str, Any]]:
    cams = pipeline.datamanager.eval_dataset.cameras
    n = len(cams)
    idx = sorted({int(round(j * (n - 1) / max(1, num - 1))) for j in range(num)}) if num > 1 else [0]
    return [(f"eval/{i:03d}", cams[i : i + 1]) for i in idx]


def fuse(cfg: FuseConfig) -> Dict[str, Any]:
    """The whole export; returns a summary (also written beside the run folder as RUN.fuse.json)."""
    device = torch.device(cfg.device)
    t_all = time.time()
    wm_config, wm_pipeline, base_config, student_pipeline, ckpt, base_state = setup_runs(cfg, device)
    wm_model = wm_pipeline.model
    student = student_pipeline.model
    cams = pool_cameras(wm_pipeline, cfg.train_views, cfg.orbit_views, cfg.seed)
    t0 = time.time()
    if cfg.pool_cache is not None and Path(cfg.pool_cache).is_file():
        pool = SamplePool(**torch.load(cfg.pool_cache))
    else:
        pool = build_pool(wm_model, cams, cfg.keep_other, cfg.seed)
        if cfg.pool_cache is not None:
            Path(cfg.pool_cache).parent.mkdir(parents=True, exist_ok=True)
            torch.save({f: getattr(pool, f) for f in SamplePool.__dataclass_fields__}, cfg.pool_cache)
    cache_s = time.time() - t0
    print(
        f"[fuse] pool: {len(cams)} views, {len(pool)} rays ({int(pool.changed.sum())} changed by the sticker), "
        f"{pool.nbytes() / 2**20:.0f} MiB, {cache_s:.0f} s",
        file=sys.stderr,
        flush=True,
    )
    log: List[Dict[str, float]] = []
    t0 = time.time()
    final = distill(student, pool, cfg, wm_model.background_color(), float(wm_model.final_wrap.gate.mu), device, log)
    distill_s = time.time() - t0
    fused_config = fused_run_config(base_config, cfg.output_dir, cfg.experiment_name, cfg.timestamp, cfg.data)
    config_path = save_fused_run(fused_config, student_pipeline, base_state, Path(ckpt).resolve().parent.parent)
    summary = {
        "fused_config": str(config_path),
        "method": fused_config.method_name,
        "base_checkpoint": str(ckpt),
        "watermarked_config": str(cfg.load_config),
        "pool_views": len(cams),
        "pool_rays": len(pool),
        "pool_changed_rays": int(pool.changed.sum()),
        "cache_seconds": cache_s,
        "distill_seconds": distill_s,
        "total_seconds": time.time() - t_all,
        "final_losses": final,
        "log": log,
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
    }
    run_dir = config_path.parent
    run_dir.with_name(run_dir.name + ".fuse.json").write_text(json.dumps(summary, indent=1, default=str))
    print(
        f"[fuse] fused {fused_config.method_name} run: {config_path} ({summary['total_seconds']:.0f} s)",
        file=sys.stderr,
        flush=True,
    )
    return summary


def main(cfg: FuseConfig) -> int:
    compat.apply()  # the plugin's host fixes (offline LPIPS, checkpoint types)

    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")

    def body() -> int:
        fuse(cfg)
        return 0

    return run_command(body)


def entrypoint() -> None:
    """``ns-gsticker-export fuse ...`` (one subcommand for now)."""
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", torch.get_num_threads())))
    args = sys.argv[1:]
    if args and args[0] == "fuse":
        args = args[1:]
    raise SystemExit(main(tyro.cli(FuseConfig, args=args)))


if __name__ == "__main__":
    entrypoint()
