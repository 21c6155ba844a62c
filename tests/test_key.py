"""Owner key: numpy values in the training state (optimizer lr etc.) are stored as plain Python values, so a key
loads with torch's weights_only loader without any allow-list, in a fresh process."""

import subprocess
import sys

import numpy as np
import torch
from conftest import field_mark_key

from gsticker_plugin.heads import HeadConfig, Heads
from gsticker_plugin.key import OwnerKey, message_from_owner_id


def test_key_with_numpy_state_loads_without_allow_list(tmp_path):
    heads = Heads(HeadConfig(width=8, depth=2), 48)
    key = OwnerKey(
        owner_id="alice",
        message=message_from_owner_id("alice"),
        heads_config=vars(HeadConfig(width=8, depth=2)),
        heads_state=heads.state_dict(),
        training_state={
            "step": np.int64(7),
            "heads_optimizer": {"param_groups": [{"lr": np.float64(1e-3)}]},
            "arr": np.arange(3),
        },
    )
    path = key.save(tmp_path / "k.gskey")
    # a fresh interpreter: no gsticker compat allow-list installed
    code = (
        "import torch,sys; p=torch.load(sys.argv[1], weights_only=True); "
        "print(type(p['training_state']['step']).__name__, p['training_state']['heads_optimizer']['param_groups'][0]['lr'])"
    )
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["int", "0.001"]
    loaded = OwnerKey.load(path)
    assert torch.equal(loaded.training_state["arr"], torch.arange(3))
    assert torch.equal(loaded.message, key.message)


def test_a_field_mark_key_reads_back_with_its_mark(tmp_path):
    back = OwnerKey.load(field_mark_key().save(tmp_path / "k.gskey"))
    assert back.field_mark == field_mark_key().field_mark
    assert back.geometry is None and back.version == 5


def test_a_key_whose_field_mark_lacks_a_setting_or_has_the_wrong_type_is_refused(tmp_path):
    import pytest

    from gsticker_plugin.errors import GStickerError

    for bad in ({"pattern_seed": "7"}, {"amplitude": 1}, {"levels": (0, 1)}, {"pattern_seed": True}):
        path = field_mark_key(**bad).save(tmp_path / "bad.gskey")
        with pytest.raises(GStickerError, match="malformed field mark"):
            OwnerKey.load(path)


def test_the_commitment_binds_the_field_mark_so_no_other_pattern_seed_can_be_claimed_later(tmp_path):
    """A key signed with one pattern seed, then edited to another (to make some other model read as marked), no
    longer matches its signed commitment and is refused."""
    import dataclasses

    import pytest
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    from gsticker_plugin.errors import GStickerError
    from gsticker_plugin.key import commitment

    key = dataclasses.replace(field_mark_key(), salt="00" * 16)
    key.sign(Ed25519PrivateKey.generate())
    other = dataclasses.replace(key, field_mark={**key.field_mark, "pattern_seed": 8})
    assert commitment(other) != commitment(key) and key.signed() and not other.signed()
    with pytest.raises(GStickerError, match="signature"):
        OwnerKey.load(other.save(tmp_path / "swapped.gskey"))
