"""bench.targets: the summary of per-view rows against the sticker issue's targets, its table and chart."""

from __future__ import annotations

from gsticker_plugin.bench.targets import page
from gsticker_plugin.evaluation.targets import chart, report, summarize


def _rows(matches, psnr_clean=40.0, marked_gt=26.0, clean_gt=26.1):
    return [
        {
            "index": i,
            "matches": m,
            "bit_acc": m / 48,
            "pvalue": 0.5,
            "psnr_vs_clean_db": psnr_clean,
            "psnr_marked_vs_gt_db": marked_gt,
            "psnr_clean_vs_gt_db": clean_gt,
            "decode_s": 5.0,
        }
        for i, m in enumerate(matches)
    ]


def test_all_views_all_bits_meets_every_target():
    v = summarize(_rows([48, 48, 48]), 48, {"wall_s": 300.0}, split_size=3)
    assert v["bit_acc"] == 1.0 and v["views_all_bits"] == 3 and v["views_passing"] == 3 and v["threshold"] == 41
    assert all(v["targets"].values()), v["targets"]
    assert abs(v["psnr_drop_db"] - 0.1) < 1e-9 and v["train_minutes"] == 5.0


def test_misses_are_reported_as_not_met_and_partial_runs_as_not_measured():
    v = summarize(_rows([48, 40, 30], psnr_clean=30.0, marked_gt=25.0, clean_gt=26.0), 48, {"wall_s": 1200.0}, 3)
    assert abs(v["bit_acc"] - 118 / 144) < 1e-9 and v["matches_min"] == 30 and v["views_passing"] == 1
    t = v["targets"]
    assert t["bit_acc >= 99.5 %"] is False and t["PSNR vs unwatermarked >= 35 dB"] is False
    assert t["test PSNR within 0.3 dB of the base"] is False and t["training <= 15 min"] is False
    partial = summarize(_rows([48, 48]), 48, None, split_size=200)
    assert partial["targets"]["bit_acc >= 99.5 %"] is None and partial["targets"]["training <= 15 min"] is None
    md = report(partial)
    assert "2 of 200" in md and "not measured" in md and "| met |" in md


def test_chart_is_a_png(tmp_path):
    from PIL import Image

    p = chart(_rows([48, 47, 48]), 48, 41, tmp_path / "views.png")
    with Image.open(p) as im:
        assert im.format == "PNG" and im.size[0] > 100
    assert chart([], 48, 41, tmp_path / "none.png") is None


def test_page_prints_only_numbers_the_summary_holds():
    """The page's targets table and counts come from summarize's JSON: bits matched, the views below all bits,
    the per-view PSNR change range, the training wall time."""
    rows = _rows([48, 47, 48])
    rows[1]["psnr_marked_vs_gt_db"] = 26.2  # +0.1 dB for view 1, -0.1 for the others
    v = summarize(rows, 48, {"wall_s": 155.0}, split_size=3)
    assert v["bits_matched"] == 143 and v["bits_total"] == 144
    assert v["views_below_all_bits"] == [{"index": 1, "matches": 47}] and v["train_wall_s"] == 155.0
    assert (
        abs(v["psnr_change_per_view_db"]["min"] + 0.1) < 1e-9 and abs(v["psnr_change_per_view_db"]["max"] - 0.1) < 1e-9
    )
    run = {
        "command": "python -m gsticker_plugin.bench.targets --x",
        "date": "d",
        "cpu": "c",
        "threads": 2,
        "steps": 300,
        "pool_views": 16,
        "warmup_steps": 50,
        "owner_id": "o",
    }
    md = page({"run": run, "train": {"wall_s": 155.0}, "views": v}, "bench-targets.json", "bench-targets.png")
    assert "**99.31 %** (143 of 144 bits; 2 views 48/48; view 1 47/48)" in md
    assert "per view -0.10..+0.10" in md and "**2.6 min** (155 s wall" in md and "3 of 3; decoding 5.0 s" in md
    assert "[bench-targets.json](bench-targets.json)" in md and "a 300-step sticker" in md
