"""Tests for gsticker_plugin.extractor and the fast path's sign renders (small CPU tensors)."""

from __future__ import annotations

import torch
from conftest import tiny_view_and_wrap

from gsticker_plugin.attacks import hue_shift
from gsticker_plugin.extractor import (
    BlindExtractor,
    ExtractorConfig,
    LearnedExtractor,
    LearnedExtractorConfig,
    RandomCNN,
    Whitening,
    value_channel,
)
from gsticker_plugin.fastpath import render_signs, sign_jacobian
from gsticker_plugin.sticker import BlindTerm


def images(n=6, h=32, w=32, seed=0):
    return torch.rand(n, 3, h, w, generator=torch.Generator().manual_seed(seed))


def test_value_channel_is_unchanged_by_a_hue_shift():
    img = images(2)
    for shift in (0.1, 0.25, -0.5):
        assert torch.allclose(value_channel(hue_shift(img, shift)), value_channel(img), atol=1e-5)


def test_random_cnn_is_not_a_constant_function_of_the_image():
    # with PyTorch's default init this shape of network varied by ~1e-8 across images: whitening then read zeros
    cnn = RandomCNN(ExtractorConfig(widths=(8, 16, 16, 32), num_bits=12))
    spread = cnn(images(8)).std(0)
    assert float(spread.min()) > 1e-3


def test_random_cnn_is_fixed_by_its_seed():
    a = BlindExtractor(ExtractorConfig(seed=3, widths=(8, 8, 8, 8), num_bits=4))
    b = BlindExtractor(ExtractorConfig(seed=3, widths=(8, 8, 8, 8), num_bits=4))
    c = BlindExtractor(ExtractorConfig(seed=4, widths=(8, 8, 8, 8), num_bits=4))
    assert a.sha256() == b.sha256() != c.sha256()


def test_whitening_gives_zero_mean_unit_covariance_on_its_fit_set():
    y = torch.randn(500, 5, generator=torch.Generator().manual_seed(0)) @ torch.tensor(
        [[3.0, 0, 0, 0, 0], [1, 0.01, 0, 0, 0], [0, 0, 2, 0, 0], [0, 0, 0, 1, 0], [0, 0, 0, 0, 0.5]]
    )
    y = y + torch.tensor([1.0, -2.0, 0.0, 5.0, 0.3])
    w = Whitening(5)
    stats = w.fit(y, relative_eps=1e-9)
    z = w(y)
    assert torch.allclose(z.mean(0), torch.zeros(5), atol=1e-3)
    assert torch.allclose(torch.cov(z.T), torch.eye(5), atol=2e-2)
    assert stats["eig_min"] < stats["eig_max"]


def test_whitening_epsilon_is_relative_to_the_spread():
    # a tiny spread (1e-6) must still whiten to unit scale: an absolute epsilon of 1e-3 would shrink it to ~0
    y = torch.randn(400, 3, generator=torch.Generator().manual_seed(1)) * 1e-6
    w = Whitening(3)
    w.fit(y, relative_eps=1e-3)
    assert 0.9 < float(w(y).std(0).mean()) < 1.1


def test_learned_extractor_reads_position_and_shape():
    ext = LearnedExtractor(LearnedExtractorConfig(widths=(8, 8, 8, 8), grid=2, num_bits=6))
    out = ext(images(3, 40, 24))
    assert out.shape == (3, 6)
    # the coordinate channels make the same pattern at another place read differently
    img = torch.zeros(1, 3, 32, 32)
    left, right = img.clone(), img.clone()
    left[..., 4:10, 4:10] = 1.0
    right[..., 4:10, 22:28] = 1.0
    assert not torch.allclose(ext(left), ext(right))


def test_blind_term_is_bounded_by_its_amplitude():
    term = BlindTerm(num_frequencies=3, hidden_dim=8, amplitude=0.5)
    with torch.no_grad():
        term.mlp[-1].weight.mul_(1000.0)
    with torch.no_grad():
        out = term(torch.rand(200, 3))
    assert out.shape == (200, 1) and float(out.abs().max()) <= 0.5


def test_render_signs_at_zero_is_the_clean_render_and_moves_with_the_signs():
    view, wrap, bg = tiny_view_and_wrap()
    clean = view.image
    assert torch.allclose(render_signs(view, wrap, torch.zeros(6), bg), clean)
    assert not torch.allclose(render_signs(view, wrap, torch.ones(6), bg), clean)


def test_sign_jacobian_predicts_small_sign_changes():
    view, wrap, bg = tiny_view_and_wrap()
    r = sign_jacobian(view, wrap, 6, bg)
    s = torch.tensor([1.0, -1.0, 1.0, 1.0, -1.0, -1.0]) * 1e-2
    exact = render_signs(view, wrap, s, bg, clamp=False) - view.image
    linear = torch.einsum("k,khwc->hwc", s, r)
    assert float((exact - linear).norm() / exact.norm()) < 0.05
