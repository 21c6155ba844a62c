"""The recipient's message recovery: the owner's bits from a shared run's folded sticker.

A shared run holds the sticker of the owner's message folded into one output (``gsticker_plugin.sticker.Sticker.fold``)::

    w_f = (2M - 1) W / sqrt(K)        W: the per-bit patterns [K hidden], the sticker's trained last layer

Training moves ``W`` only a little from its initial value ``W0``. A recipient who can regenerate ``W0`` (the same
initialisation from a seed they know) solves the least squares ``min_s || s W0 - sqrt(K) w_f ||`` and reads
``M = s > 0``. This module is that attack: :func:`recover_bits` for given patterns, :func:`regenerated_patterns` for
the patterns a recipient rebuilds from a shared run's config and a seed (the way ``ns-train`` seeds its
processes), :func:`best_recovery` over several seeds (the fit with the smallest residual).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Iterable, List, Optional

import torch
from torch import Tensor

from gsticker_plugin.errors import GStickerError


@dataclass
class Recovery:
    """Bits read by one least-squares fit, its relative residual and the seed its patterns came from."""

    bits: Tensor
    residual: float
    seed: Optional[int]


def folded_last_layer(pipeline_state: Dict[str, Any], prefix: str = "_model.folded_sticker.") -> Tensor:
    """The folded sticker's output weights ``w_f`` [hidden] from a shared checkpoint's pipeline state."""
    names = sorted(
        (k for k in pipeline_state if k.startswith(prefix + "mlp.") and k.endswith(".weight")),
        key=lambda k: int(k[len(prefix + "mlp.") :].split(".")[0]),
    )
    if not names:
        raise GStickerError("the checkpoint holds no folded sticker (not a shared geometrysticker run)")
    return pipeline_state[names[-1]].reshape(-1).float()


def recover_bits(folded: Tensor, patterns: Tensor) -> Recovery:
    """Least squares of ``folded`` [hidden] against ``patterns`` [K hidden]: the signs ``s`` with ``s patterns ~
    sqrt(K) folded``, read as bits ``s > 0``; the residual is relative to ``|folded|``."""
    k = patterns.shape[0]
    target = folded.reshape(1, -1).double() * k**0.5
    a = patterns.double()
    sol = torch.linalg.lstsq(a.T, target.T).solution.reshape(-1)
    resid = float((sol @ a - target).norm() / target.norm().clamp_min(1e-30))
    return Recovery(bits=(sol > 0).long(), residual=resid, seed=None)


def regenerated_patterns(config_path: Path, seed: int) -> Tensor:
    """The per-bit patterns [K hidden] of a sticker built from a shared run's ``config.yml`` the way ``ns-train`` builds
    it after seeding every generator with ``seed``, with the sticker drawn from the global generator at its place in
    the build (as it was before the sticker had a secret seed of its own): what a recipient gets if the sticker's
    initialisation follows ``machine.seed``. Deterministic in ``seed``."""
    # deferred: building a pipeline pulls in Nerfstudio
    from nerfstudio.scripts.train import _set_random_seed  # how ns-train seeds a process

    from gsticker_plugin import model as M
    from gsticker_plugin.runs import load_run_config

    config = load_run_config(config_path)
    secret_seeded = M.seeded_sticker
    M.seeded_sticker = lambda sc, seed=None: secret_seeded(sc, None)  # the global generator's next draws
    try:
        _set_random_seed(seed)
        pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    finally:
        M.seeded_sticker = secret_seeded
    return pipeline.model.sticker.mlp[-1].weight.detach().clone()


def best_recovery(folded: Tensor, candidates: Iterable[tuple]) -> Recovery:
    """The fit with the smallest residual over ``(seed, patterns)`` candidates."""
    best: Optional[Recovery] = None
    for seed, patterns in candidates:
        r = recover_bits(folded, patterns)
        r.seed = seed
        if best is None or r.residual < best.residual:
            best = r
    if best is None:
        raise ValueError("no candidate patterns")
    return best


def matches(bits: Tensor, message: Tensor) -> int:
    """Bits of ``bits`` equal to ``message``."""
    return int((bits.reshape(-1).long() == message.reshape(-1).long()).sum())


__all__: List[str] = [
    "Recovery",
    "best_recovery",
    "folded_last_layer",
    "matches",
    "recover_bits",
    "regenerated_patterns",
]


def field_mark_correlation(
    table: Tensor, table_size: int, levels: Iterable[int], seed: int, init_scale: float, num_bits: int = 48
) -> Tensor:
    """The recipient's reading of a field-marked shared run: bit ``k`` is the sign of ``<T~, P_k>`` on the trained rows,
    the per-bit patterns regenerated from ``seed`` (:func:`gsticker_plugin.fieldmark.patterns`).

    The base's table is independent of the patterns, so with the owner's pattern seed the mark's own term
    ``a s_k |P_k|^2 / sqrt(K)`` stands out of ``<T, P_k>``; with any other seed the bits are coin flips. The pattern
    seed is the secret that matters (drawn with ``secrets``, kept only in the owner key)."""
    from gsticker_plugin import fieldmark as FM

    pats = FM.on_rows(
        FM.patterns(table.shape, table_size, list(levels), num_bits, seed), FM.trained_rows(table, init_scale)
    )
    return (torch.einsum("knf,nf->k", pats, table.float()) > 0).long()
