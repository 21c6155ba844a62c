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
