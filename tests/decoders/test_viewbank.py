"""The owner's view bank (decoders/viewbank.py): the camera search's base renders kept beside the key and reused,
rendered again when the base changes; and the search's renders depending only on a picture's aspect ratio."""

from __future__ import annotations

from pathlib import Path

import torch
from test_pose import CountingSquare, TexturedSquare, orbit, reference

from gsticker_plugin.decoders import pose as P
from gsticker_plugin.decoders import viewbank as VB


def banked_reference(tmp_path: Path, model=None):
    """The analytic scene's reference with a checkpoint and a config file to name its bank by."""
    ref = reference(orbit(12))
    ref.model = model or CountingSquare()
    ref.checkpoint = tmp_path / "step-000000099.ckpt"
    ref.config_path = tmp_path / "config.yml"
    if not ref.checkpoint.exists():
        ref.checkpoint.write_bytes(b"the base's weights")
        ref.config_path.write_text("method_name: nerfacto\n")
    return ref


def test_a_second_search_reads_the_bank_and_renders_nothing(tmp_path):
    ref = banked_reference(tmp_path)
    search = P.PoseSearch(candidates=20)
    bank = VB.bank_folder(tmp_path / "owner.gskey")
    cands, rows = P.search_renders(ref, search, (48, 48), True, bank=bank)
    assert ref.model.renders > 0 and len(list(bank.glob("*.pt"))) == 1
    ref.model.renders = 0
    cands2, rows2 = P.search_renders(ref, search, (48, 48), True, bank=bank)
    assert ref.model.renders == 0
    assert torch.equal(rows, rows2) and torch.equal(cands.camera_to_worlds, cands2.camera_to_worlds)
    # the bank holds RGB: the search of RGB pictures reads it too
    _, rgb_rows = P.search_renders(ref, search, (48, 48), False, bank=bank)
    assert ref.model.renders == 0 and rgb_rows.shape[1] == 3 * rows.shape[1]


def test_a_changed_base_or_other_search_settings_are_rendered_again(tmp_path):
    ref = banked_reference(tmp_path)
    bank = tmp_path / "bank"
    P.search_renders(ref, P.PoseSearch(candidates=20), (48, 48), True, bank=bank)
    for change in ("checkpoint", "candidates", "aspect"):
        ref.model.renders = 0
        search, hw = P.PoseSearch(candidates=20), (48, 48)
        if change == "checkpoint":
            ref.checkpoint.write_bytes(b"the base trained further")
        elif change == "candidates":
            search = P.PoseSearch(candidates=21)
        else:
            hw = (48, 64)
        P.search_renders(ref, search, hw, True, bank=bank)
        assert ref.model.renders > 0, change
    assert len(list(bank.glob("*.pt"))) == 4


def test_a_damaged_or_misshapen_bank_file_is_rendered_again(tmp_path):
    ref = banked_reference(tmp_path)
    search = P.PoseSearch(candidates=20)
    bank = tmp_path / "bank"
    _, rows = P.search_renders(ref, search, (48, 48), True, bank=bank)
    (path,) = bank.glob("*.pt")
    for damage in (b"not a tensor file", None):
        if damage is None:
            torch.save(torch.zeros(3, 16, 16, 3), path)
        else:
            path.write_bytes(damage)
        ref.model.renders = 0
        _, again = P.search_renders(ref, search, (48, 48), True, bank=bank)
        assert ref.model.renders > 0 and torch.allclose(again, rows)


def test_a_bank_folder_that_cannot_be_written_leaves_the_search_rendering(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert not VB.save_bank(blocker / "bank" / "x.pt", torch.zeros(1, 2, 2, 3))
    ref = banked_reference(tmp_path)
    _, rows = P.search_renders(ref, P.PoseSearch(candidates=5), (48, 48), True, bank=blocker / "bank")
    assert rows.shape[0] == len(orbit(12)) + 5


def test_pictures_of_another_size_and_the_same_aspect_are_searched_with_the_same_renders():
    """The candidates' intrinsics are scaled to the search frame from the base's own size: a picture at twice the
    base's size is scored against the same small renders as one at its size."""
    ref = reference(orbit(12))
    search = P.PoseSearch(candidates=10)
    _, at_base = P.search_renders(ref, search, (48, 48), False)
    _, twice = P.search_renders(ref, search, (96, 96), False)
    assert torch.allclose(at_base, twice)


def test_the_camera_of_a_picture_at_twice_the_base_size_is_found():
    train = orbit(24)
    held = P.novel_cameras(train, 1, torch.Generator().manual_seed(5))
    image = P.render_cameras(TexturedSquare(), P.scaled_camera(held, 96, 96))["rgb"][0]
    fit = P.estimate_camera(reference(train), image, False, P.PoseSearch(candidates=60, keep=2))
    a, b = held.camera_to_worlds[0], fit.camera.camera_to_worlds[0]
    assert float((a[:, 3] - b[:, 3]).norm()) < 1e-3 and fit.rms < 1e-3, fit.history
