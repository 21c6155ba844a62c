"""The field mark: the owner's message in a nerfacto base's *own* hash table, so the shared run is a stock nerfacto.

With ``T`` the base field's hash table (every level stacked, ``[L * 2^H, F]``), ``P_k`` secret per-bit tables
(Gaussian on the chosen levels, zero on the others, drawn from a secret seed), ``M`` the message and ``a`` the
amplitude::

    T~ = T + a * sum_k (2 M_k - 1) P_k / sqrt(K)

The marked field is the base's own module with another table: same method, same state-dict keys, nothing to switch
off. The hash encoding is linear in its table, so at a sample ``x`` the density logit ``pre(x)`` changes to first
order by::

    d pre / d s_k = a * g(x) . e_k(x) / sqrt(K)       g = d pre / d enc   (the density MLP's input gradient)
                                                       e_k = enc(x; P_k)   (the encoding with table P_k)

and the density by ``sigma~ = sigma * exp(sum_k s_k d pre / d s_k)`` (nerfacto's exponential activation), which the
informed decoders fit to a suspect's geometry like the sticker's. Functions here take the field's hash encoder and
density MLP (:func:`parts`), so they work on any nerfacto-style field with the torch implementation.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from dataclasses import dataclass
from typing import ClassVar, Dict, List, Optional, Sequence, Tuple

import torch
from jaxtyping import Float
from nerfstudio.field_components.field_heads import FieldHeadNames
from torch import Tensor, nn

from gsticker_plugin import hashgrid
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.sticker import render_weights


def parts(field: nn.Module) -> Tuple[nn.Module, nn.Module]:
    """(hash encoder, density MLP) of a nerfacto field built with the torch implementation."""
    seq = getattr(getattr(field, "mlp_base", None), "model", None)
    if not isinstance(seq, nn.Sequential) or len(seq) != 2 or not hasattr(seq[0], "hash_table"):
        raise GStickerError(
            f"{type(field).__name__} has no torch hash encoder and density MLP (mlp_base.model); the field mark needs "
            "a nerfacto base trained with --pipeline.model.implementation torch"
        )
    return seq[0], seq[1]


def patterns(
    table_shape: Sequence[int], table_size: int, levels: Sequence[int], num_bits: int, seed: int
) -> Float[Tensor, "K N F"]:
    """The per-bit tables: standard Gaussian on the rows of ``levels`` (level ``l`` holds rows ``l * table_size`` to
    ``(l + 1) * table_size``), zero elsewhere, drawn from ``seed`` alone."""
    n, f = int(table_shape[0]), int(table_shape[1])
    if any(not 0 <= lv < n // table_size for lv in levels):
        raise ValueError(f"levels {list(levels)} outside the table's {n // table_size} levels")
    gen = torch.Generator().manual_seed(int(seed))
    out = torch.zeros(num_bits, n, f)
    for lv in sorted(set(levels)):
        rows = slice(lv * table_size, (lv + 1) * table_size)
        out[:, rows] = torch.randn(num_bits, table_size, f, generator=gen)
    return out


def trained_rows(table: Tensor, init_scale: float) -> Tensor:
    """[N] bool: the table's rows that training moved, some entry outside the initialization's range
    ``[-init_scale, init_scale]``. The others were never sampled: they keep their small initial values in every stock
    run, so a pattern there would show, and it would change no render."""
    return table.abs().amax(-1) > init_scale


def on_rows(pats: Float[Tensor, "K N F"], rows: Tensor) -> Float[Tensor, "K N F"]:
    """The patterns zeroed outside ``rows``."""
    return pats * rows.to(pats)[None, :, None]


def marked_table(table: Tensor, pats: Float[Tensor, "K N F"], signs: Tensor, amplitude: float) -> Tensor:
    """``T + a * sum_k s_k P_k / sqrt(K)`` for signs ``s`` in [-1, 1] (``2M - 1`` for a message)."""
    k = pats.shape[0]
    return table + amplitude * torch.einsum("k,k...->...", signs.to(pats), pats).to(table) / math.sqrt(k)


def signs_of(message: Tensor) -> Tensor:
    """0/1 bits -> -1/+1 signs."""
    return message.float() * 2.0 - 1.0


def patterns_by_row(pats: Float[Tensor, "K N F"], device) -> Float[Tensor, "NF K"]:
    """The K patterns stacked as ``[N F, K]``: row ``r * F + j`` holds feature ``j`` of table row ``r`` of each."""
    k, n, f = pats.shape
    return pats.permute(1, 2, 0).reshape(n * f, k).contiguous().float().to(device)


def csr_rows(rows: Tensor, weights: Float[Tensor, "M E"], columns: int) -> Tensor:
    """A ``[M, columns]`` sparse CSR matrix whose row ``m`` holds ``weights[m, e]`` at column ``rows[m, e]`` (repeated
    columns add up)."""
    m, per_row = weights.shape
    with warnings.catch_warnings():  # columns are table rows by construction; CSR is "beta" in torch
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        crow = torch.arange(0, m * per_row + 1, per_row, device=weights.device)
        return torch.sparse_csr_tensor(
            crow, rows.reshape(-1), weights.reshape(-1), size=(m, columns), check_invariants=False
        )


def pattern_encodings(
    encoder: nn.Module, x: Float[Tensor, "M 3"], by_row: Float[Tensor, "NF K"], f: int
) -> Float[Tensor, "M L K F"]:
    """``enc(x; P_k)`` for every pattern, from the patterns stacked by :func:`patterns_by_row`: one sparse product over
    the encoding's corners (:func:`gsticker_plugin.hashgrid.corners`)."""
    rows, w = hashgrid.corners(encoder, x)  # [m L 8]
    m, levels = rows.shape[:2]
    cols = (rows[:, :, None, :] * f + torch.arange(f, device=x.device)[None, None, :, None]).reshape(-1, 8)
    weights = w[:, :, None, :].expand(m, levels, f, 8).reshape(m * levels * f, 8).float()
    out = csr_rows(cols, weights, by_row.shape[0]) @ by_row  # [(m L F) K]
    return out.reshape(m, levels, f, -1).permute(0, 1, 3, 2)


