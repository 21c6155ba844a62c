"""Tests for gsticker_plugin.metrics: bits, binomial tails, multiple testing, view voting, PSNR/SSIM."""

from __future__ import annotations

import math

import pytest
import torch

from gsticker_plugin import metrics as M


def exact_tail(m: int, k: int) -> float:
    """P(X >= m), X ~ Binomial(k, 1/2), by exact integer arithmetic (int / int is correctly rounded)."""
    m = max(m, 0)
    if m > k:
        return 0.0
    total, c = 0, math.comb(k, m)
    for i in range(m, k + 1):  # C(k, i+1) = C(k, i) * (k - i) / (i + 1), exactly
        total += c
        c = c * (k - i) // (i + 1)
    return total / 2**k


# ---------------------------------------------------------------------------------------------------- bits
def test_message_to_bits_int_string_and_roundtrip():
    assert M.message_to_bits(5, k=4).tolist() == [0, 1, 0, 1]
    assert M.message_to_bits("0110").tolist() == [0, 1, 1, 0]
    assert M.message_to_bits([1.0, 0.0, 1.0]).dtype == torch.long
    v = 0xA5F00F123456
    bits = M.message_to_bits(v, k=48)
    assert bits.shape == (48,)
    assert M.bits_to_int(bits) == v
    assert M.bits_to_string(M.message_to_bits("1001")) == "1001"


@pytest.mark.parametrize(
    "args",
    [(5,), (16, 4), ("01a1",), ([0, 2, 1],), (torch.tensor([0.5, 1.0]),), ("0101", 3)],
)
def test_message_to_bits_rejects(args):
    with pytest.raises(ValueError):
        M.message_to_bits(*args)


def test_random_message_seeded():
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    a, b = M.random_message(48, g1), M.random_message(48, g2)
    assert torch.equal(a, b) and a.shape == (48,) and set(a.tolist()) <= {0, 1}
    assert 0 < int(a.sum()) < 48


def test_decode_bits_threshold_at_zero():
    logits = torch.tensor([[-2.0, 0.0, 0.1, 3.0], [1e-6, -1e-6, 5.0, -5.0]])
    assert M.decode_bits(logits).tolist() == [[0, 0, 1, 1], [1, 0, 1, 0]]
    assert M.decode_bits(logits).dtype == torch.long


def test_count_matches_and_accuracy_broadcast():
    msg = torch.tensor([1, 0, 1, 1])
    bits = torch.tensor([[1, 0, 1, 1], [0, 1, 0, 0], [1, 1, 1, 0]])
    assert M.count_matches(bits, msg).tolist() == [4, 0, 2]
    acc = M.bit_accuracy(bits, msg)
    assert acc.dtype.is_floating_point
    assert acc.tolist() == [1.0, 0.0, 0.5]
    # float message, extra leading dim
    assert M.count_matches(bits[None], msg.float()).shape == (1, 3)
    with pytest.raises(ValueError):
        M.count_matches(bits, torch.tensor([1, 0, 1]))


# ---------------------------------------------------------------------------------------------------- binomial
def test_pvalues_equal_exact_sum_k48_every_m():
    k = 48
    for m in range(-1, k + 2):
        ref = exact_tail(m, k) if m <= k else 0.0
        got = M.binomial_tail_pvalue(m, k)
        assert got == pytest.approx(ref, rel=1e-12, abs=0.0), m
    vec = M.binomial_tail_pvalues(torch.arange(-1, k + 2), k)
    assert vec.dtype == torch.float64
    ref = torch.tensor([exact_tail(m, k) if m <= k else 0.0 for m in range(-1, k + 2)], dtype=torch.float64)
    assert torch.allclose(vec, ref, rtol=1e-10, atol=0.0)


def test_pvalue_large_k_no_underflow_garbage():
    k = 10_000
    for m in (5_000, 5_200, 6_000, 6_500):
        ref = exact_tail(m, k)
        assert ref > 0
        assert M.binomial_tail_pvalue(m, k) == pytest.approx(ref, rel=1e-8)
    # 2**-10000 is below the smallest double: a true underflow, but the log is still right
    assert M.binomial_tail_pvalue(k, k) == 0.0
    assert M.log_binomial_tail_pvalue(k, k) == pytest.approx(-k * math.log(2), rel=1e-12)
    vec = M.binomial_tail_pvalues(torch.tensor([5_200, 6_000]), k)
    assert vec[0].item() == pytest.approx(exact_tail(5_200, k), rel=1e-8)
    assert vec[1].item() == pytest.approx(exact_tail(6_000, k), rel=1e-8)


def test_pvalue_general_p():
    k, p = 20, 0.3
    ref = sum(math.comb(k, i) * p**i * (1 - p) ** (k - i) for i in range(12, k + 1))
    assert M.binomial_tail_pvalue(12, k, p) == pytest.approx(ref, rel=1e-10)
    assert M.binomial_tail_pvalues(torch.tensor([12]), k, p).item() == pytest.approx(ref, rel=1e-10)
    with pytest.raises(ValueError):
        M.binomial_tail_pvalue(3, 10, 1.5)


