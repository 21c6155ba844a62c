"""The least-squares fit every informed decoder shares: a continuous message fitted to a suspect, then bits."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Dict, Optional, Tuple

import torch
from jaxtyping import Float, Int
from torch import Tensor
from torch.func import jvp, vmap

from gsticker_plugin.sticker import Sticker


@dataclass
class Fit:
    signs: Float[Tensor, " K"]
    explained: float  # 1 - |residual after| ^2 / |residual before| ^2 (0 when there is nothing to explain)
    residual_rms: float  # of the target (suspect minus base), in signal units
    iterations: int


def jacobian(fn: Callable[[Tensor], Tensor], s: Float[Tensor, " K"], chunk: int = 16) -> Float[Tensor, "M K"]:
    """d fn / d s by forward-mode AD, ``chunk`` directions at a time (memory stays bounded)."""
    eye = torch.eye(s.numel(), dtype=s.dtype, device=s.device)
    cols = []
    for i in range(0, s.numel(), chunk):
        cols.append(vmap(lambda v: jvp(fn, (s,), (v,))[1].reshape(-1))(eye[i : i + chunk]))
    return torch.cat(cols).T


def per_ray_jacobian(
    change: Callable[[Tensor], Tensor],
    sticker: Sticker,
    features: Float[Tensor, "N F"],
    signs: Float[Tensor, " K"],
    ray_of_sample: Int[Tensor, " N"],
    num_rays: int,
) -> Optional[Float[Tensor, "C R K"]]:
    """d change(mix(features, s)) / d s at ``signs``, when output ``[c, r]`` of ``change`` ([C R], a function of the
    sticker values at the gate-open samples) depends on the samples of ray ``r`` only; None for a sticker without a
    closed-form :meth:`Sticker.mix_jacobian` (``concat``: use :func:`jacobian`).

    Then d sum_r change[c, r] / d m_j is d change[c, ray(j)] / d m_j, so C backward passes give every sample's
    derivative, and the chain rule through the sticker's own Jacobian sums them per ray: the same matrix as
    forward-mode AD over the K directions, without K passes of the renderer.
    """
    if sticker.kind != "bilinear":
        return None
    with torch.no_grad():
        m = sticker.mix(features, signs)
    dm_ds = sticker.mix_jacobian(features, m)
    m = m.requires_grad_(True)
    with torch.enable_grad():
        out = change(m)
        grads = [
            torch.autograd.grad(out[c].sum(), m, retain_graph=c + 1 < out.shape[0])[0] for c in range(out.shape[0])
        ]
    k = dm_ds.shape[1]
    return torch.stack(
        [
            torch.zeros(num_rays, k, dtype=dm_ds.dtype, device=dm_ds.device).index_add(0, ray_of_sample, g * dm_ds)
            for g in grads
        ]
    )


def fit_message(
    predict: Callable[[Tensor], Tensor],
    target: Float[Tensor, " M"],
    num_bits: int,
    iterations: int = 10,
    damping: float = 1e-3,
    jac: Optional[Callable[[Tensor], Optional[Tensor]]] = None,
    restarts: int = 3,
    corner_rounds: int = 2,
) -> Fit:
    """Least squares ``min_s |target - (predict(s) - predict(0))|^2`` over ``s in [-1, 1]^K``.

    Levenberg-Marquardt from ``s = 0`` (Jacobians from ``jac(s)`` when it gives one, else by forward-mode AD;
    normal equations in float64, steps clamped to the box); up to ``restarts`` times again from the corner
    ``sign(s)`` of the best fit so far while that lowers the residual (a fit stuck between basins beside a marked
    corner slides into it from there); then ``corner_rounds`` rounds of :func:`corner_search` from each fit, the
    lowest residual kept. A zero target returns ``s = 0`` exactly.
    """
    s = torch.zeros(num_bits, dtype=target.dtype, device=target.device)
    with torch.no_grad():
        f0 = predict(s).reshape(-1)
    target = target.reshape(-1)
    cost0 = float((target.double() ** 2).sum())
    rms = (cost0 / max(1, target.numel())) ** 0.5
    if cost0 == 0.0:
        return Fit(signs=s, explained=0.0, residual_rms=0.0, iterations=0)

    def residual(x: Tensor) -> Tensor:
        with torch.no_grad():
            return target - (predict(x).reshape(-1) - f0)

    s, cost, it = levenberg_marquardt(predict, f0, residual, s, iterations, damping, jac, cost0)
    fits = [(s, cost)]
    tried = set()
    for _ in range(restarts):
        corner = corner_of(s)
        if tuple(corner.tolist()) in tried:
            break
        tried.add(tuple(corner.tolist()))
        s2, cost2, it2 = levenberg_marquardt(predict, f0, residual, corner, iterations, damping, jac, cost0)
        fits.append((s2, cost2))
        it += it2
        if cost2 >= cost:
            break
        s, cost = s2, cost2
    if corner_rounds > 0:
        fits = [corner_search(residual, x, c, corner_rounds) for x, c in fits]
    s, cost = min(fits, key=lambda f: f[1])
    return Fit(signs=s.detach(), explained=1.0 - cost / cost0, residual_rms=rms, iterations=it)


def levenberg_marquardt(
    predict: Callable[[Tensor], Tensor],
    f0: Tensor,
    residual: Callable[[Tensor], Tensor],
    s: Float[Tensor, " K"],
    iterations: int,
    damping: float,
    jac: Optional[Callable[[Tensor], Optional[Tensor]]],
    cost0: float,
) -> Tuple[Float[Tensor, " K"], float, int]:
    """Damped Gauss-Newton steps from ``s`` (clamped to the box) on ``|residual(s)|^2``; returns ``s``, its cost and
    the iterations run (stops when a step gains less than 1e-10 of ``cost0``)."""
    e = residual(s)
    cost = float((e.double() ** 2).sum())
    lam = damping
    it = 0
    for it in range(1, iterations + 1):
        j = jac(s) if jac is not None else None
        if j is None:
            j = jacobian(lambda x: predict(x).reshape(-1) - f0, s)
        j = j.double()
        a = j.T @ j
        g = j.T @ e.double()
        diag = torch.diagonal(a).clone()
        ridge = 1e-12 * float(diag.max()) if float(diag.max()) > 0 else 1e-30
        improved, gain = False, 0.0
        while lam < 1e8:
            step = torch.linalg.solve(a + torch.diag(lam * diag + ridge), g)
            s_try = (s + step.to(s.dtype)).clamp(-1.0, 1.0)
            e_try = residual(s_try)
            c_try = float((e_try.double() ** 2).sum())
            if c_try < cost:
                s, e, improved = s_try, e_try, True
                gain = cost - c_try
                cost = c_try
                lam = max(lam / 3.0, 1e-9)
                break
            lam *= 10.0
        if not improved or gain <= 1e-10 * cost0:
            break
    return s, cost, it


def corner_of(s: Float[Tensor, " K"], tol: float = 1e-6) -> Float[Tensor, " K"]:
    """The box corner nearest ``s``: ``sign(s_i)``, and 0 for bits with ``|s_i| <= tol`` (undetermined)."""
    return torch.where(s.abs() > tol, torch.sign(s), torch.zeros_like(s))


@torch.no_grad()
def corner_search(
    residual: Callable[[Tensor], Tensor], s: Float[Tensor, " K"], cost: float, rounds: int = 2, tol: float = 1e-6
) -> Tuple[Float[Tensor, " K"], float]:
    """Greedy single-bit flips over the box's corners, from the corner ``sign(s)``: a marked suspect's geometry is
    a corner's exactly, and a fit stuck beside it is pulled there. Bits with ``|s_i| <= tol`` stay 0; the least
    certain bits are tried first; a corner replaces ``s`` only if its squared residual is below ``cost``."""
    determined = s.abs() > tol
    corner = corner_of(s, tol)
    c = float((residual(corner).double() ** 2).sum())
    order = [int(i) for i in torch.argsort(s.abs()) if bool(determined[i])]
    for _ in range(rounds):
        flipped = False
        for i in order:
            corner[i] = -corner[i]
            c_try = float((residual(corner).double() ** 2).sum())
            if c_try < c:
                c, flipped = c_try, True
            else:
                corner[i] = -corner[i]
        if not flipped:
            break
    return (corner, c) if c < cost else (s, cost)


def fit_and_decide(
    predict: Callable[[Tensor], Tensor],
    jac: Callable[[Tensor], Optional[Tensor]],
    target: Float[Tensor, " M"],
    num_bits: int,
    has_rays: bool,
    generator: torch.Generator,
    iterations: int = 10,
) -> Tuple[Fit, Int[Tensor, " K"], int]:
    """:func:`fit_message` then :func:`decide_bits`, shared by every informed decoder; a view with no ray the gate
    opens on (``has_rays`` false) has nothing to read: ``s = 0``, every bit a coin flip."""
    if not has_rays:
        fit = Fit(signs=torch.zeros(num_bits), explained=0.0, residual_rms=0.0, iterations=0)
    else:
        fit = fit_message(predict, target, num_bits, iterations=iterations, jac=jac)
    bits, undetermined = decide_bits(fit.signs, generator)
    return fit, bits, undetermined


def left_after(summary: Dict[str, Any]) -> float:
    """What a fit leaves of its target (RMS), from its :func:`fit_summary`."""
    return summary["residual_rms"] * max(0.0, 1.0 - summary["explained"]) ** 0.5


def fit_summary(fit: Fit, undetermined: int, rays: int) -> Dict[str, Any]:
    """The per-view fit details the colour and image decoders report."""
    return {
        "signs_abs_mean": float(fit.signs.abs().mean()),
        "undetermined": undetermined,
        "explained": fit.explained,
        "residual_rms": fit.residual_rms,
        "iterations": fit.iterations,
        "rays": rays,
    }


UNDETERMINED = -1
"""The value of a bit the suspect does not determine: it matches no message bit (counted as a mismatch)."""


def decide_bits(
    signs: Float[Tensor, " K"], generator: Optional[torch.Generator] = None, tol: float = 1e-6
) -> Tuple[Int[Tensor, " K"], int]:
    """Bit ``i`` = ``signs_i > 0``; bits with ``|signs_i| <= tol`` (not determined by the suspect) are
    :data:`UNDETERMINED`, a mismatch whatever the message (deterministic and conservative: the matches of an unmarked
    suspect are then at most Binomial). Returns the bits and how many are undetermined. ``generator`` is unused."""
    bits = (signs > 0).long().cpu()
    tie = (signs.abs() <= tol).cpu()
    bits = torch.where(tie, torch.full_like(bits, UNDETERMINED), bits)
    return bits, int(tie.sum())


def tie_generator(seed: int) -> torch.Generator:
    """A generator seeded by the verification seed (the decoders' signature; undetermined bits are mismatches)."""
    return torch.Generator().manual_seed(104729 + 7919 * int(seed))
