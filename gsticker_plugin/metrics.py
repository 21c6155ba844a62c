"""Bits, detection statistics and image-quality metrics shared by training, evaluation and the CLI.

Messages are tensors ``[..., K]`` of 0/1 (integer or float). Only torch and math are imported at module
level; torchmetrics is imported inside :func:`ssim`.

Detection logic in one paragraph: a model "carries" owner message ``M`` (K bits) when the bits decoded
from a view match ``M`` in at least ``m`` places. Under the null hypothesis (a model that was never marked
with ``M``) the decoded bits are taken as fair coin flips, so the matches are ``Binomial(K, 1/2)`` and the
false-positive rate of the threshold ``m`` is :func:`binomial_tail_pvalue` ``(m, K)``;
:func:`min_matches_for_fpr` picks ``m`` for a target FPR. Several owner keys are corrected with
:func:`bonferroni` or :func:`holm`; several views are combined with :func:`combine_view_decisions`.
"""

from __future__ import annotations

import math
from typing import List, NamedTuple, Sequence, Tuple, Union

import torch
from jaxtyping import Float, Int
from torch import Tensor

PValues = Union[Sequence[float], Tensor]


# ----------------------------------------------------------------------------------------------------------------
# bits
# ----------------------------------------------------------------------------------------------------------------
def as_8_bit(images: Tensor) -> Tensor:
    """Images rounded to 8 bits, as a saved PNG holds them."""
    return torch.round(images.float().clamp(0, 1) * 255.0) / 255.0


def message_to_bits(message: Union[int, str, Sequence[int], Tensor], k: int | None = None) -> Int[Tensor, "... K"]:
    """A message as a long tensor of 0/1 bits.

    ``message`` may be an ``int`` (``k`` required; most significant bit first), a string of ``'0'``/``'1'``
    characters, a sequence of 0/1 or a tensor of 0/1 (any shape ``[..., K]``, int or float). ``k``, when
    given, must equal the number of bits.
    """
    if isinstance(message, bool):
        raise ValueError("message_to_bits: a bool is not a message; give an int with k, a '0101...' string or bits")
    if isinstance(message, int):
        if k is None or k <= 0:
            raise ValueError("message_to_bits: an int message needs the bit count k, e.g. message_to_bits(5, k=48)")
        if not 0 <= message < 2**k:
            raise ValueError(f"message_to_bits: {message} does not fit in k={k} bits (need 0 <= message < 2**k)")
        return torch.tensor([(message >> (k - 1 - i)) & 1 for i in range(k)], dtype=torch.long)
    if isinstance(message, str):
        s = message.strip()
        if not s or any(ch not in "01" for ch in s):
            raise ValueError(f"message_to_bits: {message!r} is not a string of '0'/'1' characters")
        bits = torch.tensor([int(ch) for ch in s], dtype=torch.long)
    else:
        t = torch.as_tensor(message)
        if t.ndim == 0:
            raise ValueError("message_to_bits: give a sequence or tensor of 0/1 bits, not a scalar")
        if t.numel() and not bool(((t == 0) | (t == 1)).all()):
            raise ValueError("message_to_bits: bits must all be 0 or 1 (threshold logits with decode_bits first)")
        bits = t.to(torch.long)
    if k is not None and bits.shape[-1] != k:
        raise ValueError(f"message_to_bits: got {bits.shape[-1]} bits, expected k={k}")
    return bits


def bits_to_int(bits: Int[Tensor, " K"]) -> int:
    """Inverse of :func:`message_to_bits` for an int: most significant bit first."""
    value = 0
    for b in torch.as_tensor(bits).reshape(-1).tolist():
        value = (value << 1) | int(b)
    return value


def bits_to_string(bits: Int[Tensor, " K"]) -> str:
    """Bits as a ``'0101...'`` string."""
    return "".join(str(int(b)) for b in torch.as_tensor(bits).reshape(-1).tolist())


def random_message(k: int = 48, generator: torch.Generator | None = None) -> Int[Tensor, " K"]:
    """A uniformly random K-bit message (long 0/1 tensor on CPU)."""
    return torch.randint(0, 2, (k,), generator=generator, dtype=torch.long)