def sample_features(
    encoder: nn.Module,
    mlp: nn.Module,
    positions: Float[Tensor, "N 3"],
    pats: Float[Tensor, "K N F"],
    chunk: int = 4096,
) -> Float[Tensor, "N K"]:
    """``d pre / d s_k`` per unit amplitude at encoder-space ``positions``: ``g(x) . enc(x; P_k) / sqrt(K)``.

    The encoding is linear in its table: ``enc(x; P)[l] = sum_c w_lc P[r_lc]`` over the 8 corners of each level
    (:func:`gsticker_plugin.hashgrid.corners`), so ``g . enc(x; P_k) = sum_lc w_lc g_l . P_k[r_lc]``: a sparse matrix of the weights
    ``w_lc g_l`` (one row per position, ``L x 8 x F`` entries) times the patterns stacked as ``[N F, K]``, never K
    encodings."""
    k, n, f = pats.shape
    by_row = patterns_by_row(pats, positions.device)
    out = torch.empty(positions.shape[0], k)
    for i in range(0, positions.shape[0], chunk):
        x = positions[i : i + chunk]
        with torch.no_grad():
            enc = encoder(x)
        with torch.enable_grad():
            enc.requires_grad_(True)
            (g,) = torch.autograd.grad(mlp(enc)[..., 0].sum(), enc)
        rows, w = hashgrid.corners(encoder, x)  # [m L 8]
        m, levels = rows.shape[:2]
        values = (w[..., None] * g.reshape(m, levels, 1, f)).float().reshape(m, -1)
        columns = (rows[..., None] * f + torch.arange(f, device=rows.device)).reshape(m, -1)
        out[i : i + chunk] = csr_rows(columns, values, n * f) @ by_row
    return out / math.sqrt(k)


# ---------------------------------------------------------------------------------------------- one view


