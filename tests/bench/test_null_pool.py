"""The images-alone null pooled over pages: each unmarked image once, one page's other keys."""

import json

import pytest

from gsticker_plugin.bench.null_pool import NullPoolConfig, main, pool_null


def row(name, view, matches, bits="01" * 24):
    return {"row": name, "view": view, "matches": matches, "bits": bits}


def page(per_image, other_keys=None, threshold=41):
    return {
        "threshold": threshold,
        "per_image": per_image,
        "other_keys": other_keys,
        "command": "python -m gsticker_plugin.bench.unposed --load-config RUN/config.yml --key K",
        "psnr_marked_vs_clean_db": {"mean": 36.5, "min": 35.0},
        "date": "2026-12-06 03:00 UTC",
    }


OTHERS = {
    "checks": 2,
    "matches_mean": 23.0,
    "matches_max": 25,
    "passing": 0,
    "histogram": [0] * 21 + [1] + [0] * 3 + [1] + [0] * 23,
}


def test_an_image_decoded_on_two_pages_counts_once_and_its_second_reading_is_listed():
    a = page([row("random:@64", 0, 20), row("random:@64", 1, 30), row("marked:@4", 0, 48)], OTHERS)
    b = page([row("random:@64", 1, 28), row("random:@64", 2, 26), row("marked:@2", 0, 48)], OTHERS)
    res = pool_null([a, b], ["a.md", "b.md"])
    assert res["images_per_page"] == {"a.md": 2, "b.md": 1}
    assert res["null"]["images"] == 3 and "checks" not in res["null"]  # the keys are not null images
    assert res["null"]["matches_max"] == 30  # the first page's reading of image 1, not the second's 28
    assert res["read_again"] == [
        {"row": "random:", "view": 1, "readings": [{"page": "a.md", "matches": 30}, {"page": "b.md", "matches": 28}]}
    ]
    assert res["rows"]["random:"] == {"images": 3, "mean": 76 / 3, "max": 30}
    assert res["other_keys_from"] == "a.md"


def test_a_page_without_other_keys_leaves_them_to_the_next_page_and_images_with_nothing_to_read_stay_apart():
    a = page([row("clean:@2", 0, 0, "?" * 48), row("clean:@2", 1, 22)])
    b = page([row("scene=x:@2", 0, 25)], OTHERS)
    res = pool_null([a, b], ["a.md", "b.md"])
    assert res["null"]["nothing_read"] == 1 and res["null"]["images"] == 2
    assert res["other_keys_from"] == "b.md"
    assert "clean:" in res["rows"] and res["rows"]["clean:"]["images"] == 1


def test_pages_passing_at_different_thresholds_are_not_pooled():
    with pytest.raises(ValueError, match="different thresholds"):
        pool_null([page([row("random:@1", 0, 20)]), page([row("random:@1", 1, 20)], threshold=30)], ["a", "b"])


def test_the_pooled_page_counts_each_unmarked_image_once_keeps_other_keys_apart_and_draws_its_chart(tmp_path):
    for name, rows in (("a", [row("random:@64", i, 20 + i) for i in range(3)]), ("b", [row("random:@64", 3, 41)])):
        (tmp_path / f"{name}.json").write_text(json.dumps(page(rows, OTHERS)))
    out = tmp_path / "pool.md"
    res = main(NullPoolConfig(pages=(tmp_path / "a.json", tmp_path / "b.json"), output=out))
    assert res["null"]["passing"] == 1 and res["null"]["images"] == 4
    text = out.read_text()
    assert "| other keys (a.md's marked images, one check a key; not in the null) | 2 | 23.0 | 25 |" in text
    assert "**The null: 4 distinct unmarked images, each counted once: mean 26.0, max 41, 1 at or above 41/48**" in text
    assert (tmp_path / "pool.png").stat().st_size > 1000
    assert json.loads((tmp_path / "pool.json").read_text())["images_per_page"] == {"a.md": 3, "b.md": 1}
