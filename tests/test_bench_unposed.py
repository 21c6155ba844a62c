"""The bookkeeping of the images-without-cameras bench (gsticker_plugin.bench.unposed): rows, resume, jitter."""

from pathlib import Path

import torch

from gsticker_plugin import metrics
from gsticker_plugin.bench.unposed import (
    BenchUnposedConfig,
    drawn_spec,
    not_reached,
    null_summary,
    other_keys,
    row_key,
    wanted,
)


def config(rows, random_images=0):
    return BenchUnposedConfig(load_config=Path("c.yml"), key=Path("k.gskey"), rows=rows, random_images=random_images)


def test_rows_that_differ_in_count_share_their_images():
    cfg = config(("marked:@12", "clean:@4", "marked:@24", "marked:jpeg=50@2"), random_images=3)
    assert row_key("marked:@12") == row_key("marked:@24") == "marked:"
    assert wanted(cfg) == {"marked:": 24, "clean:": 4, "marked:jpeg=50": 2, "random:": 3}
    done = {("marked:", v): {} for v in range(12)} | {("clean:", v): {} for v in range(4)}
    assert not_reached(cfg, done) == {"marked:": 12, "marked:jpeg=50": 2, "random:": 3}


def test_jittered_strengths_are_drawn_per_view_within_range_and_reproducibly():
    draws = [drawn_spec("hue=~0.5,jpeg=50", torch.Generator().manual_seed(s)) for s in range(20)]
    values = [float(d.split(",")[0].split("=")[1]) for d in draws]
    assert all(d.endswith(",jpeg=50") for d in draws)
    assert all(-0.5 <= v <= 0.5 for v in values) and min(values) < 0 < max(values)
    assert drawn_spec("hue=~0.5", torch.Generator().manual_seed(3)) == draws[3].split(",")[0]
    assert drawn_spec("noise=0.1", torch.Generator().manual_seed(0)) == "noise=0.1"


def test_other_keys_match_the_decoded_bits_like_coin_flips():
    rows = [{"bits": "01" * 24} for _ in range(10)]
    out = other_keys(rows, 64, 41)
    assert out["checks"] == 640 and 21 < out["matches_mean"] < 27 and out["passing"] == 0
    assert other_keys([], 64, 41) is None


def test_the_null_bound_is_clopper_pearson():
    """0 of n: the rule of three's exact form 1 - 0.05^(1/n); 5 of 100 lies between the observed rate and 0.12."""
    assert abs(metrics.clopper_pearson_upper(0, 800) - (1 - 0.05 ** (1 / 800))) < 1e-9
    assert 0.05 < metrics.clopper_pearson_upper(5, 100) < 0.12
    assert metrics.clopper_pearson_upper(3, 3) == 1.0


def test_the_null_pools_unmarked_images_and_other_keys():
    rows = [{"matches": 20}, {"matches": 28}, {"matches": 42}]
    others = {"checks": 7, "matches_mean": 24.0, "matches_max": 35, "passing": 0}
    n = null_summary(rows, others, 41)
    assert n["checks"] == 10 and n["images"] == 3 and n["passing"] == 1 and n["matches_max"] == 42
    assert abs(n["matches_mean"] - (20 + 28 + 42 + 7 * 24) / 10) < 1e-12
    assert n["fpr"] == 0.1 and n["fpr_upper_95"] > 0.1
    assert null_summary([], None, 41) is None
