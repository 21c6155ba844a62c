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
