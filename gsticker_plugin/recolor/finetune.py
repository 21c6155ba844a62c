"""The determined attacker's recolor: fine-tune only the color branch of a run (density frozen) toward targets.

Which parameters are "color" is decided per field by the gradient of density, not by names: a probe renders a
few rays, sums the density that each color field's ``get_density`` returns and back-propagates; every field
parameter that receives a gradient influences density (nerfacto's hash grid and base MLP, vanilla-nerf's
position MLP, TensoRF's density planes) and stays frozen, as do scene bounds (TensoRF's ``aabb``). The field's remaining parameters (nerfacto's color
head and appearance embedding, vanilla-nerf's view-dependent head and RGB head, TensoRF's color planes, basis
and color MLP) are the color branch. Everything outside the color fields (proposal networks, a sticker, the
camera optimizer) is frozen too, so density, and with it the geometry and any GeometrySticker, is bit-identical.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Tuple, Union

import torch
from jaxtyping import Float, Int
from nerfstudio.model_components.ray_generators import RayGenerator
from torch import Tensor, nn
from tqdm import tqdm

from gsticker_plugin.errors import GStickerError
from gsticker_plugin.recolor.model import require_color_fields, unwrap
from gsticker_plugin.runs import final_rgb


def _probe_rays(model, cameras, num_rays: int = 256, seed: int = 0):
    cams = cameras.to(model.device)
    gen = RayGenerator(cams)
    g = torch.Generator().manual_seed(seed)
    h, w = int(cams.height[0]), int(cams.width[0])
    idx = torch.stack(
        [
            torch.zeros(num_rays, dtype=torch.long),
            torch.randint(0, h, (num_rays,), generator=g),
            torch.randint(0, w, (num_rays,), generator=g),
        ],
        -1,
    )
    # central rays hit the object: bias half of them to the image centre
    idx[: num_rays // 2, 1] = h // 4 + torch.randint(0, max(h // 2, 1), (num_rays // 2,), generator=g)
    idx[: num_rays // 2, 2] = w // 4 + torch.randint(0, max(w // 2, 1), (num_rays // 2,), generator=g)
    return gen(idx.to(model.device))


def split_color_parameters(model: nn.Module, cameras) -> Tuple[Dict[str, nn.Parameter], Dict[str, nn.Parameter]]:
    """({name: color parameter}, {name: density parameter}) of the color fields of ``model`` (names relative to it)."""
    base = unwrap(model)
    fields = require_color_fields(base)
    names = {id(p): n for n, p in model.named_parameters()}
    candidates: Dict[str, nn.Parameter] = {}
    for _, fld in fields:
        for _, p in fld.named_parameters():
            candidates[names[id(p)]] = p
    saved = {n: (p.requires_grad, p.grad) for n, p in model.named_parameters()}
    records: List[Tensor] = []
    installed = []
    for _, fld in fields:
        prev = fld.__dict__.get("get_density")
        call = fld.get_density

        def rec(ray_samples, *args, _call=call, **kwargs):
            out = _call(ray_samples, *args, **kwargs)
            records.append(out[0] if isinstance(out, tuple) else out)
            return out

        object.__setattr__(fld, "get_density", rec)
        installed.append((fld, prev))
    try:
        for p in model.parameters():
            p.requires_grad_(True)
            p.grad = None
        with torch.enable_grad():
            model.forward(_probe_rays(model, cameras))
            total = sum(r.float().sum() for r in records if r.requires_grad)
            if not records or not isinstance(total, Tensor):
                raise GStickerError(
                    f"{type(base).__name__}'s fields computed no density while rendering; "
                    "fine-tune a NeRF-style run (nerfacto, vanilla-nerf, tensorf)"
                )
            total.backward()
        density = {n: p for n, p in candidates.items() if p.grad is not None}
    finally:
        for fld, prev in installed:
            if prev is not None:
                object.__setattr__(fld, "get_density", prev)
            else:
                del fld.__dict__["get_density"]
        for n, p in model.named_parameters():
            p.requires_grad_(saved[n][0])
            p.grad = saved[n][1]
    # Scene bounds stored as (non-trainable) parameters, e.g. TensoRF's aabb, are geometry, never color.
    color = {n: p for n, p in candidates.items() if n not in density and n.rsplit(".", 1)[-1] != "aabb"}
    if not color:
        raise GStickerError(
            f"{type(base).__name__} has no color parameters separate from its density (every field "
            "parameter affects density); fine-tune a run with a color branch (nerfacto, vanilla-nerf, tensorf)"
        )
    return color, density


def ray_schedule(
    num_views: int, hw: Tuple[int, int], steps: int, rays_per_step: int, seed: int = 0
) -> Int[Tensor, "T R 3"]:
    """The (view, row, column) of every ray of every fine-tune step: ``rays_per_step`` random pixels of random
    views per step, drawn from one generator seeded with ``seed`` (the rays never depend on the model)."""
    g = torch.Generator().manual_seed(seed)
    h, w = int(hw[0]), int(hw[1])
    out = torch.empty(steps, rays_per_step, 3, dtype=torch.long)
    for t in range(steps):
        c = torch.randint(0, num_views, (rays_per_step,), generator=g)
        out[t, :, 0] = c
        out[t, :, 1] = (torch.rand(rays_per_step, generator=g) * h).long()
        out[t, :, 2] = (torch.rand(rays_per_step, generator=g) * w).long()
    return out


@dataclass
class RayTargets:
    """Per-step target colors of a fine-tune: ``values[t]`` are the targets of the rays ``schedule[t]``."""

    schedule: Int[Tensor, "T R 3"]
    values: Float[Tensor, "T R 3"]


@torch.no_grad()
def render_ray_targets(
    model, cameras, schedule: Int[Tensor, "T R 3"], chunk: int = 4096, progress: bool = True
) -> RayTargets:
    """The model's colors at exactly the pixels a fine-tune will visit (each distinct pixel rendered once).

    What the fine-tune reads from full renders of every view, at a fraction of the cost: ``T * R`` draws from
    ``V * H * W`` pixels visit about ``1 - exp(-T R / (V H W))`` of them (300 x 1024 of 100 x 100 x 100: 26 %).
    Rays are generated as full renders generate them (pixel centres), clamped to [0, 1] as ``render_views`` does.
    """
    flat = schedule.reshape(-1, 3)
    uniq, inverse = torch.unique(flat, dim=0, return_inverse=True)
    gen = RayGenerator(cameras.to(model.device))
    parts = []
    for i in tqdm(
        range(0, uniq.shape[0], chunk),
        desc=f"rendering targets ({uniq.shape[0]} pixels)",
        leave=False,
        disable=not progress,
    ):
        out = model.forward(gen(uniq[i : i + chunk].to(model.device)))
        rgb = final_rgb(out)
        parts.append(rgb.detach().float().clamp(0.0, 1.0).cpu())
    values = torch.cat(parts)[inverse].reshape(*schedule.shape[:2], 3)
    return RayTargets(schedule=schedule, values=values)


def finetune_color(
    model: nn.Module,
    cameras,
    targets: Union[Sequence[Tensor], RayTargets],
    steps: int,
    lr: float = 5e-3,
    rays_per_step: int = 1024,
    seed: int = 0,
    progress: bool = True,
    color_params: Optional[Dict[str, nn.Parameter]] = None,
    on_step: Optional[Callable[[int, List[float]], None]] = None,
    desc: str = "fine-tuning color",
) -> Dict[str, List[float]]:
    """Adam on the color parameters only, MSE of rendered rays vs target pixels of random training views.

    ``targets``: the [H, W, 3] target image of each of ``cameras`` (rays from :func:`ray_schedule` with ``seed``),
    or :class:`RayTargets` (its schedule and per-ray colors; at least ``steps`` steps of ``rays_per_step`` rays):
    the same fine-tune when its values are the images' pixels. ``on_step(k, losses)`` runs after step k (1-based;
    the model holds the weights after k steps); ``desc`` labels the progress bar. Returns {"loss": per step}.
    """
    if isinstance(targets, RayTargets):
        schedule, values = targets.schedule, targets.values
        if schedule.shape[0] < steps or schedule.shape[1] != rays_per_step:
            raise GStickerError(
                f"the ray targets hold {schedule.shape[0]} steps of {schedule.shape[1]} rays; this "
                f"fine-tune needs {steps} of {rays_per_step}"
            )
    else:
        hw = (targets[0].shape[0], targets[0].shape[1])
        if any((t.shape[0], t.shape[1]) != hw for t in targets):
            raise GStickerError("the fine-tune's target images differ in size; give one size (one camera model)")
        schedule = ray_schedule(len(targets), hw, steps, rays_per_step, seed)
        stacked = torch.stack([t[..., :3].float() for t in targets])
        values = stacked[schedule[..., 0], schedule[..., 1], schedule[..., 2]]
    if color_params is None:
        color_params, _ = split_color_parameters(model, cameras)
    for p in model.parameters():
        p.requires_grad_(False)
    params = list(color_params.values())
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=lr, eps=1e-15)
    gen = RayGenerator(cameras.to(model.device))
    history: List[float] = []
    bar = tqdm(range(steps), desc=desc, disable=not progress)
    try:
        for t in bar:
            bundle = gen(schedule[t].to(model.device))
            target = values[t].to(model.device)
            out = model.forward(bundle)
            rgb = final_rgb(out)
            loss = torch.nn.functional.mse_loss(rgb, target)
            if isinstance(out.get("rgb_coarse"), Tensor):  # vanilla-nerf: its coarse field renders color too
                loss = loss + torch.nn.functional.mse_loss(out["rgb_coarse"], target)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            history.append(float(loss.detach()))
            bar.set_postfix(loss=f"{history[-1]:.5f}")
            if on_step is not None:
                on_step(len(history), history)
    finally:
        for p in params:
            p.requires_grad_(False)
            p.grad = None
    return {"loss": history}