def decode_bits(logits: Float[Tensor, "... K"]) -> Int[Tensor, "... K"]:
    """Hard decision: bit 1 where the extractor's logit is positive."""
    return (logits > 0).long()


def count_matches(bits: Int[Tensor, "... K"], message: Int[Tensor, "... K"]) -> Int[Tensor, "..."]:
    """Number of positions where ``bits`` equals ``message`` (0/1 values; broadcast over leading dims)."""
    bits, message = torch.as_tensor(bits), torch.as_tensor(message, device=torch.as_tensor(bits).device)
    if bits.shape[-1] != message.shape[-1]:
        raise ValueError(f"count_matches: {bits.shape[-1]} decoded bits vs a {message.shape[-1]}-bit message")
    return (bits.long() == message.long()).sum(dim=-1)


def bit_accuracy(bits: Int[Tensor, "... K"], message: Int[Tensor, "... K"]) -> Float[Tensor, "..."]:
    """Share of matching bits, in [0, 1]."""
    return count_matches(bits, message).float() / torch.as_tensor(bits).shape[-1]


# ----------------------------------------------------------------------------------------------------------------
# binomial tail
# ----------------------------------------------------------------------------------------------------------------
def _check_binom(k: int, p: float) -> None:
    if not isinstance(k, int) or isinstance(k, bool) or k < 0:
        raise ValueError(f"k must be a non-negative int (number of bits), got {k!r}")
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"p must be a probability in [0, 1], got {p!r}")


def log_binomial_tail_pvalue(m: int, k: int, p: float = 0.5) -> float:
    """``log P(X >= m)`` for ``X ~ Binomial(k, p)``; ``-inf`` when the probability is exactly 0.

    Sums the log-pmf terms (``math.lgamma``) with a log-sum-exp, so it never underflows.
    """
    _check_binom(k, p)
    m = int(m)
    if m <= 0:
        return 0.0
    if m > k:
        return -math.inf
    if p == 0.0:
        return -math.inf  # X = 0 < m
    if p == 1.0:
        return 0.0  # X = k >= m
    lp, lq = math.log(p), math.log1p(-p)
    lk = math.lgamma(k + 1)
    terms = [lk - math.lgamma(i + 1) - math.lgamma(k - i + 1) + i * lp + (k - i) * lq for i in range(m, k + 1)]
    top = max(terms)
    return top + math.log(math.fsum(math.exp(t - top) for t in terms))


def binomial_tail_pvalue(m: int, k: int, p: float = 0.5) -> float:
    """Exact ``P(X >= m)`` for ``X ~ Binomial(k, p)``: the false-positive rate of "at least m of k bits match".

    Computed in log space (see :func:`log_binomial_tail_pvalue`), so it is accurate for k up to 10,000 and
    beyond; it returns 0.0 only when the probability is below the smallest double (~5e-324).
    """
    return math.exp(log_binomial_tail_pvalue(m, k, p))


def binomial_tail_pvalues(m: Int[Tensor, "*S"], k: int, p: float = 0.5) -> Float[Tensor, "*S"]:
    """Vectorised :func:`binomial_tail_pvalue` for a tensor of match counts (float64, on ``m``'s device)."""
    _check_binom(k, p)
    m = torch.as_tensor(m)
    i = torch.arange(k + 1, dtype=torch.float64)
    if 0.0 < p < 1.0:
        logpmf = (
            torch.lgamma(torch.tensor(k + 1.0, dtype=torch.float64))
            - torch.lgamma(i + 1)
            - torch.lgamma(k - i + 1)
            + i * math.log(p)
            + (k - i) * math.log1p(-p)
        )
    else:  # degenerate: all mass on 0 (p = 0) or on k (p = 1)
        logpmf = torch.full((k + 1,), -math.inf, dtype=torch.float64)
        logpmf[k if p == 1.0 else 0] = 0.0
    # log P(X >= j) for j = 0..k, then P(X >= k+1) = 0
    log_tail = torch.logcumsumexp(logpmf.flip(0), dim=0).flip(0)
    table = torch.cat([log_tail.exp().clamp(max=1.0), torch.zeros(1, dtype=torch.float64)])
    table[0] = 1.0
    idx = m.detach().to("cpu").long().clamp(0, k + 1)
    return table[idx].to(m.device)


