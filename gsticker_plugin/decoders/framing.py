"""How a picture is framed against a render of the owner's base: zoom, crop offset, size and aspect ratio.

A picture found in the wild is a render at the base's intrinsics seen through a framing: resized (zoom ``s``,
possibly ``sx != sy`` for a stretched copy), then cropped or padded (offset ``t``) to a size ``W' x H'`` of any
aspect ratio. A render pixel ``(u, v)`` lands at ::

    u' = sx u + tx,    v' = sy v + ty

so the picture is the render of a camera with the same pose and intrinsics ::

    fx' = sx fx,   fy' = sy fy,   cx' = sx cx + tx,   cy' = sy cy + ty,   size W' x H'.

:func:`coarse_framing` finds the framing to a pixel by normalized cross-correlation over a set of zooms and every
offset that keeps enough overlap; :func:`refine_framing` refines it to a fraction of a pixel by Gauss-Newton on
``(log sx, log sy, tx, ty)``, a gain and offset of the colours solved in closed form at each step (a recoloured or
re-exposed copy frames the same way). Pure functions of tensors; :meth:`Framing.intrinsics` gives the picture's camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Sequence

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor

DEFAULT_ZOOMS = tuple(float(z) for z in torch.logspace(math.log10(0.5), math.log10(3.0), 19).tolist())
"""Zooms :func:`coarse_framing` tries: 0.5 to 3 times the render's size, 10 % apart."""
MIN_VARIANCE = (2.0 / 255.0) ** 2
"""Least variance per pixel of picture and render over an overlap :func:`coarse_framings` scores."""


@dataclass(frozen=True)
class Framing:
    """``u' = sx u + tx``, ``v' = sy v + ty`` from render pixels (base intrinsics) to picture pixels; ``score``: the
    normalized cross-correlation of picture and framed render over their overlap (1 is a perfect match)."""

    sx: float
    sy: float
    tx: float
    ty: float
    score: float = float("nan")

    def intrinsics(self, fx: float, fy: float, cx: float, cy: float):
        """The picture's ``(fx, fy, cx, cy)`` from the render's."""
        return self.sx * fx, self.sy * fy, self.sx * cx + self.tx, self.sy * cy + self.ty


def _gray(image: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W"]:
    return image.float().mean(dim=-1) if image.dim() == 3 else image.float()


def warp_render(
    render: Float[Tensor, "H W C"], framing: Framing, height: int, width: int
) -> tuple[Float[Tensor, "h w C"], Float[Tensor, "h w"]]:
    """The render as the picture would show it under ``framing`` (bilinear), and where the picture sees the render
    (1 inside its frame, 0 on padding)."""
    h0, w0 = render.shape[0], render.shape[1]
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32), indexing="ij"
    )
    # picture pixel centres -> render pixel centres (pixel centres at +0.5)
    ur = (u + 0.5 - framing.tx) / framing.sx - 0.5
    vr = (v + 0.5 - framing.ty) / framing.sy - 0.5
    grid = torch.stack([(ur + 0.5) / w0 * 2 - 1, (vr + 0.5) / h0 * 2 - 1], dim=-1)[None]
    src = render.float().permute(2, 0, 1)[None] if render.dim() == 3 else render.float()[None, None]
    out = F.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=False)[0].permute(1, 2, 0)
    inside = ((ur >= -0.5) & (ur <= w0 - 0.5) & (vr >= -0.5) & (vr <= h0 - 0.5)).float()
    return out, inside


def _ncc_masked(a: Tensor, b: Tensor, mask: Tensor) -> float:
    n = mask.sum()
    if n < 16:
        return float("-inf")
    am = (a * mask).sum() / n
    bm = (b * mask).sum() / n
    da, db = (a - am) * mask, (b - bm) * mask
    den = torch.sqrt((da * da).sum() * (db * db).sum()).clamp_min(1e-12)
    return float((da * db).sum() / den)


def _resize(image: Tensor, height: int, width: int) -> Tensor:
    """Area average when shrinking, bilinear when growing."""
    if height <= image.shape[0] and width <= image.shape[1]:
        return F.interpolate(image[None, None], size=(height, width), mode="area")[0, 0]
    return F.interpolate(image[None, None], size=(height, width), mode="bilinear", align_corners=False)[0, 0]


