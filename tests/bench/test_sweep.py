"""bench.sweep: the log parsing and the choice of the smallest variant (the training itself is a benchmark)."""

from pathlib import Path

from gsticker_plugin.bench.sweep import SweepConfig, image_lines, markdown
from gsticker_plugin.evaluation.sweep import VARIANTS, cost_lines, smallest_meeting, train_seconds


def test_train_seconds_reads_pool_and_monitor_lines(tmp_path):
    log = tmp_path / "x.log"
    log.write_text(
        "\x1b[1m[gsticker] pool: 16 views + 2 held out, 40 MiB, 83 s; gate mu=21.3, beta=2.13\x1b[0m\n"
        "[gsticker] step 50: held-out bit acc 0.5260 (clean renders: 0.500), PSNR marked/clean 15.99 dB, 17 s\n"
        "[gsticker] step 100: held-out bit acc 0.5521 (clean renders: 0.448), PSNR marked/clean 36.10 dB, 36 s\n"
    )
    pool, steps = train_seconds(log)
    assert pool == 83.0 and steps == {50: 17.0, 100: 36.0}
    assert train_seconds(tmp_path / "missing.log") == (None, {})


def _row(name, params, acc, psnr, bits=48, size=100):
    return {
        "name": name,
        "sticker_params": params,
        "num_bits": bits,
        "size": [size, size],
        "points": [
            {
                "step": 150,
                "train_seconds": 100.0,
                "bit_acc": acc,
                "psnr_vs_unwm": psnr,
                "psnr_vs_gt": 25.0,
                "matches": [48, 48],
                "views_passing": 2,
                "decode_seconds_per_view": 3.0,
            }
        ],
    }


def test_smallest_meeting_needs_both_targets_and_48_bits_at_the_base_resolution():
    rows = [
        _row("default", 9000, 1.0, 40.0),
        _row("width-16", 2000, 0.7, 45.0),
        _row("width-32", 5000, 1.0, 34.0),
        _row("bits-16", 100, 1.0, 50.0, bits=16),
        _row("res-200", 50, 1.0, 50.0, size=200),
    ]
    assert smallest_meeting(rows, 0.99, 35.0)["name"] == "default"
    rows.append(_row("width-24", 4000, 0.995, 36.0))
    assert smallest_meeting(rows, 0.99, 35.0)["name"] == "width-24"
    assert smallest_meeting(rows[1:2], 0.99, 35.0) is None
    # trained heads count toward the size: the same sticker without heads in the loop is smaller
    heads = [
        dict(_row("default", 9000, 1.0, 40.0), heads_params=280000),
        dict(_row("heads-none", 9000, 1.0, 40.0), heads_params=0),
    ]
    assert smallest_meeting(heads, 0.99, 35.0)["name"] == "heads-none"
    assert {"heads-none", "heads-8", "heads-vgg16"} <= set(VARIANTS)
    assert "--pipeline.msg-weight" in VARIANTS["heads-none"][0]


def test_markdown_has_a_row_per_point_and_names_the_command():
    cfg = SweepConfig(load_checkpoint=Path("base/step.ckpt"), variants=("default", "width-16"))
    md = markdown(cfg, [_row("default", 9000, 1.0, 40.0), _row("width-16", 2000, 0.7, 45.0)], "today", "cpu")
    assert "python -m gsticker_plugin.bench.sweep --load-checkpoint base/step.ckpt" in md
    assert "--warmup-steps 25 --pool-views 8 --work-dir outputs/bench-sweep " in md  # what the page's runs used
    # one row per checkpoint, and one in the cost table
    assert md.count("| default |") == 2 and md.count("| width-16 |") == 2
    assert "**default**" in md
    assert set(cfg.variants) <= set(VARIANTS)