def min_matches_for_fpr(k: int, fpr: float) -> int:
    """Smallest ``m`` with ``P(X >= m) <= fpr`` for ``X ~ Binomial(k, 1/2)``.

    For k = 48: fpr 1e-3 -> 36, 1e-6 -> 41, 1e-9 -> 44 (exact tails: P(X>=35) = 1.04e-3, P(X>=36) = 3.6e-4;
    P(X>=40) = 1.65e-6, P(X>=41) = 3.1e-7; P(X>=43) = 6.8e-9, P(X>=44) = 7.6e-10).
    Returns ``k + 1`` ("never") when even all k bits matching is more likely than ``fpr`` (fpr < 2**-k).
    """
    _check_binom(k, 0.5)
    if not fpr >= 0:
        raise ValueError(f"fpr must be >= 0, got {fpr!r}")
    for m in range(k + 2):
        if binomial_tail_pvalue(m, k) <= fpr:
            return m
    return k + 1  # unreachable: P(X >= k+1) = 0


def soft_score(logits: Float[Tensor, "*V K"], message: Int[Tensor, " K"]) -> Tuple[float, float]:
    """The soft correlation score ``S = sum_b (2 M_b - 1) Z_b`` of the logits summed over views (``Z``), and ``|Z|^2``."""
    z = logits.double().reshape(-1, logits.shape[-1]).sum(0)
    signs = message.to(z.device).double() * 2.0 - 1.0
    return float((signs * z).sum()), float((z * z).sum())


def soft_score_pvalue(logits: Float[Tensor, "*V K"], message: Int[Tensor, " K"]) -> float:
    """Distribution-free bound on ``P(S >= s)`` over a uniformly random message independent of the logits
    (Hoeffding for a Rademacher sum): ``exp(-s^2 / (2 |Z|^2))`` for ``s > 0``, else 1. Any extractor that existed
    before the message was drawn gets this null on unmarked images."""
    s, norm2 = soft_score(logits, message)
    if s <= 0 or norm2 <= 0:
        return 1.0
    return math.exp(-s * s / (2.0 * norm2))


# ----------------------------------------------------------------------------------------------------------------
# multiple keys
# ----------------------------------------------------------------------------------------------------------------
def _as_pvalue_tensor(pvalues: PValues) -> Tensor:
    t = torch.as_tensor(pvalues, dtype=torch.float64).reshape(-1)
    if t.numel() and (bool((t < 0).any()) or bool((t > 1).any()) or bool(t.isnan().any())):
        raise ValueError("p-values must lie in [0, 1]")
    return t


def _same_kind(result: Tensor, like: PValues) -> Union[List[float], Tensor]:
    if isinstance(like, Tensor):
        return result.to(dtype=like.dtype if like.is_floating_point() else torch.float64, device=like.device)
    return result.tolist()


def bonferroni(pvalues: PValues) -> Union[List[float], Tensor]:
    """Bonferroni-adjusted p-values ``min(1, n * p)`` (list in, list out; tensor in, tensor out)."""
    t = _as_pvalue_tensor(pvalues)
    return _same_kind((t * t.numel()).clamp(max=1.0), pvalues)


def holm(pvalues: PValues) -> Union[List[float], Tensor]:
    """Holm step-down adjusted p-values, in the input order (list in, list out; tensor in, tensor out).

    With p-values sorted ascending, ``adj_(j) = max_{i <= j} min(1, (n - i) * p_(i))`` (i from 0). Rejecting
    ``adj <= alpha`` controls the family-wise error rate at alpha, like Bonferroni, but is never less powerful.
    """
    t = _as_pvalue_tensor(pvalues)
    n = t.numel()
    if n == 0:
        return _same_kind(t, pvalues)
    order = torch.argsort(t, stable=True)
    scaled = (t[order] * torch.arange(n, 0, -1, dtype=torch.float64)).clamp(max=1.0)
    adj_sorted = torch.cummax(scaled, dim=0).values
    adj = torch.empty_like(t)
    adj[order] = adj_sorted
    return _same_kind(adj, pvalues)


# ----------------------------------------------------------------------------------------------------------------
# several views
# ----------------------------------------------------------------------------------------------------------------
class ViewVote(NamedTuple):
    share: float
    """Share of views whose own test passed."""
    passed: bool
    """Whether ``share >= min_share``."""


