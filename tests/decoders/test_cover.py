"""The covered-rectangle rule (gsticker_plugin/decoders/cover.py) on small tensors: the best rectangle's search, and
the rule's decision on a mark with a rectangle pasted from an unmarked render, on noise alone and on large images."""

from __future__ import annotations

import torch

from gsticker_plugin.decoders import cover as C


def test_max_sum_rectangle_finds_a_planted_rectangle_and_none_in_a_negative_map():
    g = -torch.rand(30, 40, generator=torch.Generator().manual_seed(0))
    g[5:17, 22:35] = 1.0
    score, rect = C.max_sum_rectangle(g)
    assert rect == (5, 17, 22, 35) and abs(score - 12 * 13) < 1e-9
    brute = max(
        (float(g[t:b, l:r].sum()), (t, b, l, r))
        for t in range(0, 30, 3)
        for b in range(t + 1, 31, 3)
        for l in range(0, 40, 3)
        for r in range(l + 1, 41, 3)
    )
    assert score >= brute[0]  # no rectangle on a coarse grid beats it
    assert C.max_sum_rectangle(-torch.ones(4, 5)) == (0.0, None)


def _mark(h: int, w: int, seed: int) -> torch.Tensor:
    return 0.02 * torch.randn(h * w, 3, generator=torch.Generator().manual_seed(seed))


def test_a_rectangle_missing_the_mark_is_found_and_noise_alone_finds_none():
    h, w = 60, 50
    pixels = torch.arange(h * w)
    mark = _mark(h, w, 0)
    noise = 0.004 * torch.randn(h * w, 3, generator=torch.Generator().manual_seed(1))
    y, x = pixels // w, pixels % w
    inside = (y >= 10) & (y < 40) & (x >= 5) & (x < 30)  # a quarter of the image pasted from the unmarked render
    change = torch.where(inside[:, None], torch.zeros(3), mark) + noise
    found = C.covered_pixels(change, mark, pixels, (h, w))
    assert found is not None and torch.equal(found, inside)
    assert C.covered_pixels(mark + noise, mark, pixels, (h, w)) is None  # the whole mark is there
    assert C.covered_pixels(noise, torch.zeros_like(mark), pixels, (h, w)) is None  # nothing predicted: no gain
    strong_noise = 0.1 * torch.randn(h * w, 3, generator=torch.Generator().manual_seed(2))
    assert C.covered_pixels(mark + strong_noise, mark, pixels, (h, w)) is None  # paper's noise 0.1


def test_a_small_rectangle_is_not_left_out_and_a_large_image_is_searched_in_blocks():
    h, w = 60, 50
    pixels = torch.arange(h * w)
    mark = _mark(h, w, 3)
    y, x = pixels // w, pixels % w
    tiny = (y >= 10) & (y < 13) & (x >= 5) & (x < 9)  # 12 pixels: under COVER_MIN_SHARE
    assert C.covered_pixels(torch.where(tiny[:, None], torch.zeros(3), mark), mark, pixels, (h, w)) is None
    H, W = 250, 230  # blocks of 3 x 3
    pixels = torch.arange(H * W)
    mark = _mark(H, W, 4)
    y, x = pixels // W, pixels % W
    inside = (y >= 30) & (y < 150) & (x >= 60) & (x < 180)
    found = C.covered_pixels(torch.where(inside[:, None], torch.zeros(3), mark), mark, pixels, (H, W))
    assert found is not None and torch.equal(found, inside)  # block edges fall on the rectangle's (multiples of 3)