@dataclass
class FieldView:
    """One camera of the base: its final field's samples on the rays the mark can change, their per-bit features and
    the base's own geometry there (accumulation, accumulation x expected depth)."""

    rays: Tensor  # [R] flat pixel indices
    density: Tensor  # [R S 1] base density
    deltas: Tensor  # [R S 1]
    steps: Tensor  # [R S 1] sample distance along the ray
    features: Tensor  # [R S K] d pre / d s per unit amplitude (0 where the sample cannot change a render)
    base_signal: Tensor  # [C R], one row per signal
    depth_scale: float
    hw: Tuple[int, int] = (0, 0)  # the camera's image size (0, 0: not recorded)
    signals: ClassVar[Tuple[str, ...]] = ("accumulation", "expected_depth")


def capture_samples(model, camera) -> Tuple[Dict[str, Tensor], Dict[str, Tensor]]:
    """Render ``camera`` with a nerfacto model, recording its final field's samples: encoder-space positions, density,
    colour (``rgb``), deltas and distances. Returns (outputs, samples)."""
    field = model.field
    encoder, _ = parts(field)
    rec: Dict[str, List[Tensor]] = {}
    original = field.forward

    def forward(ray_samples, *args, **kwargs):
        out = original(ray_samples, *args, **kwargs)
        fr = ray_samples.frustums
        rec.setdefault("deltas", []).append(ray_samples.deltas.detach())
        rec.setdefault("steps", []).append(((fr.starts + fr.ends) / 2).detach())
        rec.setdefault("density", []).append(out[FieldHeadNames.DENSITY].detach())
        rec.setdefault("rgb", []).append(out[FieldHeadNames.RGB].detach())
        return out

    hook = encoder.register_forward_pre_hook(lambda m, inp: rec.setdefault("positions", []).append(inp[0].detach()))
    object.__setattr__(field, "forward", forward)
    try:
        with torch.no_grad():
            outputs = model.get_outputs_for_camera(camera)
    finally:
        hook.remove()
        del field.__dict__["forward"]
    samples = {k: torch.cat([x.reshape(-1, *x.shape[-2:]) for x in v]) for k, v in rec.items() if k != "positions"}
    r, s = samples["density"].shape[:2]
    samples["positions"] = torch.cat([x.reshape(-1, 3) for x in rec["positions"]]).reshape(r, s, 3)
    return outputs, samples


def geometry_of(outputs: Dict[str, Tensor]) -> Float[Tensor, "2 P"]:
    """A render's accumulation and accumulation x expected depth per pixel (``depth`` for models without an expected
    depth output, e.g. TensoRF)."""
    acc = outputs["accumulation"].reshape(-1)
    depth = outputs.get("expected_depth", outputs.get("depth"))
    return torch.stack([acc, depth.reshape(-1) * acc])


def live_samples(
    density: Float[Tensor, "R S 1"], deltas: Float[Tensor, "R S 1"], min_transmittance: float, min_alpha: float
) -> Tensor:
    """[R S] bool: the samples that light reaches (transmittance above ``min_transmittance``) and that hold some
    density (opacity above ``min_alpha``): the only ones a change of density can show in a render."""
    tau = (density * deltas)[..., 0]
    trans = torch.exp(-(torch.cumsum(tau, dim=-1) - tau))
    return (trans > min_transmittance) & (tau > min_alpha)


def field_view(model, camera, pats: Tensor, min_transmittance: float = 1e-3, min_alpha: float = 1e-4) -> FieldView:
    """Capture the base's view at ``camera`` and the per-bit features of the samples that light reaches and that hold
    some density (the others cannot change the render)."""
    outputs, smp = capture_samples(model, camera)
    dens, deltas = smp["density"], smp["deltas"]
    live = live_samples(dens, deltas, min_transmittance, min_alpha)
    rays = live.any(-1).nonzero().squeeze(-1)
    encoder, mlp = parts(model.field)
    feats = torch.zeros(rays.numel(), dens.shape[1], pats.shape[0])
    kept = live[rays]
    if kept.any():
        feats[kept] = sample_features(encoder, mlp, smp["positions"][rays][kept], pats)
    base = geometry_of(outputs)[:, rays]
    return FieldView(
        rays=rays,
        density=dens[rays],
        deltas=deltas[rays],
        steps=smp["steps"][rays],
        features=feats,
        base_signal=base,
        depth_scale=float(base[1].mean().clamp_min(1e-6)) if rays.numel() else 1.0,
        hw=(int(camera.height[0, 0]), int(camera.width[0, 0])),
    )