def combine_view_decisions(per_view_pass: Sequence[bool], min_share: float = 0.5) -> ViewVote:
    """Combine per-view detection decisions into one: the share of passing views and whether it is ``>= min_share``.

    Why not pool the bits of all views into one big binomial test? Because the views of one model are not
    independent: they render the same density field, and an extractor that (wrongly) decodes bits from an
    unmarked model tends to decode the *same* wrong bits from every view. Pooling ``n`` views x ``K`` bits
    as ``n*K`` independent coin flips then makes the p-value astronomically small for what is really about
    one view's worth of evidence, so the claimed false-positive rate is badly wrong (anti-conservative).

    Instead, each view is tested on its own at a strict per-view FPR ``alpha`` (valid for that view alone,
    whatever the others do), and the model is flagged when at least a share ``s`` of the views pass. This
    is conservative under *any* dependence between views: if each view passes with probability at most
    ``alpha`` under the null, the expected number of passing views is at most ``n * alpha``, so by Markov's
    inequality ``P(share >= s) <= alpha / s`` (see :func:`combined_fpr_bound`). The bound is ``alpha / s``
    whatever the dependence, and some dependence attains it (a set of exactly ``s * n`` views passing together
    with probability ``alpha / s``, none otherwise); perfectly correlated views (all pass or none) give a rate of
    ``alpha``, independent views a rate far below the bound.
    """
    if not 0.0 < min_share <= 1.0:
        raise ValueError(f"min_share must be in (0, 1], got {min_share!r}")
    votes = [bool(v) for v in per_view_pass]
    if not votes:
        raise ValueError("combine_view_decisions: no views given; render and test at least one view")
    share = sum(votes) / len(votes)
    return ViewVote(share=share, passed=share >= min_share)


def combined_fpr_bound(per_view_fpr: float, min_share: float = 0.5) -> float:
    """Dependence-free bound ``min(1, per_view_fpr / min_share)`` on the FPR of :func:`combine_view_decisions`
    (Markov's inequality; attained by some dependence between views, so it cannot be lowered to ``per_view_fpr``)."""
    if not 0.0 < min_share <= 1.0:
        raise ValueError(f"min_share must be in (0, 1], got {min_share!r}")
    return min(1.0, per_view_fpr / min_share)


def views_needed(n_views: int, min_share: float = 0.5) -> int:
    """Smallest number of passing views out of ``n_views`` that :func:`combine_view_decisions` accepts."""
    if n_views <= 0:
        raise ValueError(f"n_views must be positive, got {n_views}")
    if not 0.0 < min_share <= 1.0:
        raise ValueError(f"min_share must be in (0, 1], got {min_share!r}")
    return next(v for v in range(n_views + 1) if v / n_views >= min_share)


def vote_pvalue(matches: Sequence[int], k: int, min_share: float = 0.5) -> float:
    """Model-level p-value of the per-view vote of :func:`combine_view_decisions`, valid under any dependence.

    The vote at per-view level ``a`` flags the model when at least :func:`views_needed` ``(n, min_share)`` views
    reach ``min_matches_for_fpr(k, a)`` matches; its false-positive rate is at most ``a / min_share``
    (:func:`combined_fpr_bound`). The smallest model-level level ``alpha`` at which the vote flags the model is
    ``P(X >= t) / min_share``, where ``t`` is the ``views_needed``-th largest match count (``X ~ Binomial(k,
    1/2)``), clamped to 1. The rejection regions are nested in ``alpha``, so ``P(p <= alpha) <= alpha`` under
    the null: this is a proper p-value, fit for :func:`bonferroni` / :func:`holm` across keys.
    """
    m = sorted((int(x) for x in torch.as_tensor(matches).reshape(-1).tolist()), reverse=True)
    if not m:
        raise ValueError("vote_pvalue: no views given; render and test at least one view")
    t = m[views_needed(len(m), min_share) - 1]
    return min(1.0, binomial_tail_pvalue(t, k) / min_share)


def vote_statistic(matches: Sequence[int], min_share: float = 0.5) -> int:
    """The match count that the vote hinges on: the :func:`views_needed`-th largest per-view match count."""
    m = sorted((int(x) for x in torch.as_tensor(matches).reshape(-1).tolist()), reverse=True)
    if not m:
        raise ValueError("vote_statistic: no views given")
    return m[views_needed(len(m), min_share) - 1]