def coarse_framings(
    picture: Float[Tensor, "H W 3"],
    renders: Float[Tensor, "N h w 3"],
    zooms: Sequence[float] = DEFAULT_ZOOMS,
    side: int = 32,
    min_overlap: float = 0.5,
    min_render_share: float = 0.2,
    min_picture_share: float = 0.5,
) -> List[Framing]:
    """For each render, the framing of ``picture`` against it to about one working pixel: for every zoom (picture px
    per render px) and every integer offset, the normalized cross-correlation of the grey levels over the overlap,
    which must cover ``min_overlap`` of the smaller of the two, ``min_render_share`` of the render and
    ``min_picture_share`` of the picture (a few pixels matched say nothing); the best pair wins. Picture and zoomed render are
    worked at a size whose larger side is ``side`` px; every render is correlated in one batched convolution per
    zoom. Isotropic (``sx == sy``): :func:`refine_framing` frees the aspect."""
    pic = _gray(picture)
    ren = renders.float().mean(dim=-1) if renders.dim() == 4 else renders.float()
    n_r, h0, w0 = ren.shape
    ph, pw = pic.shape
    best_score = torch.full((n_r,), float("-inf"))
    best = [Framing(1.0, 1.0, 0.0, 0.0, float("-inf")) for _ in range(n_r)]
    for z in zooms:
        k = side / max(ph, pw, h0 * z, w0 * z)  # working px per picture px
        sh, sw = max(4, round(ph * k)), max(4, round(pw * k))
        rh, rw = max(4, round(h0 * z * k)), max(4, round(w0 * z * k))
        ps = _resize(pic, sh, sw).double()
        rs = F.interpolate(ren[:, None], size=(rh, rw), mode="area" if rh <= h0 else "bilinear").double()
        need = max(min_overlap * min(sh * sw, rh * rw), min_render_share * rh * rw, min_picture_share * sh * sw)
        pad = F.pad(ps[None, None], (rw - 1, rw - 1, rh - 1, rh - 1))
        ones = F.pad(torch.ones(1, 1, sh, sw, dtype=torch.float64), (rw - 1, rw - 1, rh - 1, rh - 1))
        kones = torch.ones(1, 1, rh, rw, dtype=torch.float64)
        n = F.conv2d(ones, kones)[0]  # [1 Y X]
        s_p = F.conv2d(pad, kones)[0]
        s_pp = F.conv2d(pad * pad, kones)[0]
        s_r = F.conv2d(ones, rs)[0]  # [N Y X]
        s_rr = F.conv2d(ones, rs * rs)[0]
        s_pr = F.conv2d(pad, rs)[0]
        nn = n.clamp_min(1)
        cov = s_pr - s_p * s_r / nn
        var_p = (s_pp - s_p**2 / nn).clamp_min(0)
        var_r = (s_rr - s_r**2 / nn).clamp_min(0)
        flat = (var_p < MIN_VARIANCE * nn) | (var_r < MIN_VARIANCE * nn)  # a flat overlap says nothing
        score = cov / (var_p * var_r).clamp_min(1e-300).sqrt()
        score = torch.where((n >= need) & ~flat, score, torch.tensor(-2.0, dtype=torch.float64))
        flat = score.reshape(n_r, -1)
        top, idx = flat.max(dim=1)
        for i in torch.nonzero(top > best_score).reshape(-1).tolist():
            y, x = divmod(int(idx[i]), score.shape[2])
            # the render's top-left at (x - (rw - 1), y - (rh - 1)) working px; the render's px at z picture px
            best[i] = Framing(rw / k / w0, rh / k / h0, (x - (rw - 1)) / k, (y - (rh - 1)) / k, float(top[i]))
            best_score[i] = top[i]
    return best


def coarse_framing(
    picture: Float[Tensor, "H W 3"],
    render: Float[Tensor, "h w 3"],
    zooms: Sequence[float] = DEFAULT_ZOOMS,
    side: int = 32,
    min_overlap: float = 0.5,
) -> Framing:
    """:func:`coarse_framings` of one render."""
    return coarse_framings(picture, render[None], zooms, side, min_overlap)[0]


