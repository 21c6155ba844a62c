"""gsticker_plugin.hashgrid: Nerfstudio's torch hash encoding evaluated bit for bit, faster, on loaded models."""

from __future__ import annotations

import copy

import pytest
import torch
from nerfstudio.field_components.encodings import HashEncoding

from gsticker_plugin import hashgrid


def encoder(log2: int = 10, levels: int = 6) -> HashEncoding:
    torch.manual_seed(0)
    enc = HashEncoding(num_levels=levels, min_res=4, max_res=256, log2_hashmap_size=log2, implementation="torch")
    with torch.no_grad():
        enc.hash_table.normal_(0, 1.0)
    return enc


@pytest.mark.parametrize("log2,low", [(10, 0.0), (12, -0.5), (6, -2.0)])
def test_encode_is_the_stock_torch_encoding_bit_for_bit(log2, low):
    """Inside the unit cube, outside it (negative cells: the hash's ``and (T - 1)`` equals ``mod T`` there) and on a
    table smaller than the grid (collisions)."""
    enc = encoder(log2)
    x = torch.rand(4000, 3) * (1 - low) + low
    x[:10] = torch.tensor([0.0, 0.5, 1.0])  # on grid planes: ceiling == floor
    with torch.no_grad():
        assert torch.equal(hashgrid.encode(enc, x), HashEncoding.pytorch_fwd(enc, x))
        assert torch.equal(
            hashgrid.encode(enc, x.reshape(40, 100, 3)), HashEncoding.pytorch_fwd(enc, x).reshape(40, 100, -1)
        )


def test_corner_rows_are_the_stock_hash_of_each_corner():
    enc = encoder()
    scaled = (torch.rand(50, 1, 3) * 2 - 0.5) * enc.scalings.view(-1, 1)
    ceil, floor = torch.ceil(scaled).int(), torch.floor(scaled).int()
    rows = hashgrid.corner_rows(enc, ceil, floor)
    for (ux, uy, uz), got in zip(hashgrid.CORNERS, rows):
        cell = torch.stack([(ceil if u else floor)[..., d] for d, u in enumerate((ux, uy, uz))], -1)
        assert torch.equal(got, enc.hash_fn(cell))


def test_a_sped_up_encoding_renders_the_same_and_trains_through_the_stock_code():
    """Without a gradient to the table the instance runs :func:`encode`; with one, the stock forward (same values and
    the stock gradient); the class itself is untouched."""
    enc = encoder()
    module = torch.nn.Sequential(enc)
    x = torch.rand(500, 3)
    with torch.no_grad():
        want = enc(x)
    assert hashgrid.speed_up(module) == 1 and "pytorch_fwd" in vars(enc)
    assert "pytorch_fwd" not in vars(encoder())  # other instances keep the class's forward
    calls = []
    real = hashgrid.encode
    try:
        hashgrid.encode = lambda e, t: calls.append(1) or real(e, t)
        with torch.no_grad():
            assert torch.equal(enc(x), want) and calls == [1]
        out = enc(x)
        assert calls == [1] and torch.equal(out.detach(), want)
    finally:
        hashgrid.encode = real
    out.square().sum().backward()
    stock = encoder()
    HashEncoding.pytorch_fwd(stock, x).square().sum().backward()
    assert torch.equal(enc.hash_table.grad, stock.hash_table.grad)


def test_a_copy_of_a_sped_up_model_reads_its_own_table():
    enc = encoder()
    hashgrid.speed_up(enc)
    twin = copy.deepcopy(enc)
    with torch.no_grad():
        twin.hash_table.add_(1.0)
        x = torch.rand(100, 3)
        assert torch.equal(twin(x), HashEncoding.pytorch_fwd(twin, x))
        assert not torch.equal(twin(x), enc(x))
