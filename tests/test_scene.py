"""Tests for the demo-scene generator ``ns-gsticker-scene`` (gsticker_plugin/scene.py), on tiny scenes."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gsticker_plugin import scene
from gsticker_plugin.scene import SceneConfig

RES = 32
COUNTS = {"train": 3, "val": 2, "test": 2}
SPOT = Path("/work/shared/assets/spot")


def _config(out: Path, **kw) -> SceneConfig:
    base = dict(
        output_dir=out,
        resolution=RES,
        num_train=COUNTS["train"],
        num_val=COUNTS["val"],
        num_test=COUNTS["test"],
        seed=0,
    )
    base.update(kw)
    return SceneConfig(**base)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "gsticker_plugin.scene", *args], capture_output=True, text=True, timeout=120
    )


def _read(path: Path) -> np.ndarray:
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    assert not buf.has_error, buf.geterror()
    return np.asarray(buf.get_pixels(oiio.UINT8 if path.suffix == ".png" else oiio.FLOAT))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scene") / "demo"
    assert scene.main(_config(out), progress=False) == 0
    return out


# ----------------------------------------------------------------------------- pure functions


def test_camera_poses_look_at_origin_from_upper_hemisphere():
    poses = scene.sample_camera_poses(64, np.random.default_rng(3))
    assert poses.shape == (64, 4, 4)
    rot, pos = poses[:, :3, :3], poses[:, :3, 3]
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(rot), 1.0)
    assert np.allclose(np.linalg.norm(pos, axis=1), scene.CAMERA_RADIUS)
    assert (pos[:, 2] > 0).all()
    forward = -rot[:, :, 2]  # OpenGL cameras look down -z
    assert np.allclose(forward, -pos / np.linalg.norm(pos, axis=1, keepdims=True))
    assert (rot[:, 2, 1] > 0).all()  # image up points towards world +z


def test_split_poses_seeded_and_independent():
    a = scene.split_poses(0, {"train": 4, "val": 2, "test": 2})
    b = scene.split_poses(0, {"train": 9, "val": 2, "test": 2})
    c = scene.split_poses(1, {"train": 4, "val": 2, "test": 2})
    assert np.array_equal(a["val"], b["val"]) and np.array_equal(a["train"], b["train"][:4])
    assert not np.allclose(a["train"], c["train"])


def test_render_matches_pinhole_projection():
    """A small ball at a known point appears where Nerfstudio's pinhole camera model puts it."""
    import trimesh

    ball = trimesh.creation.icosphere(3, radius=0.08)
    ball.apply_translation((0.7, -0.4, 0.5))
    part = scene.Part(np.asarray(ball.vertices), np.asarray(ball.faces), color=(1.0, 1.0, 1.0))
    c2w = scene.look_at(np.array([1.5, -3.0, 2.4]))
    plotter = scene.make_plotter([part], 96)
    try:
        rgba, depth = scene.render_view(plotter, c2w, 48, 2)
    finally:
        plotter.close()
    focal = 0.5 * 48 / math.tan(0.5 * scene.CAMERA_ANGLE_X)
    p_cam = c2w[:3, :3].T @ (np.array([0.7, -0.4, 0.5]) - c2w[:3, 3])
    u, v = 24 + focal * p_cam[0] / -p_cam[2], 24 - focal * p_cam[1] / -p_cam[2]
    alpha = rgba[..., 3].astype(float)
    ys, xs = np.mgrid[:48, :48] + 0.5
    cu, cv = (alpha * xs).sum() / alpha.sum(), (alpha * ys).sum() / alpha.sum()
    assert abs(cu - u) < 0.5 and abs(cv - v) < 0.5
    assert abs(depth[int(v), int(u)] - (-p_cam[2] - 0.08)) < 0.03


# ----------------------------------------------------------------------------- the dataset


def test_dataset_format(dataset: Path):
    assert sorted(p.name for p in dataset.iterdir()) == sorted([*COUNTS, *(f"transforms_{s}.json" for s in COUNTS)])
    for split, n in COUNTS.items():
        meta = json.loads((dataset / f"transforms_{split}.json").read_text())
        assert meta["camera_angle_x"] == pytest.approx(scene.CAMERA_ANGLE_X)
        assert len(meta["frames"]) == n
        for i, frame in enumerate(meta["frames"]):
            assert frame["file_path"] == f"./{split}/r_{i}"
            assert isinstance(frame["rotation"], float)
            assert np.asarray(frame["transform_matrix"]).shape == (4, 4)
            rgba = _read(dataset / f"{split}/r_{i}.png")
            assert rgba.shape == (RES, RES, 4) and rgba.dtype == np.uint8
            alpha = rgba[..., 3]
            assert (alpha == 0).any() and (alpha == 255).any()
            assert (rgba[..., :3][alpha == 0] == 0).all()
        assert sorted(p.name for p in (dataset / split).iterdir()) == sorted(
            [f"r_{i}.png" for i in range(n)] + [f"r_{i}_depth.exr" for i in range(n)]
        )


