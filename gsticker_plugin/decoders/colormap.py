"""A smooth colour map (a trilinear lookup table over the RGB cube) fitted from a base render to a recoloured image.

A palette edit, a hue turn or a colour fine-tune changes the colour every sample of the model renders, close to a
smooth function of that colour. The informed image decoder takes its sample colours from the owner's base; for an
image of a recoloured copy it can take them through this map instead (docs/verify.md). The map is fitted from the
image and the base render only, never from the owner's message.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch
from jaxtyping import Float
from torch import Tensor


def corner_weights(rgb: Float[Tensor, "N 3"], nodes: int) -> Tuple[Tensor, Tensor]:
    """The 8 lattice nodes around each colour (flat indices ``[N 8]``) and their trilinear weights ``[N 8]``."""
    p = rgb.double().clamp(0.0, 1.0) * (nodes - 1)
    i0 = p.floor().clamp(0, nodes - 2)
    f = p - i0
    i0 = i0.long()
    idx, wts = [], []
    for dr in (0, 1):
        for dg in (0, 1):
            for db in (0, 1):
                d = torch.tensor([dr, dg, db])
                corner = i0 + d
                idx.append((corner[:, 0] * nodes + corner[:, 1]) * nodes + corner[:, 2])
                w = torch.where(d.bool(), f, 1.0 - f).prod(dim=-1)
                wts.append(w)
    return torch.stack(idx, dim=1), torch.stack(wts, dim=1)


def identity_table(nodes: int) -> Float[Tensor, "G G G 3"]:
    """The table that maps every colour to itself."""
    t = torch.linspace(0.0, 1.0, nodes, dtype=torch.float64)
    return torch.stack(torch.meshgrid(t, t, t, indexing="ij"), dim=-1)


def apply_color_map(table: Float[Tensor, "G G G 3"], rgb: Float[Tensor, "... 3"]) -> Float[Tensor, "... 3"]:
    """``rgb`` through ``table`` (trilinear), clamped to [0, 1]; differentiable in ``rgb``."""
    g = table.shape[0]
    flat = rgb.reshape(-1, 3)
    p = flat.clamp(0.0, 1.0) * (g - 1)
    i0 = p.detach().floor().clamp(0, g - 2)
    f = p - i0
    i0 = i0.long()
    t = table.reshape(-1, 3).to(flat.dtype)
    out = torch.zeros_like(flat)
    for dr in (0, 1):
        for dg in (0, 1):
            for db in (0, 1):
                d = torch.tensor([dr, dg, db], device=flat.device)
                corner = i0 + d
                w = torch.where(d.bool(), f, 1.0 - f).prod(dim=-1, keepdim=True)
                out = out + w * t[(corner[:, 0] * g + corner[:, 1]) * g + corner[:, 2]]
    return out.clamp(0.0, 1.0).reshape(rgb.shape)


def fit_color_map(
    source: Float[Tensor, "N 3"],
    target: Float[Tensor, "N 3"],
    weights: Optional[Float[Tensor, " N"]] = None,
    nodes: int = 6,
    smooth: float = 1e-3,
    prior: float = 1e-4,
) -> Float[Tensor, "G G G 3"]:
    """The table whose map takes ``source`` colours nearest ``target`` (weighted least squares), with a discrete
    Laplacian penalty ``smooth`` between neighbouring nodes and a pull ``prior`` toward the identity (nodes no colour
    reaches stay where they were); both relative to the mean data weight."""
    g = nodes
    n = g**3
    idx, wts = corner_weights(source, g)
    w = torch.ones(source.shape[0], dtype=torch.float64) if weights is None else weights.double()
    a = torch.zeros(n, n, dtype=torch.float64)
    rows = (wts * w[:, None].sqrt()).reshape(-1)
    cols = idx.reshape(-1)
    obs = torch.arange(source.shape[0]).repeat_interleave(8)
    design = torch.zeros(source.shape[0], n, dtype=torch.float64)
    design.index_put_((obs, cols), rows, accumulate=True)
    a += design.T @ design
    b = design.T @ (target.double() * w[:, None].sqrt())
    scale = float(w.sum()) / n
    lap = torch.zeros(n, n, dtype=torch.float64)
    grid = torch.arange(n).reshape(g, g, g)
    for axis in range(3):
        lo = grid.narrow(axis, 0, g - 1).reshape(-1)
        hi = grid.narrow(axis, 1, g - 1).reshape(-1)
        d = torch.zeros(lo.numel(), n, dtype=torch.float64)
        d[torch.arange(lo.numel()), lo] = -1.0
        d[torch.arange(lo.numel()), hi] = 1.0
        lap += d.T @ d
    ident = identity_table(g).reshape(n, 3)
    a += scale * (smooth * lap + prior * torch.eye(n, dtype=torch.float64))
    b += scale * (smooth * lap @ ident + prior * ident)
    return torch.linalg.solve(a, b).reshape(g, g, g, 3)
