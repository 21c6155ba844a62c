"""The base presets train through the real ``ns-train`` CLI and load back; the preset benchmark runs end to end.

Every run is tiny (32 px scene, a few iterations). Subprocesses use one torch thread: on a CPU that other jobs
are using, two oversubscribed threads are several times slower than one.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import REPO_ROOT  # noqa: E402

from gsticker_plugin.bench import presets as bench
from gsticker_plugin.evaluation import base_runs

SHARED = REPO_ROOT.parent / "shared"
PRESETS = ("gsticker-nerfacto-small", "gsticker-tensorf-small", "gsticker-vanilla-nerf-small")


def _env() -> dict:
    env = dict(os.environ)
    env.update({"GSTICKER_NO_DOWNLOAD": "1", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore", "COLUMNS": "120"})
    return env


def _tail(proc: subprocess.CompletedProcess) -> str:
    return f"stdout:\n{proc.stdout[-2500:]}\nstderr:\n{proc.stderr[-2500:]}"


# ----------------------------------------------------------------------------- presets through ns-train


@pytest.mark.slow
@pytest.mark.parametrize("preset", PRESETS)
def test_preset_trains_with_ns_train_and_loads_back(preset, tiny_scene, tmp_path, monkeypatch):
    ns_train = Path(sys.executable).parent / "ns-train"
    assert ns_train.exists(), f"ns-train is not installed next to {sys.executable}"
    out = tmp_path / "runs"
    cmd = [
        str(ns_train),
        preset,
        "--machine.device-type",
        "cpu",
        "--vis",
        "tensorboard",
        "--output-dir",
        str(out),
        "--experiment-name",
        "tiny",
        "--timestamp",
        "t",
        "--max-num-iterations",
        "3",
        "--steps-per-save",
        "3",
        "blender-data",
        "--data",
        str(tiny_scene),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=_env(), cwd=tmp_path)
    assert proc.returncode == 0, _tail(proc)
    base = out / "tiny" / preset / "t"
    config_path = base / "config.yml"
    assert config_path.is_file(), _tail(proc)
    checkpoints = sorted((base / "nerfstudio_models").glob("step-*.ckpt"))
    assert [c.name for c in checkpoints] == ["step-000000002.ckpt"], checkpoints  # 3 iterations: steps 0..2

    # Load it back the way ns-viewer / ns-render do, and render one camera.
    from nerfstudio.utils.eval_utils import eval_setup

    from gsticker_plugin import compat

    compat.apply()  # the host fixes the ns-* commands apply

    monkeypatch.setenv("GSTICKER_NO_DOWNLOAD", "1")
    config, pipeline, checkpoint, step = eval_setup(config_path, test_mode="inference")
    assert config.method_name == preset and step == 2 and checkpoint == checkpoints[0]
    camera = pipeline.datamanager.train_dataset.cameras[0:1]
    with torch.no_grad():
        outputs = pipeline.model.get_outputs_for_camera(camera)
    fine = "_fine" if "rgb" not in outputs else ""  # vanilla-nerf: rgb_coarse/rgb_fine, depth_coarse/depth_fine
    rgb = outputs[f"rgb{fine}"]
    assert rgb.shape == (32, 32, 3)
    assert torch.isfinite(rgb).all() and float(rgb.min()) >= 0.0 and float(rgb.max()) <= 1.0
    assert f"depth{fine}" in outputs and torch.isfinite(outputs[f"depth{fine}"]).all()


def test_small_vanilla_nerf_builds_stock_fields_of_the_configured_size(monkeypatch):
    from nerfstudio.data.scene_box import SceneBox
    from nerfstudio.fields.vanilla_nerf_field import NeRFField
    from nerfstudio.models.vanilla_nerf import NeRFModel

    from gsticker_plugin import compat

    compat.apply()  # the host fixes the ns-* commands apply
    from gsticker_plugin.small_nerf import SmallNeRFModel, SmallNeRFModelConfig

    monkeypatch.setenv("GSTICKER_NO_DOWNLOAD", "1")

    def build(**kw):
        box = SceneBox(aabb=torch.tensor([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]))
        return SmallNeRFModelConfig(**kw).setup(scene_box=box, num_train_data=4)

    def mlp_params(model):
        return sum(p.numel() for n, p in model.named_parameters() if n.startswith(("field_coarse", "field_fine")))

    model = build()
    assert isinstance(model, SmallNeRFModel) and isinstance(model, NeRFModel)
    for fld in (model.field_coarse, model.field_fine):
        assert type(fld) is NeRFField
        linears = [m for m in fld.mlp_base.modules() if isinstance(m, torch.nn.Linear)]
        assert len(linears) == 4 and all(m.out_features == 64 for m in linears)
        assert fld.position_encoding.get_out_dim() == 3 + 2 * 3 * 10
    wide = build(base_mlp_num_layers=8, base_mlp_layer_width=256, head_mlp_layer_width=128, skip_connections=(4,))
    assert mlp_params(wide) > 20 * mlp_params(model)  # the stock size, for comparison
    # stock get_outputs on a few rays: the coarse and fine images vanilla-nerf renders
    from nerfstudio.cameras.rays import RayBundle

    n = 5
    rays = RayBundle(
        origins=torch.tensor([[0.0, 0.0, 4.0]]).repeat(n, 1),
        directions=torch.tensor([[0.0, 0.0, -1.0]]).repeat(n, 1),
        pixel_area=torch.ones(n, 1),
        camera_indices=torch.zeros(n, 1, dtype=torch.long),
        nears=torch.full((n, 1), 2.0),
        fars=torch.full((n, 1), 6.0),
    )
    out = model.get_outputs(rays)
    assert out["rgb_fine"].shape == (n, 3) and out["rgb_coarse"].shape == (n, 3)


# ----------------------------------------------------------------------------- benchmark helpers


def test_white_composite_and_psnr():
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[0, 0] = (255, 0, 0, 255)  # opaque red
    rgba[0, 1] = (0, 0, 0, 0)  # transparent: white
    rgba[1, 0] = (0, 0, 0, 255)  # opaque black
    rgba[1, 1] = (0, 0, 0, 51)  # 20 % black over white
    rgb = base_runs.white_composite(rgba)
    assert rgb.shape == (2, 2, 3)
    assert torch.allclose(rgb[0, 0], torch.tensor([1.0, 0.0, 0.0]))
    assert torch.allclose(rgb[0, 1], torch.ones(3))
    assert torch.allclose(rgb[1, 0], torch.zeros(3))
    assert torch.allclose(rgb[1, 1], torch.full((3,), 0.8))
    assert torch.equal(base_runs.white_composite(rgba[..., :3]), torch.from_numpy(rgba[..., :3] / np.float32(255)))
    a = torch.zeros(4, 4, 3)
    assert base_runs.psnr(a, a + 0.1) == pytest.approx(20.0)
    assert base_runs.psnr(a, a + 0.01) == pytest.approx(40.0)
    assert base_runs.psnr(a, a) == math.inf


def test_count_parameters_excludes_lpips():
    class Model(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.field = torch.nn.Linear(3, 4)  # 16
            self.lpips = torch.nn.Linear(100, 100)  # excluded
            self.head = torch.nn.Sequential(torch.nn.Linear(4, 2))  # 10
            self.register_buffer("aabb", torch.zeros(2, 3))  # not a parameter

    assert base_runs.count_parameters(Model()) == 26


@pytest.mark.slow  # starts subprocesses
def test_bench_rejects_bad_input_with_one_line(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "gsticker_plugin.bench.presets",
            "--data",
            str(empty),
            "--output",
            str(tmp_path / "p.md"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=_env(),
        cwd=REPO_ROOT,
    )
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: ") and "transforms_train.json" in last and "transforms.json" in last, last
    assert not (tmp_path / "p.md").exists()
    cfg = bench.BenchConfig(data=tmp_path, quick=True)
    assert cfg.iterations_for(3000) == 20 and cfg.test_views() == 3
    cfg = bench.BenchConfig(data=tmp_path, quick=True, max_num_iterations=7, num_test_views=5)
    assert cfg.iterations_for(3000) == 7 and cfg.test_views() == 5
    assert (
        bench.BenchConfig(data=tmp_path).iterations_for(3000) == 3000
        and bench.BenchConfig(data=tmp_path).test_views() == 25
    )


# ----------------------------------------------------------------------------- benchmark end to end


@pytest.mark.slow
def test_bench_quick_end_to_end(tiny_scene, tmp_path, monkeypatch):
    md = tmp_path / "docs" / "presets.md"
    args = [
        "--data",
        str(tiny_scene),
        "--presets",
        "gsticker-nerfacto-small",
        "--output",
        str(md),
        "--output-dir",
        str(tmp_path / "runs"),
        "--quick",
        "--threads",
        "1",
    ]
    proc = subprocess.run(
        [sys.executable, "-m", "gsticker_plugin.bench.presets", *args],
        capture_output=True,
        text=True,
        timeout=600,
        env=_env(),
        cwd=REPO_ROOT,
    )
    assert proc.returncode == 0, _tail(proc)
    assert "[bench-presets]" in proc.stdout and "test view 1/2" in proc.stdout  # progress on the terminal

    report = json.loads(md.with_suffix(".json").read_text())
    (result,) = report["results"]
    assert result["preset"] == "gsticker-nerfacto-small"
    assert result["iterations"] == 20
    assert result["test_views"] == 2 == result["test_views_available"] == len(result["test_psnr_per_view"])
    for key in ("train_seconds", "seconds_per_iteration", "test_psnr", "setup_seconds", "eval_seconds"):
        assert isinstance(result[key], float) and math.isfinite(result[key]) and result[key] > 0, key
    assert result["seconds_per_iteration"] == pytest.approx(result["train_seconds"] / 20)
    assert isinstance(result["parameters"], int) and 100_000 < result["parameters"] < 5_000_000
    assert report["machine"]["nproc"] >= 1 and report["machine"]["cpu"] and report["machine"]["torch"]
    assert report["machine"]["torch_threads"] == 1
    assert report["command"] == "python -m gsticker_plugin.bench.presets " + " ".join(args)
    checkpoint = Path(result["checkpoint"])
    assert checkpoint.name == "step-000000019.ckpt" and checkpoint.is_file()
    assert [p.name for p in checkpoint.parent.glob("*.ckpt")] == [checkpoint.name]  # only the latest is kept

    text = md.read_text()
    row = next(line for line in text.splitlines() if line.startswith("| `gsticker-nerfacto-small`"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == f"{result['parameters']:,}"
    assert float(cells[2]) == pytest.approx(result["seconds_per_iteration"], abs=1e-3)
    assert cells[3] == f"{result['test_psnr']:.2f} dB"
    assert cells[5] == "20"
    assert "| preset | parameters | s/iteration | test PSNR" in text
    assert report["command"] in text and "nproc" in text

    # The benchmark's PSNR agrees with the model's own metric on the same test view (same ground truth).
    monkeypatch.setenv("GSTICKER_NO_DOWNLOAD", "1")
    pipeline = base_runs.load_pipeline(Path(result["config"]), checkpoint, tiny_scene)
    dataset = pipeline.datamanager.eval_dataset
    assert Path(dataset._dataparser_outputs.image_filenames[0]).parent.name == "test"
    assert base_runs.count_parameters(pipeline.model) == result["parameters"]
    with torch.no_grad():
        outputs = pipeline.model.get_outputs_for_camera(dataset.cameras[0:1])
    metrics, _ = pipeline.model.get_image_metrics_and_images(outputs, dataset[0])
    assert metrics["psnr"] == pytest.approx(result["test_psnr_per_view"][0], abs=0.05)


@pytest.mark.slow
def test_bench_evaluate_reproduces_shared_nerfacto_psnr(monkeypatch):
    """On the shared lego100 base (README: 25.5 dB over the first 25 test views) two test views score > 20 dB."""
    base = SHARED / "checkpoints/lego100-nerfacto-small/nerfacto/base"
    data = SHARED / "data/lego100"
    if not (base / "config.yml").is_file() or not data.is_dir():
        pytest.skip("shared lego100 base is missing")
    monkeypatch.setenv("GSTICKER_NO_DOWNLOAD", "1")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        scored = base_runs.evaluate(base / "config.yml", base / "nerfstudio_models/step-000002999.ckpt", data, 2)
    finally:
        torch.set_num_threads(threads)
    assert scored["test_views"] == 2
    assert 20.0 < scored["test_psnr"] < 40.0, scored
    assert 500_000 < scored["parameters"] < 5_000_000


def test_final_rgb_takes_vanilla_nerfs_fine_image_and_names_the_fix_otherwise():
    from gsticker_plugin.errors import GStickerError
    from gsticker_plugin.runs import final_rgb

    a, b = torch.zeros(2, 2, 3), torch.ones(2, 2, 3)
    assert final_rgb({"rgb": a, "rgb_fine": b}) is a
    assert final_rgb({"rgb_coarse": a, "rgb_fine": b}) is b
    with pytest.raises(GStickerError, match="NeRF-style"):
        final_rgb({"depth": a})


def test_presets_train_on_the_cpu_when_there_is_no_cuda_device(monkeypatch):
    """A preset copied from the README must not stop on "Found no NVIDIA driver" on a CPU-only machine."""
    import torch

    from method_configs import geometrysticker, presets

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for make in (presets.nerfacto_small_config, presets.nerfacto_capture_config, presets.tensorf_small_config):
        assert make().machine.device_type == "cpu"
    assert geometrysticker.geometrysticker_config().machine.device_type == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert presets.nerfacto_small_config().machine.device_type == "cuda"
