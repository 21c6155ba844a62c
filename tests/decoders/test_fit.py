"""Tests for the informed decoders' shared fit (gsticker_plugin/decoders/fit.py), on small synthetic problems."""

from __future__ import annotations

import torch

from gsticker_plugin.decoders.fit import corner_search, decide_bits, fit_message


def _problem(seed=0, k=12, m=200):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(m, k, generator=g, dtype=torch.float64)
    b = torch.randn(m, k, generator=g, dtype=torch.float64)
    return lambda s: a @ torch.tanh(2.0 * s.double()) + 0.5 * (b @ s.double()) ** 2 / k


def test_corner_search_pulls_a_fit_with_wrong_signs_to_the_marked_corner():
    predict = _problem()
    truth = torch.tensor([1.0, -1.0] * 6, dtype=torch.float64)
    target = predict(truth) - predict(torch.zeros(12, dtype=torch.float64))
    stuck = truth * 0.4
    stuck[[1, 4, 7]] *= -1  # three bits on the wrong side
    res = lambda s: target - (predict(s) - predict(torch.zeros(12, dtype=torch.float64)))  # noqa: E731
    cost = float((res(stuck) ** 2).sum())
    s, c = corner_search(res, stuck, cost)
    assert torch.equal(s, truth) and c < 1e-20


def test_corner_search_keeps_an_interior_fit_that_explains_more_and_leaves_undetermined_bits_at_zero():
    predict = _problem(1)
    zero = torch.zeros(12, dtype=torch.float64)
    inner = torch.full((12,), 0.3, dtype=torch.float64)
    res = lambda s: predict(inner) - predict(s)  # noqa: E731
    s, c = corner_search(res, inner, 0.0)
    assert torch.equal(s, inner) and c == 0.0
    half = inner.clone()
    half[:4] = 0.0
    s, _ = corner_search(lambda x: predict(half) - predict(x) + 1.0, half, float("inf"))
    assert torch.equal(s[:4], zero[:4]) and bool((s[4:].abs() == 1).all())


def test_fit_message_recovers_every_bit_of_a_corner_and_reads_nothing_from_a_zero_target():
    predict = _problem(2, k=16)
    for seed in range(3):
        truth = torch.randint(0, 2, (16,), generator=torch.Generator().manual_seed(seed)).double() * 2 - 1
        target = predict(truth) - predict(torch.zeros(16, dtype=torch.float64))
        bits, undetermined = decide_bits(fit_message(predict, target, 16).signs)
        assert undetermined == 0 and torch.equal(bits, (truth > 0).long())
    fit = fit_message(predict, torch.zeros(200, dtype=torch.float64), 16)
    assert decide_bits(fit.signs)[1] == 16


def _saturated(seed, k=16):
    """A sticker-like problem: 40 outputs sum 300 saturated tanh samples of the bits' mixture."""
    g = torch.Generator().manual_seed(seed)
    f = torch.randn(300, k, generator=g, dtype=torch.float64)
    a = torch.rand(40, 300, generator=g, dtype=torch.float64)
    truth = torch.randint(0, 2, (k,), generator=g).double() * 2 - 1
    predict = lambda s: a @ torch.tanh(8.0 * (f @ s.double()) / k**0.5)  # noqa: E731
    return predict, truth, predict(truth) - predict(torch.zeros(k, dtype=torch.float64))


def test_restart_from_the_fits_corner_and_corner_search_find_marks_a_single_fit_misses():
    for seed, plain_matches in ((2, 14), (24, 15)):
        predict, truth, target = _saturated(seed)
        plain, _ = decide_bits(fit_message(predict, target, 16, restarts=0, corner_rounds=0).signs)
        full, _ = decide_bits(fit_message(predict, target, 16).signs)
        assert int((plain == (truth > 0).long()).sum()) == plain_matches  # one Levenberg-Marquardt run stops short
        assert torch.equal(full, (truth > 0).long())
