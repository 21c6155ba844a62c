"""Unit tests of the sticker, the gate and the compositing on small tensors."""

import math

import pytest
import torch

from gsticker_plugin.sticker import (
    Gate,
    Sticker,
    composite,
    laplace_cdf_gate,
    positional_encoding,
    sparsity_loss,
)


def test_gate_is_laplace_cdf():
    mu, beta = torch.tensor(2.0), torch.tensor(0.5)
    sigma = torch.tensor([[0.0], [1.5], [2.0], [2.5], [10.0]])
    psi = laplace_cdf_gate(sigma, mu, beta)
    expected = [0.5 * math.exp(-2 / 0.5), 0.5 * math.exp(-1), 0.5, 1 - 0.5 * math.exp(-1), 1 - 0.5 * math.exp(-16)]
    assert torch.allclose(psi.squeeze(-1), torch.tensor(expected), atol=1e-6)
    assert torch.all(psi[1:] >= psi[:-1])  # monotone in sigma


def test_sparsity_loss_prefers_binary_gates():
    assert sparsity_loss(torch.tensor([0.0, 1.0, 1.0])) < sparsity_loss(torch.tensor([0.5, 0.5, 0.5]))
    assert torch.isfinite(sparsity_loss(torch.tensor([0.0, 1.0])))


def test_positional_encoding_shape_and_values():
    x = torch.rand(7, 3)
    enc = positional_encoding(x, 5)
    assert enc.shape == (7, 3 + 6 * 5)
    assert torch.allclose(enc[:, :3], x)
    assert torch.allclose(enc[:, 3], torch.sin(math.pi * x[:, 0]), atol=1e-6)


def test_gate_calibration_sets_mu_in_base_units():
    gate = Gate()
    dens = torch.cat([torch.full((100, 1), 0.01), torch.full((100, 1), 50.0)])
    weights = torch.cat([torch.zeros(100, 1), torch.full((100, 1), 0.1)])
    gate.calibrate(dens, weights, quantile=0.5, beta_ratio=0.1)
    assert float(gate.mu) == pytest.approx(50.0)
    assert float(gate.beta) == pytest.approx(5.0, rel=1e-4)
    assert bool(gate.calibrated)
    with pytest.raises(ValueError):
        Gate().calibrate(dens, torch.zeros_like(dens))


def test_gate_beta_is_capped():
    gate = Gate()
    gate.mu.fill_(10.0)
    with torch.no_grad():
        gate.log_beta.fill_(math.log(100.0))
    assert float(gate.beta) == pytest.approx(10.0 * gate.max_beta_ratio)


def test_sticker_depends_on_message_and_position_and_is_bounded():
    torch.manual_seed(0)
    st = Sticker(num_bits=8, num_frequencies=3, hidden_dim=16)
    torch.nn.init.normal_(st.mlp[-1].weight, std=5.0)
    pos = torch.rand(32, 3)
    m1 = st(pos, torch.zeros(8, dtype=torch.long))
    m2 = st(pos, torch.ones(8, dtype=torch.long))
    assert m1.shape == (32, 1)
    assert not torch.allclose(m1, m2)
    assert not torch.allclose(m1[:16], m1[16:])
    assert m1.abs().max() <= 1.0


def test_composite_matches_closed_form():
    density = torch.tensor([[[0.0], [1e4], [1.0]]])
    rgb = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]])
    deltas = torch.full((1, 3, 1), 0.1)
    color, weights = composite(density, rgb, deltas, torch.ones(3))
    assert torch.allclose(color, torch.tensor([[0.0, 1.0, 0.0]]), atol=1e-4)
    empty, w0 = composite(torch.zeros_like(density), rgb, deltas, torch.ones(3))
    assert torch.allclose(empty, torch.ones(1, 3)) and float(w0.sum()) == 0.0


def test_render_cached_keeps_the_clean_composite_and_renders_bit_identically():
    """The fast path composites each view's clean rays once: same image, psi and gradients as recomputing them."""
    from gsticker_plugin.fastpath import ViewCache, render_cached
    from gsticker_plugin.sticker import DensityWrap, WrapState

    torch.manual_seed(0)
    a, s = 12, 6
    density = torch.rand(a, s, 1) * 5
    view = ViewCache(image=torch.rand(4, 4, 3), active=torch.randperm(16)[:a], positions=torch.rand(a, s, 3).half(),
                     deltas=torch.full((a, s, 1), 0.1), density=density, rgb=torch.rand(a, s, 3).half())
    gate = Gate()
    gate.calibrate(density.reshape(-1, 1), torch.ones(a * s, 1))
    st = Sticker(num_bits=8, num_frequencies=2, hidden_dim=8)
    class Field(torch.nn.Module):
        def get_density(self, ray_samples):  # never called: render_cached only uses the wrap's delta()
            raise AssertionError

    wrap = DensityWrap(Field(), "f", st, gate, WrapState(), torch.tensor([[0.0] * 3, [1.0] * 3]))
    msg = torch.randint(0, 2, (8,))

    def step(v, bg):
        st.zero_grad()
        img, psi = render_cached(v, wrap, msg, bg)
        img.square().sum().backward()
        return img.detach(), psi.detach(), [p.grad.clone() for p in st.parameters()]

    white = torch.ones(3)
    first = step(view, white)
    assert view.clean_rgb is not None
    kept = view.clean_rgb[1]
    again = step(view, white)
    assert view.clean_rgb[1] is kept  # reused, not recomputed
    fresh = ViewCache(**{k: v for k, v in vars(view).items() if k != "clean_rgb"})
    recomputed = step(fresh, white)
    for x, y, z in zip(first[:2] + tuple(first[2]), again[:2] + tuple(again[2]), recomputed[:2] + tuple(recomputed[2])):
        assert torch.equal(x, y) and torch.equal(x, z)
    black = step(view, torch.zeros(3))  # another background: recomputed for it
    assert torch.equal(view.clean_rgb[0], torch.zeros(3)) and not torch.equal(black[0], first[0])
