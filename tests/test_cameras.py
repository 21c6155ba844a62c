"""Cameras of suspect images (gsticker_plugin/cameras.py): transforms files read into frames, images matched to
frames, frames as cameras at the image size."""

import json

import pytest
import torch

from gsticker_plugin import cameras as I
from gsticker_plugin.errors import GStickerError


def test_cameras_file_frames_names_and_intrinsics_at_the_image_size(tmp_path):
    """--cameras: frames named by file_path without ./ and extension, images matched by name (or by a unique last
    component), Blender's camera_angle_x and nerfstudio's fl_x/w/h scaled to the image's size, one-line errors."""
    import math

    c2w = [[1, 0, 0, 0.5], [0, 1, 0, -1], [0, 0, 1, 4], [0, 0, 0, 1]]
    path = tmp_path / "transforms.json"
    path.write_text(
        json.dumps(
            {
                "camera_angle_x": 0.6,
                "frames": [
                    {"file_path": "./test/r_0", "transform_matrix": c2w},
                    {"file_path": "./train/r_0.png", "transform_matrix": c2w},
                    {
                        "file_path": "shots/a.jpg",
                        "transform_matrix": c2w[:3],
                        "fl_x": 100.0,
                        "fl_y": 90.0,
                        "cx": 40.0,
                        "cy": 30.0,
                        "w": 80,
                        "h": 60,
                    },
                ],
            }
        )
    )
    frames = I.read_cameras_file(path)
    assert sorted(frames) == ["shots/a", "test/r_0", "train/r_0"]
    assert I.match_frame("test/r_0.png", frames) == "test/r_0" and I.match_frame("a.PNG", frames) == "shots/a"
    assert I.match_frame("r_0.png", frames) is None  # two frames end in r_0: ambiguous, not guessed
    assert I.frame_name("./x/y.z.png") == "x/y.z"
    cam = I.camera_for_image(frames["test/r_0"], 50, 100, I.PoseMap(torch.eye(4)[:3], 2.0))
    assert math.isclose(float(cam.fx), 0.5 * 100 / math.tan(0.3), rel_tol=1e-6) and float(cam.fy) == float(cam.fx)
    assert (float(cam.cx), float(cam.cy), int(cam.width), int(cam.height)) == (50.0, 25.0, 100, 50)
    assert torch.allclose(cam.camera_to_worlds[0, :, 3], torch.tensor([1.0, -2.0, 8.0]))  # translation scaled
    cam = I.camera_for_image(frames["shots/a"], 30, 40)  # half the w, h the intrinsics refer to
    assert [float(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy)] == [50.0, 45.0, 20.0, 15.0]
    with pytest.raises(GStickerError, match="aspect ratio"):
        I.camera_for_image(frames["shots/a"], 40, 40)
    for text, msg in (
        ("not json", "not readable JSON"),
        (json.dumps({"frames": []}), "no 'frames' list"),
        (json.dumps({"frames": [{"file_path": "a", "transform_matrix": c2w}]}), "no intrinsics"),
        (
            json.dumps({"camera_angle_x": 1, "frames": [{"file_path": "a", "transform_matrix": [[1]]}]}),
            "4x4 camera-to-world",
        ),
        (json.dumps({"frames": [{"file_path": "a", "transform_matrix": c2w, "fl_x": 9}]}), "w, h"),
    ):
        path.write_text(text)
        with pytest.raises(GStickerError, match=msg):
            I.read_cameras_file(path)
    with pytest.raises(GStickerError, match="does not exist"):
        I.read_cameras_file(tmp_path / "missing.json")