# ----------------------------------------------------------------------------------------------------------------
# empirical null
# ----------------------------------------------------------------------------------------------------------------
def empirical_threshold(null_matches: Sequence[int], fpr: float, k: int) -> int:
    """Smallest ``m`` that at most a share ``fpr`` of the observed null match counts reached.

    ``null_matches`` are per-view match counts of *unmarked* renders/images decoded with the owner's key.
    With ``n`` null samples and ``fpr < 1/n`` this is one more than the largest null count seen (the empirical
    exceedance rate is then 0). On its own it certifies nothing below about ``3/n`` (rule of three: the 95 %
    upper confidence bound on the exceedance probability of a threshold none of ``n`` samples reached, see
    :func:`clopper_pearson_upper`); it is used to make the binomial threshold *stricter* when the extractor's
    null is not at chance, never looser. Returns ``k + 1`` ("never") when even ``k`` matches were too frequent.
    """
    t = [int(x) for x in torch.as_tensor(null_matches).reshape(-1).tolist()]
    if not t:
        raise ValueError("empirical_threshold: the null is empty; decode at least one unmarked view")
    if not fpr >= 0:
        raise ValueError(f"fpr must be >= 0, got {fpr!r}")
    n = len(t)
    for m in range(0, k + 2):
        if sum(1 for x in t if x >= m) <= fpr * n:
            return m
    return k + 1


def clopper_pearson_upper(x: int, n: int, confidence: float = 0.95) -> float:
    """One-sided Clopper-Pearson upper confidence bound on a rate observed as ``x`` events in ``n`` trials.

    The ``p`` with ``P(Binomial(n, p) <= x) = 1 - confidence`` (found by bisection on the exact tail); 1.0 when
    ``x >= n``. For ``x = 0`` it is ``1 - (1 - confidence)^(1/n)``, about ``3/n`` at 95 % ("rule of three").
    """
    if n <= 0 or not 0 <= x:
        raise ValueError(f"clopper_pearson_upper: need n > 0 and x >= 0, got x={x}, n={n}")
    if x >= n:
        return 1.0
    alpha = 1.0 - confidence
    lo, hi = 0.0, 1.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        cdf = 1.0 - binomial_tail_pvalue(x + 1, n, mid)  # P(X <= x)
        if cdf > alpha:
            lo = mid
        else:
            hi = mid
    return hi


# ----------------------------------------------------------------------------------------------------------------
# image quality
# ----------------------------------------------------------------------------------------------------------------
def psnr(a: Float[Tensor, "B C H W"], b: Float[Tensor, "B C H W"], max_val: float = 1.0) -> Float[Tensor, " B"]:
    """Per-image PSNR in dB, ``10 log10(max_val^2 / MSE)``; ``inf`` for identical images."""
    if a.shape != b.shape or a.ndim < 3:
        raise ValueError(f"psnr: need two images of one shape (..., C, H, W), got {tuple(a.shape)}, {tuple(b.shape)}")
    dt = torch.promote_types(torch.promote_types(a.dtype, b.dtype), torch.float32)
    mse = (a.to(dt) - b.to(dt)).pow(2).mean(dim=(-3, -2, -1))
    return 10.0 * torch.log10(max_val**2 / mse)


def ssim(a: Float[Tensor, "B C H W"], b: Float[Tensor, "B C H W"]) -> Float[Tensor, " B"]:
    """Per-image SSIM (torchmetrics, Gaussian 11x11 window, ``data_range=1.0``)."""
    # the torchmetrics.functional root alias warns (FutureWarning) in torchmetrics >= 1.x; import from .image
    # deferred: slow to import, only this metric needs it
    from torchmetrics.functional.image import structural_similarity_index_measure

    if a.shape != b.shape or a.ndim != 4:
        raise ValueError(f"ssim: need two images of one shape (B, C, H, W), got {tuple(a.shape)}, {tuple(b.shape)}")
    dt = torch.promote_types(torch.promote_types(a.dtype, b.dtype), torch.float32)
    return structural_similarity_index_measure(a.to(dt), b.to(dt), data_range=1.0, reduction="none")