def geometry_from_logits(view: FieldView, change: Float[Tensor, "R S"]) -> Float[Tensor, " M"]:
    """The view's geometry (its signals: accumulation, and scaled accumulation x depth) with the density logits
    changed by ``change`` at every sample: ``sigma * exp(change)``."""
    density = view.density * torch.exp(change)[..., None]
    w = render_weights(density, view.deltas)
    return torch.cat([w.sum(-2)[..., 0], (w * view.steps).sum(-2)[..., 0] / view.depth_scale])


def predict(view: FieldView, signs: Tensor, amplitude: float) -> Float[Tensor, " M"]:
    """The view's geometry with the mark of ``signs`` at ``amplitude``."""
    return geometry_from_logits(view, amplitude * (view.features @ signs.to(view.features)))


def predict_jacobian(view: FieldView, signs: Tensor, amplitude: float) -> Float[Tensor, "M K"]:
    """d :func:`predict` / d signs. Output ``r`` of each signal depends on ray ``r``'s samples alone, so one backward
    pass per signal gives every sample's derivative, and the chain rule through the linear logits sums them per
    ray."""
    with torch.no_grad():
        change = amplitude * (view.features @ signs.to(view.features))
    change.requires_grad_(True)
    r = view.rays.numel()
    with torch.enable_grad():
        out = geometry_from_logits(view, change)
        n = len(view.signals)
        grads = [
            torch.autograd.grad(out[c * r : (c + 1) * r].sum(), change, retain_graph=c < n - 1)[0] for c in range(n)
        ]
    return torch.cat([amplitude * torch.einsum("rs,rsk->rk", g, view.features) for g in grads])


# ---------------------------------------------------------------------------------------------- TensoRF planes
#
# TensoRF's density is ``relu(sum_c plane_c(x) line_c(x))`` over its three vector-matrix planes and their lines: linear
# in the planes. The per-bit patterns are smooth tables of the planes' shape (a standard Gaussian on a coarse grid,
# upsampled), so at a sample ``pre(x)`` changes by exactly ``a * f_k(x) / sqrt(K)``, ``f_k`` the encoding with the
# planes replaced by ``P_k``, and the density by ``relu(pre + a f . s / sqrt(K))``. The decoder reads it where it is
# exact: the suspect's density at the base's samples (:class:`DensityView`), not its renders, whose fine samples
# TensoRF places by the density it renders.

PLANES_GRID = 20
"""Side of the coarse grid each plane pattern is drawn on before it is upsampled to the planes' resolution."""


def planes_of(field: nn.Module) -> nn.Module:
    """The density encoding of a TensoRF field (vector-matrix planes)."""
    enc = getattr(field, "density_encoding", None)
    if enc is None or not hasattr(enc, "plane_coef") or not hasattr(enc, "line_coef"):
        raise GStickerError(f"{type(field).__name__} has no TensoRF vector-matrix density encoding")
    return enc


def host_of(field: nn.Module) -> str:
    """Where a field's mark lives: ``hash`` (a nerfacto field's torch hash table) or ``planes`` (TensoRF's density
    planes); one-line error for any other field."""
    with contextlib.suppress(GStickerError):
        parts(field)
        return "hash"
    with contextlib.suppress(GStickerError):
        planes_of(field)
        return "planes"
    raise GStickerError(
        f"{type(field).__name__} carries no field mark: the field mark needs a nerfacto base with the torch "
        "implementation or a TensoRF base (vector-matrix); pass --pipeline.mark sticker"
    )


def marked_parameter(field: nn.Module) -> nn.Parameter:
    """The tensor the mark is written into: the hash table, or TensoRF's density planes."""
    return parts(field)[0].hash_table if host_of(field) == "hash" else planes_of(field).plane_coef