def test_cost_lines_give_the_first_checkpoint_meeting_both_targets_ordered_by_image_size_and_bits():
    slow = _row("res-200", 50, 1.0, 40.0, size=200)
    slow["points"].insert(0, {**slow["points"][0], "step": 50, "train_seconds": 30.0, "psnr_vs_unwm": 30.0})
    early = _row("bits-64", 60, 1.0, 40.0, bits=64)
    early["points"].insert(0, {**early["points"][0], "step": 50, "train_seconds": 20.0})
    lines = cost_lines([slow, _row("width-16", 20, 0.7, 45.0), early], 0.99, 35.0)
    body = [x for x in lines if x.startswith("| ") and not x.startswith("| variant")]
    assert [x.split(" | ")[0] for x in body] == ["| width-16", "| bits-64", "| res-200"]
    assert "| not reached | - |" in body[0]
    assert "| 64 | 50 | 20.0 |" in body[1]  # met at its first checkpoint
    assert "| 200 px | 48 | 150 | 100.0 |" in body[2]  # its first checkpoint misses the PSNR target
    assert body[2].endswith("| 3.00 | - | - |")  # no pool seconds recorded: no per-step cost
    slow["pool_seconds"] = 40.0
    body = [x for x in cost_lines([slow], 0.99, 35.0) if x.startswith("| res-200")]
    assert body[0].endswith("| 3.00 | 40 | 0.40 |")  # (100 s at step 150 - 40 s pool) / 150 steps


def test_the_robust_variant_trains_the_robust_presets_sticker_settings():
    from method_configs.geometrysticker import geometrysticker_robust_config

    args = VARIANTS["robust"][0]
    given = dict(zip(args[::2], args[1::2]))
    p = geometrysticker_robust_config().pipeline
    assert float(given["--pipeline.model.sticker-amplitude"]) == p.model.sticker_amplitude
    assert (float(given["--pipeline.mark-psnr"]), float(given["--pipeline.target-psnr"])) == (
        p.mark_psnr,
        p.target_psnr,
    )
    assert float(given["--pipeline.condition-weight"]) == p.condition_weight
    assert given["--pipeline.condition-scale-free"] == str(p.condition_scale_free)
    assert float(given["--pipeline.condition-blur"]) == p.condition_blur


def _with_images(row, readings):
    """``row`` whose points carry image-decoder readings ``readings[i] = {attack: (bit_acc, matches)}``."""
    for p, r in zip(row["points"], readings):
        p["image_psnr_db"] = 36.5
        p["image_decode_seconds_per_view"] = 1.3
        p["image"] = {
            a: {"bit_acc": acc, "matches": m, "views_passing": sum(x >= 41 for x in m)} for a, (acc, m) in r.items()
        }
    return row


def test_the_image_table_gives_a_row_per_checkpoint_with_each_attacks_accuracy_and_views_passing():
    cfg = SweepConfig(load_checkpoint=Path("base/step.ckpt"), variants=("robust",), image_views=2)
    plain = _row("default", 9000, 1.0, 40.0)
    assert image_lines([plain], cfg) == []  # no readings, no table
    row = _with_images(_row("robust", 9456, 1.0, 35.0), [{"clean": (1.0, [48, 48]), "jpeg=50": (0.9375, [48, 42])}])
    lines = image_lines([plain, row], cfg)
    assert (
        "| variant | step | train s | held-out PSNR (dB) | image clean | image jpeg=50 | image decode s/view |" in lines
    )
    assert "| robust | 150 | 100.0 | 36.50 | 100.0 (2/2) | 93.8 (2/2) | 1.3 |" in lines
    assert sum(line.startswith("| default |") for line in lines) == 0  # the point without readings has no row


def test_the_command_line_names_the_image_views_and_attacks_only_when_asked():
    row = _row("robust", 9456, 1.0, 35.0)
    cfg = SweepConfig(load_checkpoint=Path("b.ckpt"), image_views=24, image_attacks=("clean", "hue=~0.5"))
    md = markdown(cfg, [row], "today", "cpu")
    assert (
        "--work-dir outputs/bench-sweep --image-views 24 --image-attacks clean hue=~0.5 --output docs/experiments/bench-sweep.md`"
        in md
    )
    assert "--camera-seed" not in md  # bench.unposed's default seed is left out
    assert "--image-views" not in markdown(SweepConfig(load_checkpoint=Path("b.ckpt")), [row], "today", "cpu")