def refine_framing(
    picture: Float[Tensor, "H W 3"],
    render: Float[Tensor, "h w 3"],
    start: Framing,
    iterations: int = 30,
    anisotropic: bool = True,
) -> Framing:
    """``start`` refined to a fraction of a pixel: Gauss-Newton on ``(log sx, log sy, tx, ty)`` (``log sx = log sy``
    unless ``anisotropic``) of ``sum (a R(warp) + b - P)^2`` over the pixels where the picture sees the render, the
    gain ``a`` and offset ``b`` solved in closed form at every step; a step is kept only if it lowers the cost."""
    pic, ren = _gray(picture), _gray(render)
    h, w = pic.shape
    h0, w0 = ren.shape
    gx = torch.zeros_like(ren)
    gy = torch.zeros_like(ren)
    gx[:, 1:-1] = (ren[:, 2:] - ren[:, :-2]) / 2
    gy[1:-1] = (ren[2:] - ren[:-2]) / 2
    stack = torch.stack([ren, gx, gy])[None]
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    params = torch.tensor([math.log(start.sx), math.log(start.sy), start.tx, start.ty], dtype=torch.float64)

    def residual(p: Tensor, jacobian: bool = False):
        """Residual over the pixels that see the render; with ``jacobian``, its derivative in ``p`` (the gain held)."""
        sx, sy = math.exp(float(p[0])), math.exp(float(p[1] if anisotropic else p[0]))
        ur = (u + 0.5 - float(p[2])) / sx - 0.5
        vr = (v + 0.5 - float(p[3])) / sy - 0.5
        grid = torch.stack([(ur + 0.5) / w0 * 2 - 1, (vr + 0.5) / h0 * 2 - 1], dim=-1)[None].float()
        sampled = F.grid_sample(stack, grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
        inside = (ur >= 0) & (ur <= w0 - 1) & (vr >= 0) & (vr <= h0 - 1)
        x, y = sampled[0][inside].double(), pic[inside].double()
        if x.numel() < 16:
            return torch.full((1,), float("inf"), dtype=torch.float64), None
        xm, ym = x.mean(), y.mean()
        a = ((x - xm) * (y - ym)).sum() / ((x - xm) ** 2).sum().clamp_min(1e-12)
        r = a * (x - xm) + ym - y
        if not jacobian:
            return r, None
        dxu, dxv = sampled[1][inside].double(), sampled[2][inside].double()
        cols = torch.stack(
            [
                -dxu * (ur[inside] + 0.5),  # d/d log sx
                -dxv * (vr[inside] + 0.5),  # d/d log sy
                -dxu / sx,  # d/d tx
                -dxv / sy,  # d/d ty
            ],
            dim=1,
        )
        if not anisotropic:
            cols = torch.stack([cols[:, 0] + cols[:, 1], torch.zeros_like(cols[:, 1]), cols[:, 2], cols[:, 3]], dim=1)
        return r, a * (cols - cols.mean(dim=0))

    def cost(p: Tensor) -> float:
        r, _ = residual(p)
        return float((r * r).mean())

    best = cost(params)
    for _ in range(iterations):
        r, jac = residual(params, jacobian=True)
        if jac is None:
            break
        jtj = jac.T @ jac + 1e-9 * torch.eye(4, dtype=torch.float64)
        step = torch.linalg.solve(jtj, -(jac.T @ r))
        for scale in (1.0, 0.5, 0.25):
            trial = params + scale * step
            if not anisotropic:
                trial[1] = trial[0]
            c = cost(trial)
            if c < best:
                params, best = trial, c
                break
        else:
            break
    sx, sy = float(torch.exp(params[0])), float(torch.exp(params[1] if anisotropic else params[0]))
    framing = Framing(sx, sy, float(params[2]), float(params[3]))
    warped, seen = warp_render(render, framing, h, w)
    return Framing(sx, sy, framing.tx, framing.ty, _ncc_masked(_gray(warped), pic, seen))


def find_framing(
    picture: Float[Tensor, "H W 3"], render: Float[Tensor, "h w 3"], zooms: Sequence[float] = DEFAULT_ZOOMS
) -> Framing:
    """:func:`coarse_framing`, then :func:`refine_framing`."""
    return refine_framing(picture, render, coarse_framing(picture, render, zooms))
