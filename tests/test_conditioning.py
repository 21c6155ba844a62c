"""The sticker's conditioning term: the Gram of the render's per-bit change and the estimate's noise variance."""

import torch
from conftest import tiny_view_and_wrap

from gsticker_plugin.fastpath import condition_term, noise_variance, render_signs, sign_gram


def _per_bit_changes(view, wrap, message, bg, eps: float = 1e-2):
    """The render's change per bit at the corner ``message`` by float32 central differences: ``[K H W 3]`` (a step of
    1e-2: its second-order error is far below the float32 rounding of a smaller step, which failed 6 sticker inits in 30)."""
    signs = message.float() * 2 - 1
    changes = []
    for b in range(signs.numel()):
        e = torch.zeros_like(signs)
        e[b] = eps
        plus = render_signs(view, wrap, signs + e, bg, clamp=False)
        minus = render_signs(view, wrap, signs - e, bg, clamp=False)
        changes.append(((plus - minus) / (2 * eps)).reshape(*view.hw, 3))
    return torch.stack(changes)


def test_the_sign_gram_is_the_gram_of_the_renders_per_bit_change_at_the_corner():
    view, wrap, bg = tiny_view_and_wrap()
    message = torch.tensor([1, 0, 1, 1, 0, 0])
    j = _per_bit_changes(view, wrap, message, bg).reshape(6, -1).T.double()  # [(ray, channel) K]
    gram = sign_gram(view, wrap, message, bg).double()
    want = (j.T @ j).detach()
    assert torch.allclose(gram.detach(), want, rtol=5e-2, atol=1e-3 * float(torch.diagonal(want).mean()))


def test_the_blurred_sign_gram_is_the_gram_of_the_blurred_per_bit_change_images():
    from gsticker_plugin.fastpath import smoothed

    view, wrap, bg = tiny_view_and_wrap()
    view.image = torch.full((5, 5, 3), 0.5)  # the 16 rays are a scattered subset of a 5x5 image
    view.active = torch.tensor([0, 2, 3, 4, 6, 7, 9, 11, 12, 13, 15, 17, 19, 20, 22, 24])
    message = torch.tensor([0, 1, 1, 0, 1, 0])
    changes = _per_bit_changes(view, wrap, message, bg).double()
    j = torch.stack([smoothed(c, 1.0).reshape(-1) for c in changes], dim=1)
    want = j.T @ j
    sharp = sign_gram(view, wrap, message, bg).double().detach()
    gram = sign_gram(view, wrap, message, bg, blur=1.0).double().detach()
    # float32 central differences: entries far below the diagonal carry their rounding, hence the absolute slack
    assert torch.allclose(gram, want, rtol=5e-2, atol=3e-2 * float(torch.diagonal(want).mean()))
    assert float(torch.trace(gram)) < float(torch.trace(sharp))  # the low-pass removes some of the change's energy


def test_the_conditioning_term_trains_through_the_sticker_and_prefers_separable_bits():
    view, wrap, bg = tiny_view_and_wrap()
    message = torch.tensor([1, 0, 1, 1, 0, 0])
    loss = noise_variance(sign_gram(view, wrap, message, bg), 0.1)
    loss.backward()
    grads = [p.grad for p in wrap.sticker.parameters() if p.grad is not None]
    assert grads and max(float(g.abs().max()) for g in grads) > 0
    # equal energy: orthogonal columns give a smaller variance than nearly collinear ones
    assert noise_variance(torch.eye(2), 0.1) < noise_variance(torch.tensor([[1.0, 0.99], [0.99, 1.0]]), 0.1)


def test_the_scale_free_term_only_sees_the_spectrums_shape_and_blurred_grams_average_in():
    even, uneven = torch.eye(3), torch.diag(torch.tensor([1.0, 1.0, 0.01]))
    for gram in (even, uneven):  # the plain term drops by log 4 when the change doubles; the scale-free one does not
        plain = float(condition_term([gram], 0.1, False)) - float(condition_term([4 * gram], 0.1, False))
        free = float(condition_term([gram], 0.1, True)) - float(condition_term([4 * gram], 0.1, True))
        assert abs(plain - torch.log(torch.tensor(4.0)).item()) < 1e-4 and abs(free) < 1e-4
    assert float(condition_term([even], 0.1, True)) < float(condition_term([uneven], 0.1, True))
    both = float(condition_term([even, uneven], 0.1, True))
    assert abs(both - 0.5 * float(condition_term([even], 0.1, True) + condition_term([uneven], 0.1, True))) < 1e-6


def test_the_gram_stats_give_each_bits_noise_deviation_and_flag_collinear_bits():
    from gsticker_plugin.bench.conditioning import gram_stats

    orthogonal = torch.zeros(6, 3)
    orthogonal[0, 0], orthogonal[1, 1], orthogonal[2, 2] = 2.0, 1.0, 0.5
    st = gram_stats(orthogonal, 0.1)
    assert abs(st["trace"] - 5.25) < 1e-9 and abs(st["eig_min"] - 0.25) < 1e-9
    assert abs(st["bit_std_median"] - 0.1) < 1e-9  # 0.1 / |column|: 0.05, 0.1, 0.2
    assert st["bits_std_below_0.4"] == 3
    collinear = torch.tensor([[1.0, 1.0, 0.0], [0.0, 1e-3, 0.0], [0.0, 0.0, 1.0]])
    assert gram_stats(collinear, 0.1)["bit_std_median"] > 50 * gram_stats(orthogonal, 0.1)["bit_std_median"]


def test_render_signs_at_zero_is_the_clean_render_and_moves_with_the_signs():
    view, wrap, bg = tiny_view_and_wrap()
    clean = view.image
    assert torch.allclose(render_signs(view, wrap, torch.zeros(6), bg), clean)
    assert not torch.allclose(render_signs(view, wrap, torch.ones(6), bg), clean)
