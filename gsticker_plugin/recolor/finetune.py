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

from typing import Callable, Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

from gsticker_plugin.errors import GStickerError
from gsticker_plugin.recolor.model import require_color_fields, unwrap


def _probe_rays(model, cameras, num_rays: int = 256, seed: int = 0):
    from nerfstudio.model_components.ray_generators import RayGenerator

    cams = cameras.to(model.device)
    gen = RayGenerator(cams)
    g = torch.Generator().manual_seed(seed)
    h, w = int(cams.height[0]), int(cams.width[0])
    idx = torch.stack([torch.zeros(num_rays, dtype=torch.long),
                       torch.randint(0, h, (num_rays,), generator=g),
                       torch.randint(0, w, (num_rays,), generator=g)], -1)
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
                raise GStickerError(f"{type(base).__name__}'s fields computed no density while rendering; "
                                    "fine-tune a NeRF-style run (nerfacto, vanilla-nerf, tensorf)")
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
        raise GStickerError(f"{type(base).__name__} has no color parameters separate from its density (every field "
                            "parameter affects density); fine-tune a run with a color branch (nerfacto, vanilla-nerf, tensorf)")
    return color, density


def finetune_color(model: nn.Module, cameras, targets: Sequence[Tensor], steps: int, lr: float = 5e-3,
                   rays_per_step: int = 1024, seed: int = 0, progress: bool = True,
                   color_params: Optional[Dict[str, nn.Parameter]] = None,
                   on_step: Optional[Callable[[int, List[float]], None]] = None) -> Dict[str, List[float]]:
    """Adam on the color parameters only, MSE of rendered rays vs target pixels of random training views.

    ``targets[i]`` is the [H, W, 3] target image of ``cameras[i]``. ``on_step(k, losses)`` runs after step k
    (1-based; the model holds the weights after k steps). Returns {"loss": per step}.
    """
    from tqdm import tqdm

    from nerfstudio.model_components.ray_generators import RayGenerator

    if color_params is None:
        color_params, _ = split_color_parameters(model, cameras)
    for p in model.parameters():
        p.requires_grad_(False)
    params = list(color_params.values())
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=lr, eps=1e-15)
    cams = cameras.to(model.device)
    gen = RayGenerator(cams)
    g = torch.Generator().manual_seed(seed)
    n = len(targets)
    hs = [t.shape[0] for t in targets]
    ws = [t.shape[1] for t in targets]
    stacked = torch.stack([t.to(model.device) for t in targets])  # same size views (one camera model)
    history: List[float] = []
    bar = tqdm(range(steps), desc="fine-tuning color", disable=not progress)
    try:
        for _ in bar:
            c = torch.randint(0, n, (rays_per_step,), generator=g)
            y = (torch.rand(rays_per_step, generator=g) * torch.tensor(hs)[c]).long()
            x = (torch.rand(rays_per_step, generator=g) * torch.tensor(ws)[c]).long()
            idx = torch.stack([c, y, x], -1).to(model.device)
            bundle = gen(idx)
            target = stacked[idx[:, 0], idx[:, 1], idx[:, 2]]
            out = model.forward(bundle)
            rgb = out.get("rgb", out.get("rgb_fine"))
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