def plane_patterns(shape: Sequence[int], grid: int, num_bits: int, seed: int) -> Float[Tensor, "K ..."]:
    """The per-bit plane patterns: for each bit and plane component a standard Gaussian on a ``grid x grid`` grid,
    upsampled bilinearly to the planes' resolution and scaled to unit standard deviation; drawn from ``seed``
    alone."""
    planes, comps, h, w = (int(x) for x in shape)
    gen = torch.Generator().manual_seed(int(seed))
    coarse = torch.randn(num_bits * planes, comps, grid, grid, generator=gen)
    fine = torch.nn.functional.interpolate(coarse, size=(h, w), mode="bilinear", align_corners=True)
    fine = fine.reshape(num_bits, planes, comps, h, w)
    return fine / fine.flatten(1).std(dim=1).clamp_min(1e-12)[:, None, None, None, None]


def plane_features(
    enc: nn.Module, positions: Float[Tensor, "N 3"], pats: Tensor, chunk: int = 4096
) -> Tuple[Float[Tensor, " N"], Float[Tensor, "N K"]]:
    """The density before its relu at ``positions`` (in [-1, 1]) and ``d pre / d s_k`` per unit amplitude
    (``f_k / sqrt(K)``). The K patterns are stacked as K times the components (the lines repeated), so one pass of
    the encoding gives them all; the encoding is restored afterwards."""
    k = pats.shape[0]
    planes, comps = int(pats.shape[1]), int(pats.shape[2])
    stacked = pats.permute(1, 0, 2, 3, 4).reshape(planes, k * comps, *pats.shape[3:]).to(enc.plane_coef)
    lines = enc.line_coef.data.repeat(1, k, 1, 1)
    pre = torch.empty(positions.shape[0])
    feats = torch.empty(positions.shape[0], k)
    saved = (enc.plane_coef.data, enc.line_coef.data, enc.num_components)
    with torch.no_grad():
        for i in range(0, positions.shape[0], chunk):
            pre[i : i + chunk] = enc(positions[i : i + chunk]).sum(-1).float()
        try:
            enc.plane_coef.data, enc.line_coef.data, enc.num_components = stacked, lines, k * comps
            for i in range(0, positions.shape[0], chunk):
                f = enc(positions[i : i + chunk]).reshape(-1, planes, k, comps)
                feats[i : i + chunk] = f.sum(dim=(1, 3)).float()
        finally:
            enc.plane_coef.data, enc.line_coef.data, enc.num_components = saved
    return pre, feats / math.sqrt(k)


PROBE_SAMPLES = 32768
"""Samples of a TensoRF base's view where the suspect's density is read (evenly spaced among those with density)."""


@dataclass
class DensityView:
    """One camera of a TensoRF base, read at its samples: a fixed-size, evenly spaced share of its fine samples that
    hold density, their world positions, density before the relu and per-bit features, and the base's accumulation
    per pixel."""

    world: Float[Tensor, "N 3"]
    pre: Float[Tensor, " N"]
    features: Float[Tensor, "N K"]
    accumulation: Float[Tensor, " P"]
    hw: Tuple[int, int]


def density_view(model, camera, pats: Tensor, max_samples: int = PROBE_SAMPLES) -> DensityView:
    """Render a TensoRF base at ``camera`` recording its fine samples' world positions (the PDF pass), and keep at
    most ``max_samples`` of those with density (evenly spaced in render order) with their per-bit features."""
    from nerfstudio.data.scene_box import SceneBox

    field = model.field
    rec: Dict[str, List[Tensor]] = {}
    original = field.forward

    def forward(ray_samples, *args, **kwargs):
        out = original(ray_samples, *args, **kwargs)
        dens = out[FieldHeadNames.DENSITY].detach().reshape(-1)
        rec.setdefault("world", []).append(ray_samples.frustums.get_positions().detach().reshape(-1, 3)[dens > 0])
        return out

    object.__setattr__(field, "forward", forward)
    try:
        with torch.no_grad():
            outputs = model.get_outputs_for_camera(camera)
    finally:
        del field.__dict__["forward"]
    world = torch.cat(rec["world"]) if rec else torch.zeros(0, 3)
    if world.shape[0] > max_samples:
        world = world[torch.linspace(0, world.shape[0] - 1, max_samples).round().long()]
    enc = planes_of(field)
    pre, feats = plane_features(enc, SceneBox.get_normalized_positions(world, field.aabb) * 2 - 1, pats)
    return DensityView(
        world=world.cpu(),
        pre=pre,
        features=feats,
        accumulation=outputs["accumulation"].reshape(-1).cpu(),
        hw=(int(camera.height[0, 0]), int(camera.width[0, 0])),
    )


