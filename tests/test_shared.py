"""The shared run (gsticker_plugin.shared): ``ns-train geometrysticker`` on a nerfacto base writes a stock run of a
Nerfstudio method whose hash table carries the message, and nothing else.

Pure parts first (the marked state, the stock method and data manager, the mark's choice), then a real run: a
100-step nerfacto base on the tiny scene, marked by ``ns-train geometrysticker``, opened without gsticker, rendered by
stock ``ns-render`` and read by ``ns-verify-owner``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Dict

import pytest
import torch
from conftest import BIN, CPU_ARGS, TINY_MESSAGE, ns_train, subprocess_env

from gsticker_plugin import fieldmark as FM
from gsticker_plugin import runs
from gsticker_plugin.decoders.viewbank import bank_folder
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.key import OwnerKey, default_key_path, parse_message
from gsticker_plugin.shared import as_stock_method, marked_pipeline_state, stock_method_name
from gsticker_plugin.trainer import chosen_mark

HELPERS = Path(__file__).parent / "helpers"
OWNER_PATTERN_SEED = 977
"""The tests' owner pattern seed (a user's is drawn with `secrets`): not one a recipient would guess first."""


# ---------------------------------------------------------------------------------------------- pure parts


def test_the_marked_state_differs_from_the_base_in_the_one_table():
    g = torch.Generator().manual_seed(0)
    state = {"_model.table": torch.randn(64, 2, generator=g), "_model.other": torch.randn(5, generator=g), "x": 3}
    pats = FM.patterns((64, 2), 16, [1], 8, seed=1)
    msg = parse_message("10110010", 8)
    out = marked_pipeline_state(state, "_model.table", pats, msg, 0.1)
    assert set(out) == set(state) and out["_model.other"] is state["_model.other"] and out["x"] == 3
    diff = out["_model.table"] - state["_model.table"]
    assert diff[:16].abs().sum() == 0 and diff[32:].abs().sum() == 0 and diff[16:32].abs().sum() > 0
    assert torch.allclose(diff, FM.marked_table(torch.zeros(64, 2), pats, FM.signs_of(msg), 0.1))


def test_a_preset_base_is_shared_as_nerfstudios_own_method_with_its_data_manager():
    from nerfstudio.configs.method_configs import method_configs

    from method_configs.presets import nerfacto_small_config, tensorf_small_config

    cfg = nerfacto_small_config()
    assert stock_method_name(cfg) == "nerfacto" and stock_method_name(tensorf_small_config()) == "tensorf"
    rays = cfg.pipeline.datamanager.train_num_rays_per_batch
    as_stock_method(cfg, "nerfacto")
    assert cfg.method_name == "nerfacto"
    assert type(cfg.pipeline.datamanager) is type(method_configs["nerfacto"].pipeline.datamanager)
    assert cfg.pipeline.datamanager.train_num_rays_per_batch == rays  # the base's own settings kept
    stock = method_configs["nerfacto"]
    assert stock_method_name(stock) == "nerfacto"


def test_the_mark_is_the_field_for_torch_nerfacto_and_tensorf_and_the_sticker_otherwise():
    from method_configs.presets import nerfacto_small_config, tensorf_small_config, vanilla_nerf_small_config

    nerfacto, tensorf = nerfacto_small_config().pipeline.model, tensorf_small_config().pipeline.model
    vanilla = vanilla_nerf_small_config().pipeline.model
    assert chosen_mark("auto", nerfacto) == "field" and chosen_mark("auto", tensorf) == "field"
    assert chosen_mark("field", tensorf) == "field"
    assert chosen_mark("auto", vanilla) == "sticker" and chosen_mark("sticker", nerfacto) == "sticker"
    with pytest.raises(GStickerError, match="--pipeline.mark sticker"):
        chosen_mark("field", vanilla)
    nerfacto.implementation = "tcnn"
    tensorf.tensorf_encoding = "cp"
    assert chosen_mark("auto", nerfacto) == "sticker" and chosen_mark("auto", tensorf) == "sticker"
    with pytest.raises(GStickerError, match="--pipeline.mark sticker"):
        chosen_mark("field", tensorf)


# ---------------------------------------------------------------------------------------------- a real shared run


@pytest.fixture(scope="module")
def shared(tiny_trained_base, tmp_path_factory) -> Dict[str, Path]:
    """``ns-train geometrysticker`` on the 100-step tiny base, message ``TINY_MESSAGE`` and pattern seed
    ``OWNER_PATTERN_SEED``: ``{base, run, key, out}``."""
    out = tmp_path_factory.mktemp("shared")
    ckpt = max((tiny_trained_base.parent / "nerfstudio_models").glob("step-*.ckpt"))
    args = ["geometrysticker", "--load-checkpoint", str(ckpt), *CPU_ARGS, "--output-dir", str(out)]
    args += ["--experiment-name", "gs", "--timestamp", "run", "--pipeline.message", TINY_MESSAGE]
    ns_train([*args, "--pipeline.pattern-seed", str(OWNER_PATTERN_SEED)], out)
    key = default_key_path("gs", "geometrysticker", "run")
    return {"base": tiny_trained_base, "run": out / "gs" / "nerfacto" / "run" / "config.yml", "key": key, "out": out}


def test_the_shared_run_is_a_stock_run_with_the_base_state_dict_keys_and_no_secret(shared):
    run = shared["run"]
    assert sorted(p.name for p in (shared["out"] / "gs").iterdir()) == ["nerfacto"]  # no geometrysticker folder
    assert sorted(p.name for p in run.parent.iterdir()) == ["config.yml", "nerfstudio_models"]
    cfg, base_cfg = runs.load_run_config(run), runs.load_run_config(shared["base"])
    assert cfg.method_name == "nerfacto" and type(cfg.pipeline.model) is type(base_cfg.pipeline.model)
    assert cfg.pipeline.model == base_cfg.pipeline.model
    text = run.read_text()
    assert "gsticker_plugin" not in text and TINY_MESSAGE not in text and "pattern_seed" not in text
    state = runs.load_checkpoint_state(runs.latest_checkpoint(run.parent / "nerfstudio_models"))["pipeline"]
    base = runs.load_checkpoint_state(runs.latest_checkpoint(shared["base"].parent / "nerfstudio_models"))["pipeline"]
    assert set(state) == set(base) and all(state[k].shape == base[k].shape for k in base)
    changed = [k for k in base if not torch.equal(state[k], base[k])]
    table = "_model.field.mlp_base.model.0.hash_table"
    assert changed == [table]
    # the recipient's tell: rows a stock run leaves at their initial values (never sampled) are left as they were
    untouched = ~FM.trained_rows(base[table], 0.001)
    assert untouched.sum() > 100 and torch.equal(state[table][untouched], base[table][untouched])
    key = OwnerKey.load(shared["key"])
    assert (
        key.field_mark["pattern_seed"] == OWNER_PATTERN_SEED
        and key.field_mark["levels"] == [0, 1, 2, 3]
        and key.signed()
    )
    assert key.heads_state == {} and key.geometry is None and key.model_run == str(run.parent)


def test_the_shared_run_opens_with_gsticker_not_importable(shared):
    proc = subprocess.run(
        [sys.executable, str(HELPERS / "open_without_gsticker.py"), str(shared["run"])],
        capture_output=True,
        text=True,
        env=subprocess_env(1),
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got == {"method": "nerfacto", "model": "NerfactoModel", "rgb": [32, 32, 3], "gsticker_loaded": []}


def test_stock_ns_render_renders_the_shared_run(shared, tmp_path):
    cmd = [str(BIN / "ns-render"), "dataset", "--load-config", str(shared["run"]), "--split", "test"]
    cmd += ["--output-path", str(tmp_path / "render"), "--rendered-output-names", "rgb"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env(1), cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert len(list((tmp_path / "render" / "test" / "rgb").glob("*.jpg"))) == 2


def verify(config: Path, key: Path, out: Path) -> dict:
    proc = subprocess.run(
        [str(BIN / "ns-verify-owner"), "--load-config", str(config), "--key", str(key), "--output", str(out)]
        + ["--num-views", "4", "--no-figure"],
        capture_output=True,
        text=True,
        env=subprocess_env(1),
        timeout=600,
    )
    assert proc.returncode in (0, 1), proc.stderr[-3000:]
    return json.loads((out / "report.json").read_text())


def test_ns_verify_owner_reads_the_message_from_the_shared_run_and_nothing_from_its_base(shared, tmp_path):
    marked = verify(shared["run"], shared["key"], tmp_path / "marked")
    assert marked["verdict"] == "owned" and marked["decoder"]["kind"] == "geometry"
    assert [v["matches"] for v in marked["keys"][0]["per_view"]] == [48] * 4
    base = verify(shared["base"], shared["key"], tmp_path / "base")
    assert base["verdict"] == "not shown" and max(v["matches"] for v in base["keys"][0]["per_view"]) < 41


def test_a_recipient_who_regenerates_the_patterns_from_guessed_seeds_reads_the_shared_table_at_chance(shared):
    """The recipient correlates the shared table with patterns from seeds 0-7 and the config's machine.seed; the
    owner's control, the same reading with the key's secret seed, shows the seed is what protects the message."""
    from gsticker_plugin.attacks.recipient import field_mark_correlation

    cfg = runs.load_run_config(shared["run"])
    table = runs.load_checkpoint_state(runs.latest_checkpoint(shared["run"].parent / "nerfstudio_models"))["pipeline"][
        "_model.field.mlp_base.model.0.hash_table"
    ]
    size = 2**cfg.pipeline.model.log2_hashmap_size
    message = parse_message(TINY_MESSAGE)
    guesses = [*range(8), cfg.machine.seed]
    read = [int((field_mark_correlation(table, size, [0, 1, 2, 3], s, 0.001) == message).sum()) for s in guesses]
    assert max(read) < 41 and len(set(read)) > 1, read
    owner = field_mark_correlation(table, size, [0, 1, 2, 3], OWNER_PATTERN_SEED, 0.001)
    assert int((owner == message).sum()) >= 41


def verify_images(images: Path, key: Path, out: Path) -> dict:
    proc = subprocess.run(
        [str(BIN / "ns-verify-owner"), "--images", str(images), "--key", str(key), "--output", str(out), "--no-figure"],
        capture_output=True,
        text=True,
        env=subprocess_env(1),
        timeout=900,
    )
    assert proc.returncode in (0, 1), proc.stderr[-3000:]
    return json.loads((out / "report.json").read_text())


def test_ns_verify_owner_reads_pictures_of_the_shared_run_without_cameras_and_nothing_from_the_bases(shared, tmp_path):
    """A stock ns-render PNG of the shared run's first test view, read with no camera file (the camera found against
    the owner's base, then the field-mark image fit), beside two copies framed unlike the base's square cameras: the
    render letterboxed into a 16:9 frame with black bars (read once the bars are cut) and cropped to 16:9 (searched
    with its framing). None is skipped for its shape; the render and the letterbox read OWNED; the base's own
    pictures framed the same way read nothing. The camera search's base renders are kept beside the key by the first
    call and read by the second."""
    from PIL import Image

    verdicts = {}
    bank = bank_folder(shared["key"])
    for name, config in (("shared", shared["run"]), ("base", shared["base"])):
        cmd = [str(BIN / "ns-render"), "dataset", "--load-config", str(config), "--split", "test"]
        cmd += ["--output-path", str(tmp_path / name), "--rendered-output-names", "rgb", "--image-format", "png"]
        proc = subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env(1), cwd=tmp_path, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        pictures = sorted((tmp_path / name / "test" / "rgb").glob("*.png"))
        for extra in pictures[1:]:
            extra.unlink()
        render = Image.open(pictures[0]).convert("RGB")
        w, h = render.size
        box = Image.new("RGB", (round(h * 16 / 9), h), (0, 0, 0))
        box.paste(render, ((box.size[0] - w) // 2, 0))
        box.save(pictures[0].parent / "letterbox.png")
        ch = round(w * 9 / 16)
        render.crop((0, (h - ch) // 2, w, (h - ch) // 2 + ch)).save(pictures[0].parent / "crop-16x9.png")
        before = {p: p.stat().st_mtime_ns for p in bank.glob("*.pt")}
        rep = verify_images(pictures[0].parent, shared["key"], tmp_path / f"report-{name}")
        assert rep["decoder"]["kind"] == "image" and rep["input"]["views"] == 3 and not rep["input"]["skipped"]
        fits = {v["name"]: v["image_fit"] for v in rep["keys"][0]["per_view"]}
        assert fits["letterbox.png"]["content_box"][2:] == [(box.size[0] - w) // 2, (box.size[0] - w) // 2 + w], fits
        assert fits["crop-16x9.png"]["camera"] == "estimated with its framing", fits
        verdicts[name] = (rep["verdict"], {v["name"]: v["matches"] for v in rep["keys"][0]["per_view"]})
        after = {p: p.stat().st_mtime_ns for p in bank.glob("*.pt")}
        assert len(after) == 1 and (name == "shared" or after == before), (before, after)
    # the 32x18 crop of this 32 px scene is searched but not read reliably (lego100's crops are:
    # docs/experiments/bench-framed.md)
    shared_reads = verdicts["shared"][1]
    assert verdicts["shared"][0] == "owned", verdicts
    assert shared_reads[pictures[0].name] >= 41 and shared_reads["letterbox.png"] >= 41, verdicts
    assert verdicts["base"][0] == "not shown" and max(verdicts["base"][1].values()) < 41, verdicts
