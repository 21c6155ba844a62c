"""LLFF captures as nerfstudio-data (gsticker_plugin/llff.py): the camera convention, the intrinsics at the images'
size, the split, and one-line errors."""

import json

import numpy as np
import pytest
from PIL import Image

from gsticker_plugin.errors import GStickerError
from gsticker_plugin.llff import LLFFConfig, llff_to_opengl, main


def _row(down, right, back, t, hwf=(3024.0, 4032.0, 3260.0)):
    m = np.stack(
        [np.asarray(down, float), np.asarray(right, float), np.asarray(back, float), np.asarray(t, float), hwf], 1
    )
    return np.concatenate([m.reshape(-1), [1.0, 10.0]])


def test_an_llff_camera_looking_down_minus_z_is_the_opengl_identity():
    c2w = llff_to_opengl(_row([0, -1, 0], [1, 0, 0], [0, 0, 1], [0.5, -1, 5])[None])[0]
    assert np.allclose(c2w[:3, :3], np.eye(3)) and np.allclose(c2w[:3, 3], [0.5, -1, 5])


def test_the_conversion_keeps_every_rotation_proper_and_maps_axes_as_opengl_wants():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))  # a proper rotation: columns right, up, back of an OpenGL camera
    right, up, back = q[:, 0], q[:, 1], q[:, 2]
    c2w = llff_to_opengl(_row(-up, right, back, [1, 2, 3])[None])[0]
    assert np.allclose(c2w[:3, :3], q) and np.isclose(np.linalg.det(c2w[:3, :3]), 1.0)


def _capture(tmp_path, n=5, size=(40, 30)):
    (tmp_path / "images_8").mkdir()
    for i in range(n):
        Image.new("RGB", size, (i * 40, 0, 0)).save(tmp_path / "images_8" / f"IMG_{i:04d}.png")
    rows = [_row([0, -1, 0], [1, 0, 0], [0, 0, 1], [i, 0, 5], hwf=(300.0, 400.0, 350.0)) for i in range(n)]
    np.save(tmp_path / "poses_bounds.npy", np.stack(rows))
    return tmp_path


def test_transforms_hold_intrinsics_at_the_image_size_and_a_held_out_split(tmp_path):
    assert main(LLFFConfig(input=_capture(tmp_path), every_test=2)) == 0
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert (meta["w"], meta["h"]) == (40, 30) and meta["fl_x"] == pytest.approx(350.0 * 40 / 400)
    assert [f["file_path"] for f in meta["frames"]] == [f"images_8/IMG_{i:04d}.png" for i in range(5)]
    assert meta["test_filenames"] == ["images_8/IMG_0000.png", "images_8/IMG_0002.png", "images_8/IMG_0004.png"]
    assert set(meta["train_filenames"]) == {"images_8/IMG_0001.png", "images_8/IMG_0003.png"}
    assert meta["frames"][3]["transform_matrix"][0][3] == 3


def test_resized_copies_carry_their_own_intrinsics(tmp_path):
    main(LLFFConfig(input=_capture(tmp_path), resolution=20))
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert (meta["w"], meta["h"]) == (20, 15) and meta["fl_x"] == pytest.approx(350.0 * 20 / 400)
    assert Image.open(tmp_path / meta["frames"][0]["file_path"]).size == (20, 15)


def test_a_capture_whose_images_do_not_match_its_poses_is_refused_in_one_line(tmp_path):
    _capture(tmp_path)
    (tmp_path / "images_8" / "IMG_0000.png").unlink()
    with pytest.raises(GStickerError, match="4 images for 5 poses"):
        main(LLFFConfig(input=tmp_path))
    with pytest.raises(GStickerError, match="no poses_bounds.npy"):
        main(LLFFConfig(input=tmp_path / "images_8"))
