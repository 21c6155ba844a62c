"""The registered draws of pictures found in the wild (gsticker_plugin.evaluation.wild): framings from the seed alone,
inside the protocol's ranges, every row at its fixed magnitude."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from gsticker_plugin.evaluation import wild as W


def test_framings_come_from_the_seed_alone_and_stay_inside_the_protocols_ranges():
    views = [v for v in range(200) if v not in (1, 2, 3)]
    a = W.draw_framings(views, (100, 100), seed=11, count=24)
    assert a == W.draw_framings(views, (100, 100), seed=11, count=24)
    assert a != W.draw_framings(views, (100, 100), seed=12, count=24)
    assert len({f.view for f in a}) == 24 and not {f.view for f in a} & {1, 2, 3}
    for f in a:
        assert W.ZOOM[0] <= f.zoom <= W.ZOOM[1] and f.aspect in W.ASPECTS and f.side in W.SIDES
        assert max(f.width, f.height) == round(f.side * 100)
        assert math.isclose(f.width / f.height, f.aspect[0] / f.aspect[1], rel_tol=0.03)
        assert math.isclose(max(f.render_width, f.render_height), f.zoom * max(f.width, f.height), abs_tol=1.0)
        assert f.cover >= W.MIN_COVER


def test_many_draws_reach_every_aspect_and_size_and_zooms_on_both_sides_of_one():
    fr = W.draw_framings(list(range(200)), (100, 100), seed=5, count=200)
    assert {f.aspect for f in fr} == set(W.ASPECTS) and {f.side for f in fr} == set(W.SIDES)
    zooms = np.array([f.zoom for f in fr])
    assert zooms.min() < 0.8 and zooms.max() > 1.35
    assert any(f.left > 0 or f.top > 0 for f in fr)  # some pictures show bars (zoomed out)
    assert any(f.left < 0 or f.top < 0 for f in fr)  # some are crops


def test_a_framed_picture_puts_the_resized_render_where_its_framing_says():
    render = Image.new("RGB", (100, 100), (200, 30, 30))
    f = W.Framing(
        view=0,
        zoom=0.8,
        aspect=(16, 9),
        side=1.0,
        width=100,
        height=56,
        render_width=80,
        render_height=80,
        left=10,
        top=-12,
    )
    pic = np.asarray(W.frame(render, f))
    assert pic.shape == (56, 100, 3)
    assert (pic[:, :10] == 0).all() and (pic[:, 90:] == 0).all()  # bars left and right
    assert (np.abs(pic[:, 12:88].astype(int) - [200, 30, 30]) <= 1).all()
    k = W.framed_intrinsics(90.0, 90.0, 50.0, 50.0, (100, 100), f)
    assert k == {"fx": 72.0, "fy": 72.0, "cx": 50.0, "cy": 28.0, "width": 100, "height": 56}


@pytest.mark.parametrize("row", sorted(W.ROWS))
def test_every_row_is_applied_at_its_fixed_magnitude(row):
    rng = np.random.default_rng(0)
    im = Image.fromarray((rng.random((40, 60, 3)) * 255).astype(np.uint8))
    out = W.ROWS[row](im, 0)
    a = np.asarray(im, dtype=np.float32) / 255
    b = np.asarray(out, dtype=np.float32) / 255
    if row == "framed":
        assert (a == b).all()
    elif row == "resize 0.5":
        assert out.size == (30, 20)
    elif row == "crop + JPEG + hue":
        assert out.size == (48, 32)
    elif row == "cropout 25 %":
        white = (b == 1.0).all(-1) & ~(a == 1.0).all(-1)
        assert abs(white.mean() - 0.25) < 0.03
    elif row == "noise 0.1":
        assert abs(float((b - a).std()) - 0.1) < 0.02
    else:
        assert out.size == im.size and np.abs(b - a).mean() > 0.01
    assert W.ROWS[row](im, 0).tobytes() == out.tobytes()  # the same picture every time


def test_rotation_and_hue_turn_by_exactly_their_magnitude_half_the_views_each_way():
    im = Image.new("RGB", (41, 41), (0, 0, 0))
    im.putpixel((30, 20), (255, 255, 255))  # a dot right of the centre
    up, down = np.asarray(W.ROWS["rotation +-30"](im, 0)), np.asarray(W.ROWS["rotation +-30"](im, 1))
    for out, sign in ((up, 1), (down, -1)):
        inner = out[8:33, 8:33].astype(float).sum(-1)
        y, x = np.unravel_index(np.argmax(inner), inner.shape)
        angle = math.degrees(math.atan2(-(y + 8 - 20), x + 8 - 20))
        assert abs(angle - sign * 30) < 6, angle
    red = Image.new("RGB", (8, 8), (255, 0, 0))
    turned = np.asarray(W.ROWS["hue +-0.5"](red, 0))[0, 0]
    assert turned[0] < 10 and turned[1] > 245 and turned[2] > 245  # red turned half way round: cyan


def test_the_stage_sums_marked_rows_and_counts_each_null_picture_once():
    from gsticker_plugin.evaluation.report import _wild
    from gsticker_plugin.evaluation.stages.wild import summary

    lines = [
        {"suspect": "shared", "row": "framed", "i": i, "kind": "marked", "matches": m, "seconds": s}
        for i, (m, s) in enumerate([(48, 10.0), (40, 20.0), (47, 30.0), (48, 40.0)])
    ]
    lines += [
        {"suspect": "base", "row": "framed", "i": i, "kind": "null", "matches": m, "seconds": 5.0}
        for i, m in enumerate([20, 24, 28, 41])
    ]
    res = summary(lines, 41, [])
    (marked,) = [r for r in res["rows"] if r["suspect"] == "shared"]
    assert marked["pictures"] == 4 and marked["passing"] == 0.75 and marked["min_matches"] == 40
    assert marked["bit_acc"] == (48 + 40 + 47 + 48) / 4 / 48 and marked["seconds_median"] == 25.0
    null = res["null"]
    assert null["pictures"] == 4 and null["false_positives"] == 1 and null["at_least_36"] == 1 and null["max"] == 41
    assert 0.25 < null["fpr_upper_95"] < 1.0
    page = "\n".join(_wild({"wild": res}))
    assert "| shared | framed | 4 |" in page and "4 distinct unmarked pictures" in page


def test_random_null_pictures_are_drawn_from_the_registered_seed_and_differ():
    from gsticker_plugin.evaluation.stages.wild import random_picture

    pics = [np.asarray(random_picture(i, (64, 36))) for i in range(8)]
    assert all(p.shape == (36, 64, 3) for p in pics)
    assert (pics[0] == np.asarray(random_picture(0, (64, 36)))).all()
    assert len({p.tobytes() for p in pics}) == 8
    assert (pics[2] == pics[2][0, 0]).all()  # a flat colour


def test_the_wild_protocol_is_registered_and_off_unless_asked():
    from gsticker_plugin.evaluation.config import load_protocol

    root = __import__("pathlib").Path(__file__).resolve().parents[2]
    assert load_protocol(root / "method_configs/eval/smoke.yaml").wild is None
    if (root.parent / "shared").is_dir():
        p = load_protocol(root / "method_configs/eval/lego100-wild.yaml")
        assert p.wild.seed == W.REGISTERED_SEED and p.wild.views == 24 and p.wild.development_views == [1, 2, 3]
        assert set(p.wild.rows) <= set(W.ROWS) and len(p.recolor.colors) == 10 and p.recolor.model_hue == [0.25, 0.5]