def test_depth_present_and_sane(dataset: Path):
    meta = json.loads((dataset / "transforms_train.json").read_text())
    for frame in meta["frames"]:
        alpha = _read(dataset / (frame["file_path"] + ".png"))[..., 3]
        depth = _read(dataset / frame["depth_file_path"])
        assert depth.shape == (RES, RES, 1)
        depth = depth[..., 0]
        assert np.isfinite(depth).all()
        assert (depth[alpha == 0] == 0).all()
        d = depth[alpha > 0]
        assert (d > meta["near"]).all() and (d < meta["far"]).all()
        # fully covered pixels back-project into the scene's bounds
        c2w = np.asarray(frame["transform_matrix"])
        focal = 0.5 * RES / math.tan(0.5 * meta["camera_angle_x"])
        ys, xs = np.nonzero(alpha == 255)
        dirs = np.stack([(xs + 0.5 - RES / 2) / focal, -(ys + 0.5 - RES / 2) / focal, -np.ones(len(xs))], -1)
        world = (dirs * depth[ys, xs][:, None]) @ c2w[:3, :3].T + c2w[:3, 3]
        assert np.abs(world).max() < 1.5 and np.linalg.norm(world, axis=1).max() < scene.SCENE_RADIUS + 0.05


def test_at_least_three_distinct_dominant_colors(dataset: Path):
    from skimage.color import rgb2hsv

    pixels = np.concatenate([_read(p).reshape(-1, 4) for p in sorted((dataset / "train").glob("*.png"))])
    opaque = pixels[pixels[:, 3] == 255, :3]
    hsv = rgb2hsv(opaque[None].astype(np.float64) / 255)[0]
    vivid = hsv[(hsv[:, 1] > 0.5) & (hsv[:, 2] > 0.2), 0] * 360
    bins = {
        "red": (vivid < 15) | (vivid > 345),
        "green": (vivid > 90) & (vivid < 150),
        "blue": (vivid > 210) & (vivid < 250),
    }
    for name, mask in bins.items():
        assert mask.sum() > 0.02 * len(opaque), f"{name} is not a dominant color: {mask.sum()} of {len(opaque)}"


def test_loads_with_nerfstudio_blender_dataparser(dataset: Path):
    from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig

    parser = BlenderDataParserConfig(data=dataset).setup()
    for split, n in COUNTS.items():
        outputs = parser.get_dataparser_outputs(split)
        assert len(outputs.image_filenames) == n
        assert int(outputs.cameras.width[0]) == RES and int(outputs.cameras.height[0]) == RES
        assert outputs.cameras.camera_to_worlds.shape == (n, 3, 4)


def test_deterministic_for_a_seed_across_processes(dataset: Path, tmp_path: Path):
    args = ["--resolution", str(RES), "--num-train", "3", "--num-val", "2", "--num-test", "2"]
    same = _cli("--output-dir", str(tmp_path / "same"), "--seed", "0", *args)
    assert same.returncode == 0, same.stderr
    for path in sorted(dataset.rglob("*")):
        if path.is_file():
            assert (tmp_path / "same" / path.relative_to(dataset)).read_bytes() == path.read_bytes(), path
    assert scene.main(_config(tmp_path / "other", seed=1), progress=False) == 0
    assert (tmp_path / "other/train/r_0.png").read_bytes() != (dataset / "train/r_0.png").read_bytes()


# ----------------------------------------------------------------------------- custom meshes