def test_min_matches_for_fpr_k48():
    assert M.min_matches_for_fpr(48, 1e-3) == 36
    assert M.min_matches_for_fpr(48, 1e-6) == 41
    assert M.min_matches_for_fpr(48, 1e-9) == 44
    for fpr in (1e-3, 1e-6, 1e-9):
        m = M.min_matches_for_fpr(48, fpr)
        assert exact_tail(m, 48) <= fpr < exact_tail(m - 1, 48)
    assert M.min_matches_for_fpr(48, 1.0) == 0
    assert M.min_matches_for_fpr(48, 1e-20) == 49  # even 48/48 is more likely than 1e-20


# ---------------------------------------------------------------------------------------------------- multiple keys
def test_bonferroni_and_holm_hand_example():
    p = [0.01, 0.04, 0.03, 0.005]
    # Bonferroni: x4, capped at 1
    assert M.bonferroni(p) == pytest.approx([0.04, 0.16, 0.12, 0.02])
    assert M.bonferroni([0.3, 0.5]) == pytest.approx([0.6, 1.0])
    # Holm: sorted 0.005, 0.01, 0.03, 0.04 -> x4, x3, x2, x1 = 0.02, 0.03, 0.06, 0.04 -> cummax 0.02, 0.03, 0.06, 0.06
    assert M.holm(p) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    t = M.holm(torch.tensor(p))
    assert isinstance(t, torch.Tensor)
    assert torch.allclose(t.double(), torch.tensor([0.03, 0.06, 0.06, 0.02], dtype=torch.float64))
    assert M.holm([0.9, 0.5]) == pytest.approx([1.0, 1.0])
    with pytest.raises(ValueError):
        M.holm([0.2, 1.2])


# ---------------------------------------------------------------------------------------------------- views
def test_combine_view_decisions():
    share, passed = M.combine_view_decisions([True, False, True, True])
    assert share == 0.75 and passed is True
    vote = M.combine_view_decisions([True, False, False], min_share=0.5)
    assert vote.share == pytest.approx(1 / 3) and vote.passed is False
    assert M.combine_view_decisions([True, False], min_share=0.5).passed is True
    assert M.combine_view_decisions([True, True, False], min_share=1.0).passed is False
    with pytest.raises(ValueError):
        M.combine_view_decisions([])
    with pytest.raises(ValueError):
        M.combine_view_decisions([True], min_share=0.0)
    assert M.combined_fpr_bound(1e-6, 0.5) == pytest.approx(2e-6)
    assert M.views_needed(10, 0.7) == 7  # 0.7 * 10 is 7.000000000000001 in floating point
    assert M.views_needed(3, 0.5) == 2
    assert M.views_needed(4, 0.5) == 2


# ---------------------------------------------------------------------------------------------------- image quality
def test_psnr_identical_and_known_noise():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(2, 3, 16, 16, generator=g) * 0.5 + 0.25
    assert torch.isinf(M.psnr(a, a)).all()
    sign = torch.randint(0, 2, a.shape, generator=g).float() * 2 - 1
    b = a + 0.1 * sign  # MSE exactly 0.01 -> 20 dB
    out = M.psnr(a, b)
    assert out.shape == (2,)
    assert torch.allclose(out, torch.full((2,), 20.0), atol=1e-3)
    b2 = a.clone()
    b2[1] += 0.01 * sign[1]  # only image 1 differs: 40 dB
    out2 = M.psnr(a, b2)
    assert torch.isinf(out2[0]) and out2[1].item() == pytest.approx(40.0, abs=1e-3)
    assert M.psnr(a * 255, b * 255, max_val=255.0)[0].item() == pytest.approx(20.0, abs=1e-3)


def test_ssim_per_image():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(2, 3, 32, 32, generator=g)
    b = a.clone()
    b[1] = torch.rand(3, 32, 32, generator=g)
    s = M.ssim(a, b)
    assert s.shape == (2,)
    assert s[0].item() == pytest.approx(1.0, abs=1e-5)
    assert s[1].item() < 0.5


def test_soft_score_bound_holds_over_random_messages_for_fixed_logits():
    # the null: logits fixed (an unmarked image), message uniformly random -> P(p <= a) <= a for every a
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(3, 48, generator=g) * torch.linspace(0.1, 3.0, 48)
    pvals = torch.tensor([M.soft_score_pvalue(logits, torch.randint(0, 2, (48,), generator=g)) for _ in range(4000)])
    for a in (0.01, 0.05, 0.2, 0.5):
        assert float((pvals <= a).float().mean()) <= a + 0.01


def test_soft_score_is_small_when_logits_follow_the_message():
    g = torch.Generator().manual_seed(1)
    msg = torch.randint(0, 2, (48,), generator=g)
    weak = (msg.float() * 2 - 1) * 0.3 + torch.randn(24, 48, generator=g)  # ~62 % bit accuracy per view
    assert M.soft_score_pvalue(weak, msg) < 1e-6
    assert M.soft_score_pvalue(-weak, msg) == 1.0
    s, norm2 = M.soft_score(weak, msg)
    assert s > 0 and norm2 > 0