def density_field(model: nn.Module) -> nn.Module:
    """The field a model renders its density with: ``model.field``, or that of the first model it wraps (a recolored
    run's)."""
    from nerfstudio.fields.base_field import Field

    for module in model.modules():
        found = getattr(module, "field", None)
        if isinstance(found, Field):
            return found
    raise GStickerError(f"{type(model).__name__} has no Nerfstudio field to read density from; pass a NeRF run")


def probe_density(model, positions: Float[Tensor, "N 3"], chunk: int = 65536) -> Float[Tensor, " N"]:
    """A model's density at world ``positions``, through its field's public ``get_density`` on zero-length samples
    there (any Nerfstudio field: density is a function of position)."""
    from nerfstudio.cameras.rays import Frustums, RaySamples

    field = density_field(model)
    dev = next(field.parameters()).device
    out = torch.empty(positions.shape[0])
    for i in range(0, positions.shape[0], chunk):
        pos = positions[i : i + chunk, None].to(dev)
        n = pos.shape[0]
        zeros = torch.zeros(n, 1, 1, device=dev)
        frustums = Frustums(
            origins=pos,
            directions=torch.nn.functional.normalize(torch.ones_like(pos), dim=-1),
            starts=zeros,
            ends=zeros,
            pixel_area=torch.ones_like(zeros),
        )
        samples = RaySamples(frustums=frustums, camera_indices=torch.zeros(n, 1, 1, dtype=torch.long, device=dev))
        with torch.no_grad():
            dens = field.get_density(samples)
        dens = dens[0] if isinstance(dens, tuple) else dens
        out[i : i + n] = dens.reshape(-1).float().cpu()
    return out


def density_at(view: DensityView, signs: Tensor, amplitude: float) -> Float[Tensor, " N"]:
    """The marked density ``relu(pre + a f . s)`` at the view's samples."""
    return torch.relu(view.pre + amplitude * (view.features @ signs.to(view.features)))


def density_jacobian(view: DensityView, signs: Tensor, amplitude: float) -> Float[Tensor, "N K"]:
    """d :func:`density_at` / d signs: ``a f`` where the relu is open, 0 elsewhere."""
    opened = (view.pre + amplitude * (view.features @ signs.to(view.features))) > 0
    return amplitude * view.features * opened[:, None].to(view.features)


def view_of(model, camera, pats: Tensor):
    """The base's view at ``camera`` for its field's host: :func:`field_view` (hash) or :func:`density_view`
    (planes)."""
    return density_view(model, camera, pats) if host_of(model.field) == "planes" else field_view(model, camera, pats)


def key_patterns(field: nn.Module, mark: Dict, num_bits: int) -> Tensor:
    """The per-bit patterns a key's field mark names, on the field's host: hash patterns on the levels and the rows
    training moved, or smooth plane patterns (``mark["grid"]``)."""
    table = marked_parameter(field).data
    if mark.get("host", "hash") == "planes":
        return plane_patterns(table.shape, int(mark["grid"]), num_bits, mark["pattern_seed"])
    encoder, _ = parts(field)
    pats = patterns(table.shape, encoder.hash_table_size, mark["levels"], num_bits, mark["pattern_seed"])
    return on_rows(pats, trained_rows(table, mark["init_scale"]))


# ---------------------------------------------------------------------------------------------- images


@dataclass
class ImageView:
    """One camera of the base in colour: the rays the mark can change, the base's colour there and its derivative in
    the signs (through density and the colour head's geometry features alike)."""

    rays: Tensor  # [R] flat pixel indices
    base_rgb: Tensor  # [R 3]
    jacobian: Tensor  # [R 3 K] d rgb / d s per unit amplitude
    hw: Tuple[int, int]
    image: Optional[Tensor] = None  # [H*W 3] the base's colour at every pixel (None: not kept)
    depth: Optional[Tensor] = None  # [H*W 1] the base's expected depth at every pixel (None: not kept)
    accumulation: Optional[Tensor] = None  # [H*W 1] its accumulation


