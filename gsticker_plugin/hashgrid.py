"""Nerfstudio's torch hash encoding, evaluated bit for bit but about twice as fast, for models this plugin renders.

``HashEncoding.pytorch_fwd`` hashes each of a sample's 8 grid corners per level as::

    h(x, y, z) = ((x * 1) xor (y * 2654435761) xor (z * 805459861)) mod T  +  offset_level

on int64, building each corner's coordinates with a ``cat`` and multiplying all three every time. The products
depend on one axis each, so :func:`corner_rows` forms the 6 products once (floor and ceiling per axis) and xors them
per corner; the table size ``T`` is a power of two, so ``mod T`` is ``and (T - 1)`` (equal for negative values in
two's complement). The gathers and the trilinear blend are the stock expressions in the stock order, so
:func:`encode` returns the stock output exactly (a test compares them bit for bit).

:func:`speed_up` gives the torch hash encodings of one loaded model this forward (an attribute of the instances;
Nerfstudio's class is untouched) for passes without a gradient to the table; a pass that trains the table runs the
stock code.
"""

from __future__ import annotations

import types
from typing import List, Tuple

import torch
from jaxtyping import Float
from torch import Tensor, nn

PRIMES = (1, 2654435761, 805459861)
"""The per-axis multipliers of Nerfstudio's ``HashEncoding.hash_fn``."""

CORNERS = ((1, 1, 1), (1, 0, 1), (0, 0, 1), (0, 1, 1), (1, 1, 0), (1, 0, 0), (0, 0, 0), (0, 1, 0))
"""``pytorch_fwd``'s corners in its order (``hashed_0`` ... ``hashed_7``): 1 the ceiling along x, y, z, 0 the floor."""


def corner_rows(encoder: nn.Module, ceil: Tensor, floor: Tensor) -> List[Tensor]:
    """The stacked-table rows of the 8 corners (``[..., L]`` each, in :data:`CORNERS` order) of the integer cells
    ``ceil`` / ``floor`` (``[..., L, 3]``): ``encoder.hash_fn`` of each corner."""
    size = int(encoder.hash_table_size)
    offset = encoder.hash_offset.to(ceil.device)
    axes = [
        (floor[..., d].long() * PRIMES[d], ceil[..., d].long() * PRIMES[d]) for d in range(3)
    ]  # [axis][0 floor, 1 ceiling]
    rows = []
    for cx, cy, cz in CORNERS:
        h = torch.bitwise_xor(torch.bitwise_xor(axes[0][cx], axes[1][cy]), axes[2][cz])
        h = h & (size - 1) if size & (size - 1) == 0 else h % size
        rows.append(h + offset)
    return rows


def cells(encoder: nn.Module, x: Float[Tensor, "*bs 3"]) -> Tuple[Tensor, Tensor, Tensor]:
    """The grid cell of ``x`` at every level, as ``pytorch_fwd`` computes it: its ceiling and floor corners (int32,
    ``[..., L, 3]``) and the position inside it (``[..., L, 3]``)."""
    scaled = x[..., None, :] * encoder.scalings.view(-1, 1).to(x.device)
    ceil = torch.ceil(scaled).type(torch.int32)
    floor = torch.floor(scaled).type(torch.int32)
    return ceil, floor, scaled - floor


def corners(encoder: nn.Module, x: Float[Tensor, "N 3"]) -> Tuple[Tensor, Tensor]:
    """The table rows the encoding interpolates at ``x`` (``[N L 8]``, rows of the stacked table, in :data:`CORNERS`
    order) and their trilinear weights (``[N L 8]``, summing to 1): ``enc(x)[n, l] = sum_c w[n, l, c]
    T[rows[n, l, c]]``."""
    ceil, floor, offset = cells(encoder, x)
    weights = []
    for up in CORNERS:
        w = torch.ones_like(offset[..., 0])
        for d, u in enumerate(up):
            w = w * (offset[..., d] if u else 1 - offset[..., d])
        weights.append(w)
    return torch.stack(corner_rows(encoder, ceil, floor), -1), torch.stack(weights, -1)


def encode(encoder: nn.Module, x: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs LF"]:
    """``encoder.pytorch_fwd(x)``, bit for bit."""
    ceil, floor, offset = cells(encoder, x)
    table = encoder.hash_table
    f = []
    for rows in corner_rows(encoder, ceil, floor):
        f.append(torch.index_select(table, 0, rows.reshape(-1)).reshape(*rows.shape, table.shape[-1]))
    o0, o1, o2 = offset[..., 0:1], offset[..., 1:2], offset[..., 2:3]
    p0, p1, p2 = 1 - o0, 1 - o1, 1 - o2
    f_03 = f[0] * o0 + f[3] * p0
    f_12 = f[1] * o0 + f[2] * p0
    f_56 = f[5] * o0 + f[6] * p0
    f_47 = f[4] * o0 + f[7] * p0
    f0312 = f_03 * o1 + f_12 * p1
    f4756 = f_47 * o1 + f_56 * p1
    return torch.flatten(f0312 * o2 + f4756 * p2, start_dim=-2, end_dim=-1)


def _pytorch_fwd(self, in_tensor: Tensor) -> Tensor:
    if torch.is_grad_enabled() and self.hash_table.requires_grad:
        return type(self).pytorch_fwd(self, in_tensor)
    return encode(self, in_tensor)


def speed_up(model: nn.Module) -> int:
    """Give every torch hash encoding in ``model`` :func:`encode` for passes without a gradient to its table; returns
    how many. Copies of the model (``copy.deepcopy``) keep it, bound to their own encodings."""
    from nerfstudio.field_components.encodings import HashEncoding

    count = 0
    for module in model.modules():
        if isinstance(module, HashEncoding) and getattr(module, "tcnn_encoding", None) is None:
            object.__setattr__(module, "pytorch_fwd", types.MethodType(_pytorch_fwd, module))
            count += 1
    return count
