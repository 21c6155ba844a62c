"""Forward-facing captures in the nerfstudio-data format: the generated capture layout, novel cameras that stay
within the captured trajectory, transforms files mapped to a run's coordinates as its dataparser maps them, and a
stock-style nerfacto run of the generated capture watermarked and verified from the model and from ``ns-render``
images at the capture's own ``transforms.json`` cameras."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Dict

import numpy as np
import pytest
import torch
from conftest import CPU_ARGS, STICKER_SEED_ARGS, TINY_MESSAGE, console_script, run_parallel, subprocess_env
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

from gsticker_plugin import cameras as C
from gsticker_plugin import fastpath as F
from gsticker_plugin import scene
from gsticker_plugin.verify import cli as V


def _cameras(c2w: np.ndarray) -> Cameras:
    n = c2w.shape[0]
    return Cameras(
        camera_to_worlds=torch.tensor(c2w[:, :3], dtype=torch.float32),
        fx=torch.full((n, 1), 40.0),
        fy=torch.full((n, 1), 40.0),
        cx=torch.full((n, 1), 16.0),
        cy=torch.full((n, 1), 16.0),
        width=torch.full((n, 1), 32),
        height=torch.full((n, 1), 32),
        camera_type=CameraType.PERSPECTIVE,
    )


def _forward(c2w: torch.Tensor) -> torch.Tensor:
    f = -c2w[:, :3, 2]
    return f / f.norm(dim=-1, keepdim=True)


def test_capture_poses_face_the_scene_from_one_side_and_are_told_apart_from_an_orbit():
    poses = scene.sample_capture_poses(40, np.random.default_rng(0))
    lo = np.asarray(scene.CAPTURE_CENTER) - np.asarray(scene.CAPTURE_SPREAD)
    hi = np.asarray(scene.CAPTURE_CENTER) + np.asarray(scene.CAPTURE_SPREAD)
    assert ((poses[:, :3, 3] >= lo) & (poses[:, :3, 3] <= hi)).all()
    to_origin = -poses[:, :3, 3] / np.linalg.norm(poses[:, :3, 3], axis=1, keepdims=True)
    assert (np.einsum("ni,ni->n", -poses[:, :3, 2], to_origin) > 0.95).all()  # each looks at the scene
    assert F.camera_layout(_cameras(poses)) == "capture"
    assert F.camera_layout(_cameras(scene.sample_camera_poses(40, np.random.default_rng(0)))) == "orbit"


def test_novel_cameras_stay_within_a_capture_and_keep_orbits_as_they_were():
    train = _cameras(scene.sample_capture_poses(12, np.random.default_rng(1)))
    novel = F.novel_cameras(train, 64, torch.Generator().manual_seed(0))
    pos, tpos = novel.camera_to_worlds[:, :, 3], train.camera_to_worlds[:, :, 3]
    extent = float((tpos.amax(0) - tpos.amin(0)).norm())
    assert bool((pos >= tpos.amin(0) - 0.1 * extent - 1e-5).all() and (pos <= tpos.amax(0) + 0.1 * extent + 1e-5).all())
    # every novel camera looks within a few degrees of the captured directions' span
    cos = (_forward(novel.camera_to_worlds) @ _forward(train.camera_to_worlds).T).amax(dim=1)
    spread = float(
        torch.rad2deg(torch.acos((_forward(train.camera_to_worlds) @ _forward(train.camera_to_worlds).T).min()))
    )
    assert float(torch.rad2deg(torch.acos(cos.clamp(max=1.0))).max()) < spread + 5.0 + 1e-3
    r = novel.camera_to_worlds[:, :, :3]
    assert torch.allclose(r.transpose(1, 2) @ r, torch.eye(3).expand(64, 3, 3), atol=1e-5)  # rotations
    orbit = _cameras(scene.sample_camera_poses(12, np.random.default_rng(1)))
    a = F.novel_cameras(orbit, 8, torch.Generator().manual_seed(3))
    b = F.orbit_cameras(orbit, 8, torch.Generator().manual_seed(3))
    assert torch.equal(a.camera_to_worlds, b.camera_to_worlds)


def test_transforms_file_maps_to_run_coordinates_as_nerfstudio_data_does(tmp_path: Path):
    """A nerfstudio-data transforms file (with the applied transform and scale ns-process-data writes) read by
    ``--cameras`` lands exactly on the cameras the run's dataparser made of it: orientation, centering, scale."""
    from PIL import Image

    rng = np.random.default_rng(4)
    poses = scene.sample_capture_poses(6, rng)
    (tmp_path / "images").mkdir()
    frames = []
    for i, c2w in enumerate(poses):
        Image.fromarray(np.zeros((24, 32, 3), np.uint8)).save(tmp_path / "images" / f"f_{i}.png")
        frames.append({"file_path": f"images/f_{i}.png", "transform_matrix": c2w.tolist()})
    meta = {
        "fl_x": 30.0,
        "fl_y": 30.0,
        "cx": 16.0,
        "cy": 12.0,
        "w": 32,
        "h": 24,
        "applied_transform": [[0.0, 1.0, 0.0, 0.3], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, -1.0, 0.1]],
        "applied_scale": 0.5,
        "frames": frames,
    }
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    outputs = NerfstudioDataParserConfig(data=tmp_path, eval_mode="all").setup().get_dataparser_outputs("train")
    pose_map = C.PoseMap(outputs.dataparser_transform, float(outputs.dataparser_scale))
    read = C.read_cameras_file(tmp_path / "transforms.json")
    for i in range(6):
        cam = C.camera_for_image(read[f"images/f_{i}"], 24, 32, pose_map)
        assert torch.allclose(cam.camera_to_worlds[0], outputs.cameras.camera_to_worlds[i], atol=1e-5), i
        assert math.isclose(float(cam.fx), float(outputs.cameras.fx[i]), rel_tol=1e-6)