@pytest.mark.skipif(not SPOT.is_dir(), reason=f"{SPOT} (the Spot cow test mesh) is not present")
@pytest.mark.parametrize("layout", ["folder", "obj_with_mtl"])
def test_custom_textured_mesh(tmp_path: Path, layout: str):
    if layout == "folder":
        mesh = SPOT
    else:
        mesh = tmp_path / "cow" / "cow.obj"
        mesh.parent.mkdir()
        shutil.copy(SPOT / "spot_texture.png", mesh.parent / "skin.png")
        (mesh.parent / "cow.mtl").write_text("newmtl skin\nKd 1 1 1\nmap_Kd skin.png\n")
        mesh.write_text("mtllib cow.mtl\nusemtl skin\n" + (SPOT / "spot_triangulated.obj").read_text())
    out = tmp_path / "out"
    assert scene.main(_config(out, num_train=2, num_val=1, num_test=1, mesh=mesh), progress=False) == 0
    rgba = np.concatenate([_read(p).reshape(-1, 4) for p in (out / "train").glob("*.png")])
    rgb = rgba[rgba[:, 3] == 255, :3].astype(int)
    # Spot's texture: white hide with black patches (an untextured render would be uniform gray)
    assert (rgb.min(axis=1) > 170).mean() > 0.1 and (rgb.max(axis=1) < 60).mean() > 0.02
    assert json.loads((out / "transforms_train.json").read_text())["scene"] == str(mesh)


# ----------------------------------------------------------------------------- bad input


def _bad_inputs(tmp: Path):
    (tmp / "garbage.obj").write_text("this is not\nan obj file\n")
    (tmp / "broken.ply").write_bytes(b"\x00\x01not a ply at all" * 8)
    tex = tmp / "badtex"
    tex.mkdir()
    (tex / "m.obj").write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    (tex / "m.mtl").write_text("newmtl a\nmap_Kd m.png\n")
    (tex / "m.png").write_bytes(b"not a png")
    (tmp / "existing").mkdir()
    (tmp / "afile").write_text("x")
    tiny = ["--resolution", "16", "--num-train", "1", "--num-val", "1", "--num-test", "1"]
    return {
        "missing mesh": (["--mesh", str(tmp / "nope.obj"), *tiny], "does not exist"),
        "garbage mesh": (["--mesh", str(tmp / "garbage.obj"), *tiny], "garbage.obj"),
        "broken mesh": (["--mesh", str(tmp / "broken.ply"), *tiny], "broken.ply"),
        "unreadable texture": (["--mesh", str(tex), *tiny], "m.png cannot be read"),
        "zero views": (["--num-train", "0"], "--num-train"),
        "unwritable output": (["--output-dir", str(tmp / "afile" / "out"), *tiny], "writable"),
        "existing output": (["--output-dir", str(tmp / "existing"), *tiny], "--overwrite"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "missing mesh",
        "garbage mesh",
        "broken mesh",
        "unreadable texture",
        "zero views",
        "unwritable output",
        "existing output",
    ],
)
def test_bad_input_exits_2_with_one_line_and_no_partial_output(tmp_path: Path, case: str):
    args, needle = _bad_inputs(tmp_path)[case]
    work = tmp_path / "work"
    work.mkdir()
    if "--output-dir" not in args:
        args = ["--output-dir", str(work / "nested" / "out"), *args]
    before = sorted(tmp_path.rglob("*"))
    result = _cli(*args)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], result.stderr
    assert sorted(tmp_path.rglob("*")) == before  # nothing left behind, not even the parent folders


def test_overwrite_replaces_a_dataset_but_not_other_folders(tmp_path: Path):
    out = tmp_path / "out"
    assert scene.main(_config(out, num_train=1, num_val=1, num_test=1), progress=False) == 0
    assert scene.main(_config(out, num_train=2, num_val=1, num_test=1, overwrite=True), progress=False) == 0
    assert len(json.loads((out / "transforms_train.json").read_text())["frames"]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "thesis.tex").write_text("keep me")
    assert scene.main(_config(precious, overwrite=True), progress=False) == 2
    assert (precious / "thesis.tex").read_text() == "keep me"


def test_interrupt_leaves_no_partial_dataset(tmp_path: Path, monkeypatch, capsys):
    calls = []

    def interrupted(path, rgba):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(scene, "write_png", interrupted)
    assert scene.main(_config(tmp_path / "a" / "out"), progress=False) == 130
    assert list(tmp_path.iterdir()) == []
    assert capsys.readouterr().err.count("\n") == 1


def test_help_lists_flags():
    result = _cli("--help")
    assert result.returncode == 0
    for flag in (
        "--output-dir",
        "--resolution",
        "--num-train",
        "--num-val",
        "--num-test",
        "--seed",
        "--mesh",
        "--overwrite",
    ):
        assert flag in result.stdout