def image_view(
    model,
    camera,
    pats: Float[Tensor, "K N F"],
    chunk: int = 1024,
    min_transmittance: float = 1e-3,
    min_alpha: float = 1e-4,
    min_change: float = 1e-4,
) -> ImageView:
    """Render ``camera`` with the base and differentiate its colour in the signs at ``s = 0``.

    The hash encoding is linear in its table, so with the marked table the encoder's output at ``x`` is
    ``enc(x; T) + sum_k s_k enc(x; P_k) / sqrt(K)`` (per unit amplitude). The field's encoder is swapped for that sum,
    each ray with its own copy of ``s``; the stock field and renderer do the rest, so a backward pass per colour
    channel gives every ray's row of the Jacobian. The proposal networks and their samples are the base's (the mark
    leaves them unchanged). Only samples that light reaches and that hold some density carry the per-bit encodings
    (a first pass finds them); rays whose colour changes by less than ``min_change`` per unit amplitude are left
    out."""
    field = model.field
    encoder, _ = parts(field)
    table = encoder.hash_table
    k, n, f = pats.shape
    by_row = patterns_by_row(pats, table.device)
    original, original_field = encoder.forward, field.forward
    state: Dict[str, Tensor] = {}

    def forward(x: Tensor) -> Tensor:
        with torch.no_grad():  # the derivative is in the signs alone
            e0 = original(x)
        live = state["live"].reshape(-1)
        ek = torch.zeros(x.shape[0], e0.shape[-1] // f, k, f, dtype=e0.dtype, device=e0.device)
        if live.any():  # a chunk of rays may cross no live sample at all
            with torch.no_grad():
                ek[live] = pattern_encodings(encoder, x[live], by_row, f).to(ek)
        s = state["s"]
        per_ray = s.repeat_interleave(x.shape[0] // s.shape[0], dim=0)
        return e0 + torch.einsum("nlkf,nk->nlf", ek, per_ray).reshape(e0.shape) / math.sqrt(k)

    def field_forward(ray_samples, *args, **kwargs):
        out = original_field(ray_samples, *args, **kwargs)
        state["live"] = live_samples(
            out[FieldHeadNames.DENSITY].detach(), ray_samples.deltas, min_transmittance, min_alpha
        )
        return out

    h, w = int(camera.height[0, 0]), int(camera.width[0, 0])
    bundle = camera.to(model.device).generate_rays(camera_indices=0, keep_shape=False)
    rgb_all, jac_all, geometry_all = [], [], []
    for i in range(0, h * w, chunk):
        sub = bundle[i : i + chunk]
        object.__setattr__(field, "forward", field_forward)
        try:
            with torch.no_grad():
                first = model(sub)
        finally:
            del field.__dict__["forward"]
        geometry_all.append(torch.cat([first["expected_depth"], first["accumulation"]], dim=-1).float().cpu())
        s = torch.zeros(len(sub), k, device=table.device, requires_grad=True)
        state["s"] = s
        object.__setattr__(encoder, "forward", forward)
        try:
            with torch.enable_grad():
                rgb = model(sub)["rgb"]
                grads = [
                    torch.autograd.grad(rgb[:, c].sum(), s, retain_graph=c < 2, allow_unused=True)[0] for c in range(3)
                ]
        finally:
            del encoder.__dict__["forward"]
        grads = [torch.zeros_like(s) if g is None else g for g in grads]
        rgb_all.append(rgb.detach().float().cpu())
        jac_all.append(torch.stack(grads, dim=1).detach().float().cpu())
    rgb_full, jac_full = torch.cat(rgb_all), torch.cat(jac_all)
    rays = (jac_full.abs().amax(dim=(1, 2)) > min_change).nonzero().squeeze(-1)
    geometry = torch.cat(geometry_all)
    return ImageView(rays, rgb_full[rays], jac_full[rays], (h, w), rgb_full, geometry[:, :1], geometry[:, 1:])
