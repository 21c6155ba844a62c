"""The images-without-cameras bench (gsticker_plugin.bench.unposed and its page, bench.unposed_page): rows, resume,
jitter, the null, the page."""

import hashlib
import json
from pathlib import Path

import pytest
import torch

from gsticker_plugin import metrics
from gsticker_plugin.bench.unposed import BenchUnposedConfig
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.evaluation.held_out import attacked, drawn_spec, folder_images, purify_steps
from gsticker_plugin.evaluation.unposed_page import (
    breaking_points,
    is_null_row,
    is_removal_row,
    match_histogram,
    not_reached,
    null_chart,
    null_summary,
    other_keys,
    row_key,
    threat_curves,
    threat_lines,
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
    # held-out camera rows stop at --num-views (24); random images need no camera: as many as asked
    assert wanted(config(("marked:@64", "random:@64"))) == {"marked:": 24, "random:": 64}


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
    assert 21 < out["matches_mean"] < 27 and out["passing"] == 0 and out["passing_pairs"] == 0
    assert other_keys([], 64, 41) is None


def test_each_other_key_is_one_check_because_images_of_one_model_read_alike():
    """Ten images decoding the same bits checked with 64 keys are 64 independent checks, not 640: counting every
    pair would shrink the null's confidence bound tenfold with no new evidence."""
    out = other_keys([{"bits": "01" * 24} for _ in range(10)], 64, 41)
    assert out["checks"] == 64 and out["pairs"] == 640 and sum(out["histogram"]) == 64
    assert out["matches_max_pairs"] == out["matches_max"]  # every image reads alike: the pairs add nothing


def test_the_null_bound_is_clopper_pearson():
    """0 of n: the rule of three's exact form 1 - 0.05^(1/n); 5 of 100 lies between the observed rate and 0.12."""
    assert abs(metrics.clopper_pearson_upper(0, 800) - (1 - 0.05 ** (1 / 800))) < 1e-9
    assert 0.05 < metrics.clopper_pearson_upper(5, 100) < 0.12
    assert metrics.clopper_pearson_upper(3, 3) == 1.0


def test_the_null_is_the_distinct_unmarked_images_and_never_the_other_keys_checks():
    """Each unmarked image counts once; the other keys' checks (the marked images' bits against random messages) are
    not null images and stay out of its count, histogram, mean and bound."""
    rows = [{"matches": 20}, {"matches": 28}, {"matches": 42}]
    n = null_summary(rows, 41)
    assert n["images"] == 3 and n["passing"] == 1 and n["matches_max"] == 42 and "checks" not in n
    assert abs(n["matches_mean"] - 30.0) < 1e-12 and n["fpr"] == 1 / 3
    assert abs(n["fpr_upper_95"] - metrics.clopper_pearson_upper(1, 3)) < 1e-12
    assert sum(n["histogram"]) == 3 and n["histogram"][42] == 1
    assert null_summary([], 41) is None


def test_other_keys_histogram_counts_each_check_once():
    rows = [{"bits": "01" * 24} for _ in range(5)]
    others = other_keys(rows, 8, 41)
    assert sum(others["histogram"]) == others["checks"] == 8 and len(others["histogram"]) == 49
    assert sum(k * c for k, c in enumerate(others["histogram"])) == others["matches_mean"] * 8
    unmarked = [{"matches": 20, "bits": "0" * 48}, {"matches": 20, "bits": "1" * 48}, {"matches": 0, "bits": "?" * 48}]
    n = null_summary(unmarked, 41)
    assert n["images"] == 2 and n["histogram"][20] == 2 and n["nothing_read"] == 1 and 0.77 < n["fpr_upper_95"] < 0.78
    assert match_histogram([0, 48, 48], 48)[48] == 2


def test_the_null_chart_is_written_beside_the_page(tmp_path):
    n = null_summary([{"matches": 22}, {"matches": 27}], 41)
    null_chart(n, [48, 47, 46], [23, 33], tmp_path / "p-null.png", 48, 41)
    assert (tmp_path / "p-null.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_removal_rows_are_the_threat_models_and_nothing_else():
    assert [is_removal_row(r) for r in ("pgd=40:", "purify=3:", "leak=0.5:")] == [True] * 3
    assert [is_removal_row(r) for r in ("marked:", "palette=blue:", "random:", "marked:jpeg=50")] == [False] * 4


def test_scene_rows_join_the_null_and_leak_or_purify_rows_do_not():
    assert [is_null_row(r) for r in ("clean:", "random:", "foreign:", "scene=out/x/train:")] == [True] * 4
    assert [is_null_row(r) for r in ("marked:", "leak=0.5:", "purify=10:", "palette=blue:")] == [False] * 4


def test_purification_runs_through_the_rows_step_counts_in_order():
    assert purify_steps(("purify=30:@2", "marked:@4", "purify=3:@1", "purify=30:jpeg=50@1")) == [3, 30]


def test_another_scene_is_read_sorted_by_name_and_must_match_the_renders_size(tmp_path):
    import imageio.v2 as imageio

    for name, value in (("b.png", 200), ("a.png", 10), ("c.png", 90)):
        imageio.imwrite(tmp_path / name, torch.full((8, 6, 3), value, dtype=torch.uint8).numpy())
    imgs = folder_images(tmp_path, 2, (8, 6))
    assert imgs.shape == (2, 8, 6, 3)
    assert torch.allclose(imgs[:, 0, 0, 0], torch.tensor([10, 200]) / 255.0)
    with pytest.raises(ValueError, match="6x9 px"):
        folder_images(tmp_path, 2, (9, 6))
    with pytest.raises(ValueError, match="needs 4 images"):
        folder_images(tmp_path, 4, (8, 6))


def test_threat_curve_pairs_each_purified_model_with_its_geometric_reading(tmp_path):
    cfg = config(("purify=10:@2", "leak=0.5:@2", "pgd=45:@2"))
    cfg.work_dir, cfg.output = tmp_path, tmp_path / "page.md"
    (tmp_path / "purify.json").write_text(
        json.dumps(
            {
                "10": {
                    "steps": 10,
                    "psnr_vs_marked_db": 30.0,
                    "psnr_vs_clean_db": 31.0,
                    "geometric_matches": [20, 45],
                    "geometric_bit_acc": 65 / 96,
                    "purify_seconds": 2.0,
                }
            }
        )
    )
    (tmp_path / "leak.json").write_text(json.dumps({"0.5": {"psnr_vs_marked_db": 51.0, "psnr_vs_clean_db": 51.2}}))
    pgd_point = {"psnr_vs_marked_db": 45.5, "psnr_vs_clean_db": 36.0, "posed_matches": [30, 42], "posed_bit_acc": 0.75}
    (tmp_path / "pgd.json").write_text(json.dumps({"45.0": pgd_point}))
    table = {
        "purify=10:": {"bit_acc": 0.5, "passing": 0, "images": 2},
        "leak=0.5:": {"bit_acc": 0.9, "passing": 1, "images": 2},
        "pgd=45:": {"bit_acc": 0.6, "passing": 0, "images": 2},
    }
    purify, leak, pgd = threat_curves(cfg, table, 41, 48)
    assert (pgd["attack"], pgd["strength"], pgd["posed_passing"], pgd["images_passing"]) == ("pgd", 45.0, "1/2", "0/2")
    assert purify["posed_passing"] is None
    assert (purify["attack"], purify["strength"], purify["geometric_passing"]) == ("purify", 10, "1/2")
    assert purify["images_passing"] == "0/2" and purify["psnr_vs_marked_db"] == 30.0
    assert (leak["attack"], leak["strength"], leak["geometric_bit_acc"], leak["psnr_vs_marked_db"]) == (
        "leak",
        0.5,
        None,
        51.0,
    )
    assert (tmp_path / "page.png").stat().st_size > 1000
    lines = threat_lines([purify, leak, pgd], cfg.output, 1e-4, 512)
    assert "| purify | 10 | 30.00 | 31.00 | 50.0 %, 0/2 | 67.7 %, 1/2 | - | 2.0 |" in lines
    assert "| pgd | 45.0 | 45.50 | 36.00 | 60.0 %, 0/2 | - | 75.0 %, 1/2 | - |" in lines
    assert any("learning rate 0.0001, 512 rays per step" in line for line in lines)


def test_a_work_dir_restored_without_attack_records_keeps_the_pages_recorded_threat_points(tmp_path):
    cfg = config(("purify=10:@2", "pgd=45:@1"))
    cfg.work_dir, cfg.output = tmp_path, tmp_path / "page.md"
    kept = {
        **{k: None for k in ("posed_bit_acc", "posed_passing", "purify_seconds", "psnr_vs_clean_db")},
        **{"attack": "purify", "strength": 10, "psnr_vs_marked_db": 33.6},
        **{"geometric_bit_acc": 0.97, "geometric_passing": "8/8", "images_bit_acc": 1.0, "images_passing": "2/2"},
    }
    table = {
        "purify=10:": {"bit_acc": 0.5, "passing": 0, "images": 2},
        "pgd=45:": {"bit_acc": 0.9, "passing": 1, "images": 1},
    }
    (purify,) = threat_curves(cfg, table, 41, 48, [kept, {**kept, "attack": "leak"}])
    assert purify["psnr_vs_marked_db"] == 33.6 and purify["geometric_passing"] == "8/8"
    assert (purify["images_bit_acc"], purify["images_passing"]) == (0.5, "0/2")  # read from the rows, not kept
    assert threat_curves(cfg, table, 41, 48) == []  # nothing recorded anywhere: no point is made up


def test_the_threat_table_says_where_each_decoder_breaks():
    def point(steps, images, geometric, acc):
        return {
            "attack": "purify",
            "strength": steps,
            "psnr_vs_marked_db": 40.0 - steps,
            "images_passing": images,
            "images_bit_acc": acc,
            "geometric_passing": geometric,
            "geometric_bit_acc": acc,
        }

    points = [point(10, "0/1", "2/2", 0.6), point(1, "1/1", "2/2", 1.0), point(3, "1/1", "1/2", 0.8)]
    points.append({**point(0.5, "0/1", None, 0.5), "attack": "leak"})
    pgd = {**point(0, "1/1", None, 1.0), "attack": "pgd", "posed_passing": "2/2", "posed_bit_acc": 1.0}
    points += [{**pgd, "strength": 50.0}, {**pgd, "strength": 40.0, "images_passing": "0/1", "images_bit_acc": 0.5}]
    lines = breaking_points(points)
    assert lines == [
        "- purify, images alone: every image passes up to 3 steps (37.0 dB vs marked); breaks at 10 steps "
        "(30.0 dB vs marked, 60.0 % of bits).",
        "- purify, informed geometric: every image passes up to 1 step (39.0 dB vs marked); breaks at 3 steps "
        "(37.0 dB vs marked, 80.0 % of bits).",
        "- leak, images alone: the weakest setting tried already breaks it; breaks at 0.5 blended (39.5 dB vs marked, "
        "50.0 % of bits).",
        "- pgd, images alone: every image passes up to a 50 dB budget (40.0 dB vs marked); breaks at a 40 dB budget "
        "(40.0 dB vs marked, 50.0 % of bits).",
        "- pgd, informed image, true cameras: every image passes up to a 40 dB budget (40.0 dB vs marked); no setting "
        "tried breaks it.",
    ]


def test_a_cropout_row_pastes_the_clean_render_of_the_same_camera_or_paints_white_without_one():
    marked = torch.full((20, 20, 3), 0.2)
    clean = torch.full((20, 20, 3), 0.6)
    pasted = attacked(marked, "crop=0.25", torch.Generator().manual_seed(0), clean)
    painted = attacked(marked, "crop=0.25", torch.Generator().manual_seed(0), None)
    inside = (pasted - marked).abs().amax(dim=-1) > 0.1
    assert 80 <= int(inside.sum()) <= 120  # a quarter of the 400 pixels
    assert torch.allclose(pasted[inside], torch.tensor(0.6), atol=1 / 255)
    assert torch.equal((painted - marked).abs().amax(dim=-1) > 0.1, inside)  # the same rectangle
    assert torch.allclose(painted[inside], torch.tensor(1.0))
    assert torch.allclose(pasted[~inside], torch.tensor(0.2), atol=1 / 255)


def test_the_summary_counts_each_route_an_image_was_read_through():
    from gsticker_plugin.evaluation.unposed_page import summarize

    row = {"matches": 40, "signals": ["rgb"], "seconds": 1.0}
    rows = [
        {**row, "degradation": "jpeg=50"},
        {**row, "degradation": "blur=1"},
        {**row, "degradation": "rotate=-3"},
        {**row, "signals": ["value"], "degradation": "none"},
        {**row, "degradation": "none", "covered_share": 0.3},
    ]
    t = summarize(rows, 41, 48)
    assert (t["read_through_jpeg"], t["read_through_blur"], t["read_as_turned"], t["read_by_value"]) == (1, 1, 1, 1)
    assert t["read_around_cover"] == 1
    assert t["passing"] == 0 and t["matches_mean"] == 40.0


def test_an_image_with_nothing_to_read_is_left_out_of_the_null_mean_and_counts_zero_for_the_owner():
    """Every bit undetermined (no ray the gate reads at the camera found): a null row's mean is over the images read,
    with the unread one counted apart; a marked row keeps its 0 matches (never flattering the owner)."""
    from gsticker_plugin.evaluation.unposed_page import read_nothing, summarize

    row = {"signals": ["rgb"], "seconds": 1.0}
    rows = [{**row, "matches": 22, "bits": "01" * 24}, {**row, "matches": 26, "bits": "10" * 24}]
    rows.append({**row, "matches": 0, "bits": "?" * 48})
    assert [read_nothing(r) for r in rows] == [False, False, True]
    null = summarize(rows, 41, 48, null=True)
    assert null["matches_mean"] == 24.0 and null["matches_min"] == 22 and null["nothing_read"] == 1
    marked = summarize(rows, 41, 48)
    assert marked["matches_mean"] == 16.0 and marked["matches_min"] == 0 and marked["nothing_read"] == 1
    pooled = null_summary(rows, 41)
    assert pooled["images"] == 2 and pooled["nothing_read"] == 1 and pooled["matches_mean"] == 24.0


def test_a_page_rewritten_from_its_rows_keeps_the_recorded_psnr_and_draws_the_null(tmp_path):
    """--page-only on a work dir whose run has changed since: the page's own JSON keeps the PSNR it was decoded at."""

    from gsticker_plugin.evaluation.unposed_page import recorded_page, write_page

    cfg = BenchUnposedConfig(
        load_config=Path("c.yml"),
        key=Path("k.gskey"),
        rows=("marked:@2", "clean:@1"),
        random_images=0,
        work_dir=tmp_path / "work",
        output=tmp_path / "page.md",
    )
    row = {"signals": ["rgb"], "seconds": 1.0, "explained": 0.0, "pose_rms": 0.0}
    done = {
        ("marked:", 0): {**row, "row": "marked:@2", "view": 0, "matches": 48, "bits": "01" * 24},
        ("marked:", 1): {**row, "row": "marked:@2", "view": 1, "matches": 47, "bits": "01" * 23 + "00"},
        ("clean:", 0): {**row, "row": "clean:@1", "view": 0, "matches": 22, "bits": "10" * 24},
    }
    assert recorded_page(cfg.output.with_suffix(".json")).get("psnr_marked_vs_clean_db") is None
    res = write_page(cfg, 48, done, 41, {"mean": 45.42, "min": 43.53})
    assert recorded_page(cfg.output.with_suffix(".json"))["psnr_marked_vs_clean_db"] == {"mean": 45.42, "min": 43.53}
    page = cfg.output.read_text()
    assert "PSNR marked vs clean 45.42 dB mean, 43.53 dB worst view" in page
    assert res["null"]["images"] == 1 and res["other_keys"]["checks"] == 64 and res["rows"]["marked:"]["passing"] == 2
    assert "**The null: 1 distinct unmarked images, each decoded once**" in page and "not part of the null" in page
    assert "![matches of the null beside the marked images](page-null.png)" in page
    assert (tmp_path / "page-null.png").exists()
    first = res["date"]
    assert res["key_sha256"] is None  # no key file: no identity made up
    cfg.key = tmp_path / "k.gskey"
    cfg.key.write_bytes(b"first key")
    res = write_page(cfg, 48, done, 41, {"mean": 45.42, "min": 43.53})
    assert res["key_sha256"] == hashlib.sha256(b"first key").hexdigest()
    assert f"Owner key sha256 `{res['key_sha256'][:16]}`." in cfg.output.read_text()
    cfg.key.write_bytes(b"a retrained model's key")  # a page-only rewrite keeps the key it was decoded with
    again = write_page(
        cfg.__class__(**{**vars(cfg), "page_only": True}),
        48,
        done,
        41,
        {"mean": 45.42, "min": 43.53},
    )
    assert again["decoded"] == first and again["machine"] == res["machine"]
    assert again["key_sha256"] == hashlib.sha256(b"first key").hexdigest()
    assert f"first page {first}; this page rewritten from their rows" in cfg.output.read_text()


def test_a_drawn_attack_row_shows_the_strength_drawn_for_each_view_and_development_rows_are_named(tmp_path):
    """``hue=~0.5`` names a range: the page prints what each view got; rows that read only the development views
    say so, rows that read more do not."""
    from gsticker_plugin.evaluation.unposed_page import drawn, write_page

    row = {"signals": ["rgb"], "seconds": 1.0, "explained": 0.0, "pose_rms": 0.0, "bits": "01" * 24}
    done = {
        ("marked:hue=~0.5", 1): {**row, "row": "marked:hue=~0.5@2", "view": 1, "matches": 48, "attack": "hue=0.257632"},
        ("marked:hue=~0.5", 0): {**row, "row": "marked:hue=~0.5@2", "view": 0, "matches": 48, "attack": "hue=-0.0037"},
        ("marked:", 0): {**row, "row": "marked:@6", "view": 0, "matches": 48},
        ("clean:", 0): {**row, "row": "clean:@1", "view": 0, "matches": 22, "bits": "10" * 24},
    }
    assert drawn([done["marked:hue=~0.5", 1], done["marked:hue=~0.5", 0]]) == "hue -0.0037, hue +0.258"
    cfg = BenchUnposedConfig(
        load_config=Path("c.yml"),
        key=Path("k.gskey"),
        rows=("marked:hue=~0.5@2", "marked:@6", "clean:@1"),
        random_images=0,
        development_views=4,
        work_dir=tmp_path / "work",
        output=tmp_path / "page.md",
    )
    write_page(cfg, 48, done, 41, {"mean": 45.0, "min": 44.0})
    page = cfg.output.read_text()
    assert "| hue=~0.5 (drawn per view: hue -0.0037, hue +0.258) |" in page
    assert "chosen; every row but `marked:` read only those views: development evidence" in page


def test_a_page_is_rewritten_from_its_own_json_without_its_run_key_or_work_dir(tmp_path):
    from gsticker_plugin.bench.unposed import main
    from gsticker_plugin.evaluation.unposed_page import write_page

    row = {"signals": ["rgb"], "seconds": 1.0, "explained": 0.0, "pose_rms": 0.0}
    done = {
        ("marked:", 0): {**row, "row": "marked:@1", "view": 0, "matches": 48, "bits": "01" * 24},
        ("clean:", 0): {**row, "row": "clean:@1", "view": 0, "matches": 22, "bits": "10" * 24},
    }
    kw = dict(load_config=tmp_path / "gone.yml", key=tmp_path / "gone.gskey", rows=("marked:@1", "clean:@1"))
    cfg = BenchUnposedConfig(**kw, random_images=0, work_dir=tmp_path / "work", output=tmp_path / "page.md")
    write_page(cfg, 48, done, 41, {"mean": 45.0, "min": 44.0})
    again = main(
        BenchUnposedConfig(**kw, random_images=0, work_dir=tmp_path / "gone", output=cfg.output, page_only=True)
    )
    assert again["rows"]["marked:"]["passing"] == 1 and again["null"]["images"] == 1
    assert again["psnr_marked_vs_clean_db"] == {"mean": 45.0, "min": 44.0} and "45.00 dB mean" in cfg.output.read_text()
    with pytest.raises(GStickerError, match="--page-only"):
        main(BenchUnposedConfig(**kw, work_dir=tmp_path / "gone", output=tmp_path / "none.md", page_only=True))
