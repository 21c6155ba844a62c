"""The field mark (gsticker_plugin.fieldmark): per-bit patterns in a nerfacto field's own hash table."""

from __future__ import annotations

import pytest
import torch
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.field_components.mlp import MLP
from torch import nn

from gsticker_plugin import fieldmark as FM
from gsticker_plugin.errors import GStickerError


def tiny_field():
    torch.manual_seed(0)
    enc = HashEncoding(num_levels=4, min_res=4, max_res=32, log2_hashmap_size=8, implementation="torch")
    with torch.no_grad():
        enc.hash_table.normal_(0, 0.1)
    mlp = MLP(in_dim=enc.get_out_dim(), num_layers=2, layer_width=16, out_dim=4, implementation="torch")
    return nn.Module(), enc, mlp


def test_patterns_live_on_their_levels_and_follow_the_seed_alone():
    _, enc, _ = tiny_field()
    size = enc.hash_table_size
    p = FM.patterns(enc.hash_table.shape, size, [1, 2], 48, seed=7)
    assert p.shape == (48, *enc.hash_table.shape)
    assert p[:, :size].abs().sum() == 0 and p[:, 3 * size :].abs().sum() == 0 and p[:, size : 3 * size].std() > 0.9
    assert torch.equal(p, FM.patterns(enc.hash_table.shape, size, [1, 2], 48, seed=7))
    assert not torch.equal(p, FM.patterns(enc.hash_table.shape, size, [1, 2], 48, seed=8))
    with pytest.raises(ValueError, match="outside"):
        FM.patterns(enc.hash_table.shape, size, [4], 48, seed=7)


def test_the_marked_table_is_the_base_table_plus_the_signed_patterns():
    _, enc, _ = tiny_field()
    t = enc.hash_table.data
    p = FM.patterns(t.shape, enc.hash_table_size, [0], 8, seed=1)
    assert torch.equal(FM.marked_table(t, p, torch.zeros(8), 0.3), t)
    s = FM.signs_of(torch.tensor([1, 0, 1, 1, 0, 0, 1, 0]))
    got = FM.marked_table(t, p, s, 0.3)
    assert torch.allclose(got, t + 0.3 * sum(si * pi for si, pi in zip(s, p)) / 8**0.5, atol=1e-6)


def test_sample_features_are_the_first_order_change_of_the_density_logit():
    _, enc, mlp = tiny_field()
    k = 6
    p = FM.patterns(enc.hash_table.shape, enc.hash_table_size, [0, 1, 2, 3], k, seed=3)
    x = torch.rand(200, 3)
    feats = FM.sample_features(enc, mlp, x, p)
    base = enc.hash_table.data.clone()
    assert torch.equal(enc.hash_table.data, base)  # restored
    s = torch.randn(k).clamp(-1, 1)
    eps = 1e-3
    with torch.no_grad():
        pre0 = mlp(enc(x))[..., 0]
        enc.hash_table.data = FM.marked_table(base, p, s, eps)
        pre1 = mlp(enc(x))[..., 0]
        enc.hash_table.data = base
    assert torch.allclose((pre1 - pre0) / eps, feats @ s, atol=2e-3, rtol=1e-2)


def test_a_field_without_a_torch_hash_encoder_is_refused():
    with pytest.raises(GStickerError, match="implementation torch"):
        FM.parts(nn.Linear(2, 2))
