"""The recipient of a shared run plays the attacker: each test runs one attack and asserts that it fails.

Message recovery from the folded sticker, key forgery and downgrade, tampered keys, config injection, pickle
checkpoints, and the owner's side (no secret left in config.yml, the key written before the checkpoint, a resume
with another run's key refused). docs/verify.md, "Threat model", says what a recipient can and cannot learn.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path
from typing import Dict

import pytest
import torch
import yaml
from conftest import CPU_ARGS, TINY_MESSAGE, TINY_STICKER_ARGS, small_key, subprocess_env

from gsticker_plugin import metrics, runs
from gsticker_plugin.attacks import recipient as R
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.key import (
    OwnerKey,
    commitment,
    fingerprint,
    owner_identity,
    payload_hmac,
    public_key_hex,
    random_message,
)
from gsticker_plugin.model import folds_to, seeded_sticker
from gsticker_plugin.recolor.cli import run as recolor
from gsticker_plugin.trainer import check_key_path, write_key
from gsticker_plugin.verify import cli as V
from gsticker_plugin.verify.check import check_commitment

BIN = Path(sys.executable).parent
SHAPE = {"kind": "bilinear", "num_bits": 48, "num_frequencies": 3, "hidden_dim": 64, "num_layers": 2, "init_scale": 0.5}


def snapshot(folder: Path) -> Dict[str, str]:
    """Every file under ``folder`` with the sha256 of its bytes."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def one_line(err: str) -> str:
    lines = [x for x in err.strip().splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err[-2000:]
    return lines[0]


# ---------------------------------------------------------------------------------------------- message recovery
def trained_like(seed: int, drift: float = 0.1) -> torch.nn.Module:
    """A sticker initialised from ``seed`` whose weights then moved by ``drift`` of their size (as training does)."""
    st = seeded_sticker(SHAPE, seed)
    g = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for p in st.parameters():
            p.add_(drift * p.abs().mean() * torch.randn(p.shape, generator=g))
    return st


def test_least_squares_reads_the_message_when_the_initial_patterns_are_known():
    """The attack itself works: with the initialisation's patterns the fold gives every bit away."""
    message = random_message()
    st = trained_like(7)
    folded = st.fold(message)["mlp.3.weight"].reshape(-1)
    got = R.recover_bits(folded, seeded_sticker(SHAPE, 7).mlp[-1].weight.detach())
    assert R.matches(got.bits, message) == 48 and got.residual < 0.2


def test_least_squares_with_patterns_from_another_seed_reads_at_chance():
    """Twenty messages (drawn from a fixed generator, so the test does not flake) against eight wrong seeds' patterns:
    the best fit's bits match like coin flips. 40/48 is past what 20 binomial(48, 1/2) draws reach once in 30 000."""
    g = torch.Generator().manual_seed(2026)
    counts = []
    for i in range(20):
        message = metrics.random_message(48, g)
        folded = trained_like(1000 + i).fold(message)["mlp.3.weight"].reshape(-1)
        best = R.best_recovery(folded, [(s, seeded_sticker(SHAPE, s).mlp[-1].weight.detach()) for s in range(8)])
        counts.append(R.matches(best.bits, message))
    assert max(counts) < 40 and 20 <= sum(counts) / len(counts) <= 28, counts


def test_the_sticker_is_initialised_from_a_secret_seed_not_the_global_generator(monkeypatch):
    """Two models built after the same torch.manual_seed (a recipient rebuilding the pipeline with machine.seed) get
    different stickers."""
    from nerfstudio.data.scene_box import SceneBox

    from gsticker_plugin import compat

    compat.apply()  # offline LPIPS, as the ns-* commands have it
    monkeypatch.setenv("GSTICKER_NO_DOWNLOAD", "1")

    from gsticker_plugin.model import GeometryStickerModelConfig
    from gsticker_plugin.small_nerf import SmallNeRFModelConfig

    box = SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    weights = []
    for _ in range(2):
        torch.manual_seed(42)
        model = GeometryStickerModelConfig(base_model=SmallNeRFModelConfig()).setup(scene_box=box, num_train_data=2)
        weights.append(model.sticker.mlp[-1].weight.detach().clone())
    assert not torch.allclose(weights[0], weights[1])


def test_recovery_from_a_real_shared_run_reads_at_chance_and_the_owners_control_reads_the_message(tiny_sticker):
    config = tiny_sticker["run"]
    key = OwnerKey.load(tiny_sticker["key"])
    state = runs.load_checkpoint_state(runs.latest_checkpoint(config.parent / "nerfstudio_models"))["pipeline"]
    folded = R.folded_last_layer(state)
    seed = int(runs.load_run_config(config).machine.seed)
    recipient = R.recover_bits(folded, R.regenerated_patterns(config, seed))
    assert R.matches(recipient.bits, key.message) < 36
    assert key.geometry["sticker_seed"] == 0  # the tests' given seed, in the key and nowhere in the shared config
    assert "sticker_seed: null" in config.read_text()
    secret = seeded_sticker(key.geometry["sticker_config"], key.geometry["sticker_seed"]).mlp[-1].weight.detach()
    assert R.matches(R.recover_bits(folded, secret).bits, key.message) >= 44  # what a leaked seed would give


# ---------------------------------------------------------------------------------------------- keys
def test_a_key_forged_from_a_shared_run_fails_the_owners_commitment_and_public_key(tmp_path, monkeypatch):
    monkeypatch.setenv("GSTICKER_IDENTITY", str(tmp_path / "alice.ed25519"))
    alice = small_key()
    alice.sign(owner_identity())
    alice_path = alice.save(tmp_path / "alice.gskey")
    published = (commitment(alice), alice.public_key)
    # the forger holds the same bits (say, recovered) and writes a key of their own, with their own identity
    mallory = small_key(message=alice.message.clone())
    mallory.sign(owner_identity(tmp_path / "mallory.ed25519"))
    forged = mallory.save(tmp_path / "forged.gskey")
    key = OwnerKey.load(forged)  # a self-consistent file: it loads
    with pytest.raises(GStickerError, match="does not match the commitment"):
        check_commitment(published[0], [(forged, key)])
    with pytest.raises(GStickerError, match="not signed by the public key"):
        check_commitment(None, [(forged, key)], published[1])
    # copying the owner's public key and signature into the forged key breaks it: the signature covers the commitment
    raw = torch.load(forged, weights_only=True)
    raw["public_key"], raw["signature"] = alice.public_key, alice.signature
    raw["hmac"] = payload_hmac(raw, bytes.fromhex(raw["secret"]))
    torch.save(raw, tmp_path / "copied.gskey")
    with pytest.raises(GStickerError, match="signature that does not match"):
        OwnerKey.load(tmp_path / "copied.gskey")
    # the owner's own key passes both
    ok = check_commitment(published[0], [(alice_path, OwnerKey.load(alice_path))], published[1])
    assert ok["signed"] and ok["given"] == published[0]


def test_a_downgraded_key_is_refused_unless_legacy_is_allowed(tmp_path):
    raw = small_key().payload()
    for version in (1, 2):
        old = {k: v for k, v in raw.items() if k not in ("hmac", "secret", "salt", "public_key", "signature")}
        old["version"] = version
        old["message"] = 1 - old["message"]  # the forger's bits, with the unkeyed fingerprint anyone recomputes
        old["fingerprint"] = fingerprint(old)
        torch.save(old, tmp_path / f"v{version}.gskey")
        with pytest.raises(GStickerError, match="allow-legacy"):
            OwnerKey.load(tmp_path / f"v{version}.gskey")
        assert OwnerKey.load(tmp_path / f"v{version}.gskey", allow_legacy=True).version == version


@pytest.mark.parametrize(
    "change, words",
    [
        ({"message": None}, "malformed 'message'"),
        ({"heads_state": "x"}, "malformed 'heads_state'"),
        ({"created": "yesterday"}, "malformed 'created'"),
        ({"geometry": {"no": "sticker"}}, "malformed geometry"),
        ({"public_key": 7}, "malformed 'public_key'"),
    ],
)
def test_a_key_with_a_valid_hmac_and_a_malformed_field_is_one_error_line(tmp_path, change, words):
    raw = small_key().payload()
    raw.update(change)
    raw["hmac"] = payload_hmac(raw, bytes.fromhex(raw["secret"]))
    torch.save(raw, tmp_path / "bad.gskey")
    with pytest.raises(GStickerError, match=words):
        OwnerKey.load(tmp_path / "bad.gskey")
    del raw["owner_id"]
    raw["hmac"] = payload_hmac(raw, bytes.fromhex(raw["secret"]))
    torch.save(raw, tmp_path / "missing.gskey")
    with pytest.raises(GStickerError, match="no 'owner_id' field"):
        OwnerKey.load(tmp_path / "missing.gskey")


def test_the_owner_identity_is_created_private_and_reused(tmp_path):
    path = tmp_path / "ids" / "owner.ed25519"
    a = owner_identity(path)
    assert path.stat().st_mode & 0o777 == 0o600
    assert public_key_hex(owner_identity(path)) == public_key_hex(a)
    path.write_text("not a key")
    with pytest.raises(GStickerError, match="not readable"):
        owner_identity(path)


def test_the_key_is_written_read_back_and_the_previous_one_kept(tmp_path):
    first, second = small_key(), small_key()
    path = tmp_path / "keys" / "run.gskey"
    write_key(first, path)
    write_key(second, path)
    assert commitment(OwnerKey.load(path)) == commitment(second)
    assert commitment(OwnerKey.load(Path(str(path) + ".bak"))) == commitment(first)


def test_an_unusable_key_path_is_refused_before_training(tmp_path):
    run_dir = tmp_path / "out" / "exp" / "geometrysticker" / "ts"
    (tmp_path / "folder.gskey").mkdir()
    with pytest.raises(GStickerError, match="is a folder"):
        check_key_path(tmp_path / "folder.gskey", run_dir)
    with pytest.raises(GStickerError, match="inside the run folder"):
        check_key_path(run_dir / "owner.gskey", run_dir)
    (tmp_path / "file").write_text("x")
    with pytest.raises(GStickerError, match="cannot write the owner key"):
        check_key_path(tmp_path / "file" / "owner.gskey", run_dir)
    check_key_path(tmp_path / "keys" / "owner.gskey", run_dir)


def test_a_key_belongs_to_the_run_whose_shared_sticker_it_folds_to():
    st = seeded_sticker(SHAPE, 3)
    message = random_message()
    state = {"_model.folded_sticker." + k: v for k, v in st.fold(message).items()}
    geometry = {"sticker_config": SHAPE, "sticker_state": st.state_dict()}
    assert folds_to(geometry, message, state)
    assert not folds_to(geometry, 1 - message, state)  # another key's message
    other = {"sticker_config": SHAPE, "sticker_state": seeded_sticker(SHAPE, 4).state_dict()}
    assert not folds_to(other, message, state)  # another run's sticker


# ---------------------------------------------------------------------------------------------- suspect files
def suspect_config(tmp_path: Path, data: Path, target: str = "", extra: str = "") -> Path:
    """A stock nerfacto-small (Blender data) config.yml as a recipient would edit it: the dataparser's ``_target`` replaced, extra
    fields added."""
    from nerfstudio.configs.method_configs import all_methods

    cfg = all_methods["gsticker-nerfacto-small"]
    cfg.pipeline.datamanager.data = cfg.pipeline.datamanager.dataparser.data = data
    text = yaml.dump(cfg)
    anchor = "_target: !!python/name:nerfstudio.data.dataparsers.blender_dataparser.Blender ''"
    assert anchor in text
    if target:
        text = text.replace(anchor, f"_target: !!python/name:{target} ''")
    if extra:
        text = text.replace(anchor, anchor + "\n" + extra)
    run = tmp_path / "suspect"
    (run / "nerfstudio_models").mkdir(parents=True)
    torch.save({"step": 0, "pipeline": {}}, run / "nerfstudio_models" / "step-000000000.ckpt")
    (run / "config.yml").write_text(text)
    return run / "config.yml"


@pytest.mark.parametrize(
    "target, extra",
    [
        ("gsticker_plugin.scene.main", ""),  # would write a scene over --output-dir
        ("gsticker_plugin.verify.calibrate.calibrate", ""),  # would rewrite another owner key's null
        ("nerfstudio.data.dataparsers.nerfstudio_dataparser.Nerfstudio", ""),  # a real dataparser, not this config's
        ("", "      overwrite: true"),  # a field the dataparser config does not declare
    ],
)
def test_an_injected_config_is_refused_and_writes_nothing(tmp_path, capsys, target, extra):
    victim = tmp_path / "victim"
    small_key().save(victim / "keys" / "other.gskey")
    (victim / "data" / "images").mkdir(parents=True)
    (victim / "data" / "images" / "a.png").write_bytes(b"png")
    config = suspect_config(tmp_path, victim / "data", target, extra)
    before, before_suspect = snapshot(victim), snapshot(config.parent)
    key = str(victim / "keys" / "other.gskey")
    status = V.main(["--load-config", str(config), "--key", key, "--output", str(tmp_path / "rep")])
    assert status == 2 and "is refused" in one_line(capsys.readouterr().err)
    with pytest.raises(SystemExit) as exc:
        recolor(["hue", "--load-config", str(config), "--output-dir", str(tmp_path / "rc"), "--shift", "0.2"])
    assert exc.value.code == 2 and "is refused" in one_line(capsys.readouterr().err)
    assert snapshot(victim) == before and snapshot(config.parent) == before_suspect
    with pytest.raises(GStickerError, match="is refused"):
        runs.load_run_config(config)


def test_a_pickled_checkpoint_is_never_unpickled(tmp_path):
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    path = tmp_path / "step-000000001.ckpt"
    torch.save({"step": 1, "pipeline": {"x": Payload()}}, path)
    with pytest.raises(GStickerError, match="never unpickled"):
        runs.load_checkpoint_state(path)
    assert not marker.exists()


# ---------------------------------------------------------------------------------------------- the owner's side
def ns_train_status(args, cwd: Path):
    proc = subprocess.run(
        [str(BIN / "ns-train"), *args], capture_output=True, text=True, env=subprocess_env(1), cwd=cwd, timeout=600
    )
    return proc.returncode, proc.stdout, proc.stderr


def sticker_args(tiny_base: Path, out: Path, *extra: str):
    ckpt = max((tiny_base.parent / "nerfstudio_models").glob("step-*.ckpt"))
    return [
        "geometrysticker",
        "--load-checkpoint",
        str(ckpt),
        *CPU_ARGS,
        "--output-dir",
        str(out),
        "--experiment-name",
        "gs",
        "--timestamp",
        "run",
        *TINY_STICKER_ARGS,
        *extra,
    ]


def test_a_failed_sticker_run_leaves_no_secret_in_its_config(tiny_base, tmp_path):
    args = sticker_args(tiny_base, tmp_path, "--pipeline.message", TINY_MESSAGE, "--pipeline.owner-id", "alice-secret")
    args += ["--pipeline.sticker-seed", "918273645"]
    args += ["--pipeline.key-path", str(tmp_path / "k.gskey"), "--data", str(tmp_path / "no-such-data")]
    status, out, err = ns_train_status(args, tmp_path)
    assert status == 2 and "does not exist" in one_line(err)
    text = (tmp_path / "gs" / "geometrysticker" / "run" / "config.yml").read_text()
    assert TINY_MESSAGE not in text and "alice-secret" not in text and "k.gskey" not in text
    assert "918273645" not in text and "sticker_seed: null" in text


def test_a_key_path_that_is_a_folder_stops_before_training(tiny_base, tmp_path):
    (tmp_path / "keys").mkdir()
    status, out, err = ns_train_status(
        sticker_args(tiny_base, tmp_path, "--pipeline.key-path", str(tmp_path / "keys")), tmp_path
    )
    assert status == 2 and "is a folder" in one_line(err)
    assert not list((tmp_path / "gs").rglob("*.ckpt"))


def test_a_resume_with_another_runs_key_is_refused_and_the_key_is_not_overwritten(tiny_sticker, tiny_base, tmp_path):
    other = OwnerKey.load(tiny_sticker["key"])
    other.geometry["sticker_state"] = seeded_sticker(other.geometry["sticker_config"], 5).state_dict()
    other.signature = other.public_key = ""  # a valid key of another run (unsigned: its commitment changed)
    other_path = other.save(tmp_path / "other.gskey")
    before = other_path.read_bytes()
    ckpt = max((tiny_sticker["run"].parent / "nerfstudio_models").glob("step-*.ckpt"))
    args = ["geometrysticker", "--load-checkpoint", str(ckpt), *CPU_ARGS, "--output-dir", str(tmp_path / "resumed")]
    args += ["--max-num-iterations", "12", "--pipeline.key-path", str(other_path)]
    status, out, err = ns_train_status(args, tmp_path)
    assert status == 2 and "does not belong" in one_line(err)
    assert other_path.read_bytes() == before


def test_the_recipient_page_shows_each_runs_recovery_beside_the_owners_control():
    from pathlib import Path as P

    from gsticker_plugin.bench.recipient import Args, page

    rows = [
        {"label": f"r{i}", "at_machine_seed": 20 + i, "best": 22 + i, "best_seed": i, "best_residual": 0.4}
        | {"owner_control": 48, "owner_control_residual": 0.01}
        for i in range(3)
    ]
    res = {"rows": rows, "date": "d", "command": "python -m gsticker_plugin.bench.recipient", "machine": {}}
    text = page(res, Args(output=P("docs/x.md")))
    assert "| r2 | 22/48 | 24/48 (seed 2, residual 0.40) | 48/48 (residual 0.010) |" in text
    assert "mean 23.0/48, min 22, max 24, 0 at 36 or more" in text


def test_a_dataparser_that_asks_a_question_gets_no_and_its_exit_is_one_error_line(tmp_path):
    """COLMAP's dataparser asks whether to downscale (and write) images into the data folder; a suspect run is never
    allowed to: the question reads "no" and the dataparser's exit becomes a GStickerError, nothing is written."""
    from types import SimpleNamespace

    answers = []

    def setup(device, test_mode):
        answers.append(input("downscale the images now? "))
        if answers[-1] != "y":
            raise SystemExit(1)
        (tmp_path / "images_2").mkdir()

    config = SimpleNamespace(pipeline=SimpleNamespace(setup=setup))
    with pytest.raises(GStickerError, match="asked a question"):
        runs.setup_pipeline(config, "cpu", "test", tmp_path / "config.yml")
    assert answers == ["n"] and not (tmp_path / "images_2").exists()


def test_a_key_of_another_scene_says_so(tiny_base, shared_dir, tmp_path, capsys):
    """A 2-step sticker on the lego100 base (its key) read against the tiny generated scene's base: "not shown", and
    the report says the key was made for another scene (on lego100 the same-scene TensoRF base agrees at 97-99 % of
    the surface pixels, another scene at 0 %: docs/verify.md)."""
    import json

    from conftest import ns_train

    lego = shared_dir / "checkpoints" / "lego100-nerfacto-small" / "nerfacto" / "base"
    key = tmp_path / "lego.gskey"
    args = ["geometrysticker", "--load-checkpoint", str(max((lego / "nerfstudio_models").glob("*.ckpt")))]
    args += ["--data", str(shared_dir / "data" / "lego100"), *CPU_ARGS, "--output-dir", str(tmp_path / "gs")]
    args += ["--max-num-iterations", "2", *TINY_STICKER_ARGS[2:], "--pipeline.key-path", str(key)]
    ns_train(args, tmp_path)
    out = tmp_path / "rep"
    status = V.main(["--load-config", str(tiny_base), "--key", str(key), "--num-views", "2", "--output", str(out)])
    stdout = capsys.readouterr().out
    assert status == 1 and "was made for another scene" in stdout
    assert json.loads((out / "report.json").read_text())["keys"][0]["scene_agreement"] < 0.5


def test_scene_agreement_is_the_share_of_surface_rays_whose_accumulation_agrees():
    from types import SimpleNamespace

    from gsticker_plugin.decoders.geometric import scene_agreement
    from gsticker_plugin.verify.check import median_agreement

    ref = SimpleNamespace(base_signal=torch.tensor([[1.0, 1.0, 1.0, 0.9]]))
    assert scene_agreement(torch.tensor([[1.0, 0.9, 0.2, 0.0]]), ref) == 0.5
    assert scene_agreement(torch.zeros(1, 0), ref) != scene_agreement(torch.zeros(1, 0), ref)  # NaN: no surface ray
    dec = {"geometry": [{"scene_agreement": v} for v in (0.9, float("nan"), 0.1, 0.95)]}
    assert median_agreement(dec) == 0.9