# ---------------------------------------------------------------------------------------------- end to end

BASE_STEPS = 150


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Dict[str, Path]:
    """A 32 px generated capture, a stock-defaults nerfacto base on it (nerfstudio-data, scene contraction, proposal
    sampler, ``last_sample`` background; fewer samples and a smaller hash grid), a geometrysticker run and its
    test views rendered by ``ns-render dataset`` as PNGs."""
    ws = tmp_path_factory.mktemp("capture")
    data = ws / "scene"
    proc = subprocess.run(
        [sys.executable, "-m", "gsticker_plugin.scene", "--layout", "capture", "--output-dir", str(data)]
        + ["--resolution", "32", "--num-train", "12", "--num-val", "2", "--num-test", "2"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    train = str(console_script("ns-train"))
    base = [
        train,
        "nerfacto",
        *CPU_ARGS,
        "--output-dir",
        str(ws),
        "--experiment-name",
        "cap",
        "--timestamp",
        "base",
        "--max-num-iterations",
        str(BASE_STEPS),
        "--steps-per-save",
        str(BASE_STEPS),
        "--pipeline.model.implementation",
        "torch",
        "--pipeline.model.log2-hashmap-size",
        "15",
        "--pipeline.model.num-nerf-samples-per-ray",
        "24",
        "--pipeline.model.num-proposal-samples-per-ray",
        "48",
        "24",
        "--pipeline.datamanager.train-num-rays-per-batch",
        "512",
        "--data",
        str(data),
    ]
    (proc,) = run_parallel([base], ws / "logs-base")
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    base_dir = ws / "cap" / "nerfacto" / "base"
    key = ws / "keys" / "cap.gskey"
    sticker = [
        train,
        "geometrysticker",
        "--pipeline.mark",
        "sticker",
        "--load-checkpoint",
        str(max((base_dir / "nerfstudio_models").glob("step-*.ckpt"))),
        *CPU_ARGS,
        "--output-dir",
        str(ws),
        "--experiment-name",
        "cap",
        "--timestamp",
        "wm",
        *STICKER_SEED_ARGS,
        "--max-num-iterations",
        "80",
        "--pipeline.pool-train-views",
        "4",
        "--pipeline.pool-novel-views",
        "4",
        "--pipeline.monitor-views",
        "1",
        "--pipeline.steps-per-monitor",
        "20",
        "--pipeline.key-path",
        str(key),
        # one fixed message: a regression test of the pipeline (the spread over random messages is benchmarked)
        "--pipeline.message",
        TINY_MESSAGE,
    ]
    (proc,) = run_parallel([sticker], ws / "logs-wm")
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    run = ws / "cap" / "geometrysticker" / "wm" / "config.yml"
    render = [str(console_script("ns-render")), "dataset", "--load-config", str(run), "--split", "test"]
    render += ["--output-path", str(ws / "renders"), "--rendered-output-names", "rgb", "--image-format", "png"]
    proc = subprocess.run(render, capture_output=True, text=True, timeout=600, env=subprocess_env())
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return {
        "data": data,
        "base": base_dir / "config.yml",
        "run": run,
        "key": key,
        "renders": ws / "renders" / "test" / "rgb",
        "ws": ws,
        "sticker_log": ws / "logs-wm" / "cmd0.stdout",
    }


def _verify(capsys, out: Path, *argv: str):
    status = V.main([*argv, "--output", str(out), "--no-progress"])
    stdout = capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())
    return status, stdout, rep


@pytest.mark.slow
def test_sticker_pool_draws_novel_views_inside_the_capture(capture):
    log = capture["sticker_log"].read_text()
    assert "novel views (capture layout) see the scene in" in log, log[-2000:]


@pytest.mark.slow
def test_capture_run_is_owned_from_the_model_its_palette_recolor_and_ns_render_images_at_its_cameras(capture, capsys):
    """Stock nerfacto defaults (nerfstudio-data, contraction, proposal sampler, last_sample) end to end."""
    ws = capture["ws"]
    status, stdout, rep = _verify(
        capsys, ws / "rep-model", "--load-config", str(capture["run"]), "--key", str(capture["key"]), "--num-views", "4"
    )
    assert status == 0 and stdout.startswith("VERDICT: OWNED"), stdout[-2000:]
    status, stdout, rep = _verify(
        capsys,
        ws / "rep-images",
        "--images",
        str(capture["renders"]),
        "--cameras",
        str(capture["data"] / "transforms.json"),
        "--key",
        str(capture["key"]),
    )
    assert rep["decoder"]["kind"] == "image" and len(rep["keys"][0]["per_view"]) == 2, stdout[-2000:]
    assert status == 0 and stdout.startswith("VERDICT: OWNED"), stdout[-2000:]
    from gsticker_plugin.recolor import cli as recolor

    dest = ws / "recolored"
    assert (
        recolor.run(["palette", "--set", "0=blue", "--load-config", str(capture["run"]), "--output-dir", str(dest)])
        == 0
    )
    (recolored,) = dest.glob("**/config.yml")
    capsys.readouterr()
    status, stdout, rep = _verify(
        capsys, ws / "rep-recolored", "--load-config", str(recolored), "--key", str(capture["key"]), "--num-views", "4"
    )
    assert status == 0 and stdout.startswith("VERDICT: OWNED"), stdout[-2000:]
    status, stdout, rep = _verify(
        capsys, ws / "rep-base", "--load-config", str(capture["base"]), "--key", str(capture["key"]), "--num-views", "4"
    )
    assert status == 1 and stdout.startswith("VERDICT: NOT SHOWN"), stdout[-2000:]


@pytest.mark.slow
def test_the_default_field_mark_of_a_capture_base_is_owned_from_the_model_and_its_recolor_and_not_from_the_base(
    capture, capsys
):
    """The default shared run of a stock-defaults nerfacto capture (contraction, proposal sampler, last_sample): a
    stock nerfacto run whose hash table carries the message."""
    ws = capture["ws"]
    key = ws / "keys" / "field.gskey"
    argv = [str(console_script("ns-train")), "geometrysticker", "--load-checkpoint"]
    argv += [str(max((capture["base"].parent / "nerfstudio_models").glob("step-*.ckpt"))), *CPU_ARGS]
    argv += [
        "--output-dir",
        str(ws),
        "--experiment-name",
        "cap",
        "--timestamp",
        "field",
        "--pipeline.key-path",
        str(key),
    ]
    (proc,) = run_parallel([argv], ws / "logs-field")
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    shared = ws / "cap" / "nerfacto" / "field" / "config.yml"
    capsys.readouterr()  # run_parallel's timing line
    views = ("--num-views", "4")
    status, stdout, rep = _verify(capsys, ws / "rep-field", "--load-config", str(shared), "--key", str(key), *views)
    assert status == 0 and stdout.startswith("VERDICT: OWNED"), stdout[-2000:]
    assert min(v["matches"] for v in rep["keys"][0]["per_view"][:2]) >= 41  # the run's own cameras
    from gsticker_plugin.recolor import cli as recolor

    dest = ws / "recolored-field"
    assert recolor.run(["hue", "--shift", "0.25", "--load-config", str(shared), "--output-dir", str(dest)]) == 0
    (recolored,) = dest.glob("**/config.yml")
    capsys.readouterr()
    status, stdout, _ = _verify(
        capsys, ws / "rep-field-hue", "--load-config", str(recolored), "--key", str(key), *views
    )
    assert status == 0 and stdout.startswith("VERDICT: OWNED"), stdout[-2000:]
    base = str(capture["base"])
    status, stdout, _ = _verify(capsys, ws / "rep-field-base", "--load-config", base, "--key", str(key), *views)
    assert status == 1 and stdout.startswith("VERDICT: NOT SHOWN"), stdout[-2000:]
