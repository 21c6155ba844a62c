"""The sticker stage's loss math (gsticker_plugin/pipeline.py), on small tensors: the warm-up ramp and the content
loss around the mark's operating point."""

import pytest
import torch

from gsticker_plugin.pipeline import content_loss, warmup_ramp


def test_the_ramp_is_zero_through_the_warm_up_then_reaches_one_over_as_many_steps():
    ramp = [warmup_ramp(s, 4) for s in range(12)]
    assert ramp[:3] == [0.0, 0.0, 0.0] and ramp[3] == 0.0
    assert ramp[4:8] == [0.25, 0.5, 0.75, 1.0] and ramp[8:] == [1.0] * 4
    assert warmup_ramp(0, 0) == 1.0  # no warm-up: full losses from the first step


def _mse(psnr: float) -> torch.Tensor:
    return torch.tensor(10.0 ** (-psnr / 10.0))


def test_the_one_sided_content_loss_pulls_every_mark_toward_zero_and_steeply_past_the_budget():
    losses = [float(content_loss(_mse(p), 38.0, None)) for p in (60.0, 50.0, 40.0, 38.0)]
    assert losses == sorted(losses) and losses[0] < 0.01 and losses[-1] == pytest.approx(1.0)
    past = float(content_loss(_mse(38.0) * 2, 38.0, None))
    assert past == pytest.approx(2.0 + 10.0)  # 11 times steeper past the budget


def test_the_two_sided_content_loss_is_zero_at_the_operating_point_and_grows_both_ways():
    at = float(content_loss(_mse(44.0), 38.0, 44.0))
    fainter, stronger = float(content_loss(_mse(50.0), 38.0, 44.0)), float(content_loss(_mse(40.0), 38.0, 44.0))
    assert at == pytest.approx(0.0, abs=1e-9) and fainter > 0 and stronger > 0
    mse = _mse(44.0).clone().requires_grad_(True)
    content_loss(mse * 0.5, 38.0, 44.0).backward()
    assert float(mse.grad) < 0  # a fainter mark is pushed back up toward the operating point
