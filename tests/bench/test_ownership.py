"""The ownership claim against the recipient of a shared run: secret random messages, the folded sticker, the key's
HMAC and commitment, and what a forger can and cannot do (docs/verify.md, "Threat model")."""

from __future__ import annotations

import pytest
import torch
from conftest import CPU_ARGS, TINY_POOL_ARGS, small_key

from gsticker_plugin.errors import GStickerError
from gsticker_plugin.key import (
    KEY_VERSION,
    OwnerKey,
    commitment,
    default_key_path,
    fingerprint,
    keys_dir,
    message_from_owner_id,
    payload_hmac,
    random_message,
)
from gsticker_plugin.sticker import FoldedSticker, Sticker


@pytest.mark.parametrize("kind", ["bilinear", "concat"])
def test_the_folded_sticker_equals_the_sticker_of_its_message(kind):
    torch.manual_seed(0)
    sticker = Sticker(48, 3, 16, 2, 0.5, kind)
    message = random_message()
    folded = FoldedSticker(3, 16, 2)
    folded.load_state_dict(sticker.fold(message), strict=True)
    x = torch.rand(200, 3)
    with torch.no_grad():
        expected = sticker(x, message)
        got = folded(x)
        other = sticker(x, 1 - message)
    assert torch.allclose(got, expected, atol=1e-6), float((got - expected).abs().max())
    assert not torch.allclose(got, other, atol=1e-3)  # the fold depends on the message
    # the folded state holds no per-bit layer and no message input
    assert all(v.shape[0] != 48 for v in folded.state_dict().values())


def test_messages_are_drawn_at_random_not_from_the_owner_id():
    drawn = {tuple(random_message().tolist()) for _ in range(20)}
    assert len(drawn) == 20
    ones = torch.stack([random_message() for _ in range(400)]).float().mean()
    assert 0.45 < float(ones) < 0.55  # uniform bits
    assert torch.equal(message_from_owner_id("alice"), message_from_owner_id("alice"))  # the explicit, weaker option


def test_key_round_trip_keeps_the_source_secret_salt_and_commitment(tmp_path):
    key = small_key(message_source="random")
    path = key.save(tmp_path / "k.gskey")
    back = OwnerKey.load(path)
    assert back.version == KEY_VERSION and back.message_source == "random" and back.null_caveats() == []
    assert back.secret == key.secret and back.salt == key.salt and len(back.salt) == 32
    assert commitment(back) == commitment(key)
    # calibrating rewrites the key (a null is stored): the commitment to its secret parts stays
    back.null = {"matches": [20, 24]}
    back.save(path)
    assert commitment(OwnerKey.load(path)) == commitment(key)


def test_a_forged_key_fails_its_integrity_check(tmp_path):
    """Edit the message and recompute the unkeyed fingerprint (what an older key's check accepted): refused."""
    key = small_key()
    path = key.save(tmp_path / "k.gskey")
    raw = torch.load(path, weights_only=True)
    raw["message"] = 1 - raw["message"]
    raw["fingerprint"] = fingerprint(raw)
    torch.save(raw, tmp_path / "forged.gskey")
    with pytest.raises(GStickerError, match="integrity check"):
        OwnerKey.load(tmp_path / "forged.gskey")
    # a forger with their own secret makes a valid file, but not one that matches the owner's commitment
    raw["secret"] = "00" * 32
    raw["hmac"] = payload_hmac(raw, bytes.fromhex(raw["secret"]))
    torch.save(raw, tmp_path / "reforged.gskey")
    reforged = OwnerKey.load(tmp_path / "reforged.gskey")
    assert commitment(reforged) != commitment(key)


def test_keys_whose_null_is_not_exact_say_why():
    assert small_key(message_source="owner-id").null_caveats()[0].startswith("the message is derived from the owner ID")
    assert "trained on the owner's message" in small_key(owner_message_prob=0.5).null_caveats()[0]
    assert "given on the command line" in small_key(message_source="given").null_caveats()[0]


def test_default_key_path_is_in_the_per_user_keys_folder(monkeypatch, tmp_path):
    monkeypatch.setenv("GSTICKER_KEYS_DIR", str(tmp_path / "keys"))
    assert keys_dir() == tmp_path / "keys"
    assert (
        default_key_path("lego", "geometrysticker", "2026-12-03_1")
        == tmp_path / "keys" / "lego-geometrysticker-2026-12-03_1.gskey"
    )
    monkeypatch.delenv("GSTICKER_KEYS_DIR")
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert keys_dir() == tmp_path / "xdg" / "gsticker" / "keys"


# ---------------------------------------------------------------------------------------------- real runs
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import zipfile  # noqa: E402
from pathlib import Path  # noqa: E402

from conftest import one_error_line  # noqa: E402

from gsticker_plugin.decoders import fit as FIT  # noqa: E402
from gsticker_plugin.key import bits_to_str  # noqa: E402
from gsticker_plugin.verify import cli as V  # noqa: E402

BIN = Path(sys.executable).parent


def _train(args, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", GSTICKER_NO_DOWNLOAD="1", PYTHONWARNINGS="ignore", COLUMNS="200")
    proc = subprocess.run([str(BIN / "ns-train"), *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def run_cli(argv, capsys):
    status = V.main([*argv, "--no-progress"] if argv[:1] not in (["commit"], ["export-key"]) else argv)
    cap = capsys.readouterr()
    return status, cap.out, cap.err


def moved_copy(run: Path, dst: Path) -> Path:
    """A copy of a run folder whose config.yml no longer points at the original (its checkpoint is found beside it)."""
    import shutil

    import yaml

    shutil.copytree(run, dst)
    cfg = yaml.load((dst / "config.yml").read_text(), Loader=yaml.Loader)
    cfg.output_dir, cfg.experiment_name, cfg.timestamp = dst / "nowhere", "x", "y"
    (dst / "config.yml").write_text(yaml.dump(cfg))
    return dst


@pytest.fixture(scope="module")
def shared_run(tiny_base, tmp_path_factory, owner_keys_dir):
    """A tiny base and a sticker trained on it with the defaults a user gets: random secret message, key in the
    per-user keys folder (here the session's GSTICKER_KEYS_DIR), owner label 'alice'."""
    ws = tmp_path_factory.mktemp("ownership")
    out = ws / "outputs"
    base = tiny_base.parent
    ckpt = max((base / "nerfstudio_models").glob("step-*.ckpt"))
    proc = _train(
        [
            "geometrysticker",
            "--load-checkpoint",
            str(ckpt),
            *CPU_ARGS,
            "--output-dir",
            str(out),
            "--experiment-name",
            "shared",
            "--timestamp",
            "run",
            "--max-num-iterations",
            "10",
            "--pipeline.owner-id",
            "alice",
            *TINY_POOL_ARGS,
        ],
        ws,
    )
    key = default_key_path("shared", "geometrysticker", "run")
    return {
        "ws": ws,
        "out": out,
        "base": base / "config.yml",
        "run": out / "shared" / "geometrysticker" / "run",
        "key": key,
        "stdout": proc.stdout,
    }


@pytest.mark.slow
def test_the_shared_output_folder_holds_no_message_no_key_and_no_key_path(shared_run):
    key_path = shared_run["key"]
    assert key_path.is_file() and not key_path.is_relative_to(shared_run["out"])
    assert str(key_path) in shared_run["stdout"]  # the trainer says where the secret went
    key = OwnerKey.load(key_path)
    assert key.message_source == "random" and key.owner_id == "alice" and key.null_caveats() == []
    message = bits_to_str(key.message)
    archive = shared_run["ws"] / "shared.zip"
    with zipfile.ZipFile(archive, "w") as z:
        for f in shared_run["out"].rglob("*"):
            if f.is_file():
                z.write(f, f.relative_to(shared_run["out"]))
    with zipfile.ZipFile(archive) as z:
        names = z.namelist()
        assert not [n for n in names if n.endswith(".gskey")], names
        blobs = {n: z.read(n) for n in names}
    assert any(n.endswith(".ckpt") for n in names) and any("events.out.tfevents" in n for n in names)
    secrets_as_bytes = [
        message.encode(),
        str(key_path).encode(),
        key_path.name.encode(),
        key.secret.encode(),
        key.salt.encode(),
        b"alice",
    ]
    for n, blob in blobs.items():
        for s in secrets_as_bytes:
            assert s not in blob, f"{n} holds {s[:20]!r}"
    # the checkpoints: no message, no per-bit sticker, no sticker optimizer state; the folded sticker only
    for n in names:
        if n.endswith(".ckpt"):
            state = torch.load(shared_run["out"] / n, map_location="cpu", weights_only=False)
            keys = list(state["pipeline"])
            assert not [k for k in keys if k.startswith(("_model.message", "_model.sticker."))], n
            if "geometrysticker" in n:  # (the base run's own checkpoint is in the folder too)
                assert bool(state["pipeline"]["_model.folded"]) and not state["optimizers"], n
            for t in state["pipeline"].values():  # no 48-long 0/1 vector anywhere
                if isinstance(t, torch.Tensor) and t.numel() == 48 and t.dtype in (torch.long, torch.int64):
                    assert not torch.equal(t.cpu(), key.message), n
    cfg = (shared_run["run"] / "config.yml").read_text()
    assert "owner_id: ''" in cfg and "message: null" in cfg and "key_path: null" in cfg


@pytest.mark.slow
def test_decoded_bits_do_not_depend_on_the_key_message_and_a_commitment_is_checked(shared_run, capsys):
    """The null rests on this: the geometric decoder's bits for a suspect are the same whatever message the key
    holds; only the matches change. The committed key verifies with --commitment, another value is an error."""
    ws = shared_run["ws"]
    key_path = shared_run["key"]
    p = torch.load(key_path, weights_only=True)
    p["message"] = 1 - p["message"]
    p["signature"] = p["public_key"] = ""  # another message is another commitment: the owner's signature is dropped
    p["hmac"] = payload_hmac(p, bytes.fromhex(p["secret"]))
    other = ws / "other-message.gskey"
    torch.save(p, other)
    decoded = {}
    for name, k in (("own", key_path), ("other", other)):
        out = ws / f"rep-{name}"
        status, stdout, err = run_cli(
            [
                "--load-config",
                str(shared_run["run"] / "config.yml"),
                "--key",
                str(k),
                "--output",
                str(out),
                "--num-views",
                "3",
                "--decode",
                "geometry",
            ],
            capsys,
        )
        assert status in (V.EXIT_OWNED, V.EXIT_NOT_SHOWN), err
        rep = json.loads((out / "report.json").read_text())
        decoded[name] = [v["decoded"] for v in rep["keys"][0]["per_view"]]
        decoded[name + "-matches"] = [v["matches"] for v in rep["keys"][0]["per_view"]]
    assert decoded["own"] == decoded["other"]
    assert [48 - m - d.count("?") for m, d in zip(decoded["own-matches"], decoded["own"])] == decoded["other-matches"]
    assert sum(decoded["own-matches"]) > sum(decoded["other-matches"])  # the run carries the key's own message
    # commit, then verify against the commitment
    status, stdout, err = run_cli(["commit", "--key", str(key_path)], capsys)
    hex_, public = stdout.split()
    assert status == 0 and len(hex_) == 64 and hex_ == commitment(OwnerKey.load(key_path))
    assert public == OwnerKey.load(key_path).public_key  # the key is signed: its public key is printed too
    out = ws / "rep-committed"
    status, stdout, err = run_cli(
        [
            "--load-config",
            str(shared_run["run"] / "config.yml"),
            "--key",
            str(key_path),
            "--output",
            str(out),
            "--num-views",
            "2",
            "--decode",
            "geometry",
            "--commitment",
            hex_,
            "--public-key",
            public,
        ],
        capsys,
    )
    rep = json.loads((out / "report.json").read_text())
    assert rep["commitment"]["matches"] is True and rep["commitment"]["signed"] and "signed by" in stdout
    status, _, err = run_cli(
        [
            "--load-config",
            str(shared_run["run"] / "config.yml"),
            "--key",
            str(other),
            "--output",
            str(ws / "rep-x"),
            "--num-views",
            "2",
            "--decode",
            "geometry",
            "--commitment",
            hex_,
        ],
        capsys,
    )
    assert status == 2 and "does not match the commitment" in one_error_line(err)


@pytest.mark.slow
def test_every_verification_failure_is_one_error_line_and_exit_2(shared_run, capsys, monkeypatch):
    ws = shared_run["ws"]
    run_cfg = shared_run["run"] / "config.yml"
    key = str(shared_run["key"])
    cases = []
    # a missing suspect, a missing key
    cases.append((["--load-config", str(ws / "nowhere" / "config.yml"), "--key", key], "does not exist"))
    cases.append((["--load-config", str(run_cfg), "--key", str(ws / "nokey.gskey")], "does not exist"))
    # a truncated suspect checkpoint
    trunc = moved_copy(shared_run["run"], ws / "truncated" / "run")
    (ck,) = (trunc / "nerfstudio_models").glob("step-*.ckpt")
    ck.write_bytes(ck.read_bytes()[: ck.stat().st_size // 2])
    cases.append((["--load-config", str(trunc / "config.yml"), "--key", key], "truncated"))
    # a checkpoint with a weight missing: named, not loaded half
    missing = moved_copy(shared_run["run"], ws / "missing-weight" / "run")
    (ck,) = (missing / "nerfstudio_models").glob("step-*.ckpt")
    state = torch.load(ck, map_location="cpu", weights_only=False)
    state["pipeline"].pop("_model.folded_sticker.pos_in.weight")
    torch.save(state, ck)
    cases.append((["--load-config", str(missing / "config.yml"), "--key", key], "folded_sticker.pos_in.weight"))
    # a foreign config that asks YAML to run a command
    evil = ws / "evil"
    evil.mkdir()
    flag = ws / "pwned"
    (evil / "config.yml").write_text(f"!!python/object/apply:os.system ['touch {flag}']\n")
    cases.append((["--load-config", str(evil / "config.yml"), "--key", key], "is refused"))
    # a key that is not a key
    (ws / "bad.gskey").write_text("not a key")
    cases.append((["--load-config", str(run_cfg), "--key", str(ws / "bad.gskey")], "not a readable"))
    for argv, words in cases:
        status, stdout, err = run_cli([*argv, "--output", str(ws / "rep-bad"), "--num-views", "2"], capsys)
        assert status == 2, (argv, stdout[-500:], err[-2000:])
        assert words in one_error_line(err), (argv, err[-2000:])
    assert not flag.exists()

    # a crash inside decoding is an error, never "not shown"
    def boom(*a, **k):
        raise RuntimeError("simulated failure in the fit")

    monkeypatch.setattr(FIT, "fit_message", boom)
    status, stdout, err = run_cli(
        [
            "--load-config",
            str(run_cfg),
            "--key",
            key,
            "--output",
            str(ws / "rep-crash"),
            "--num-views",
            "2",
            "--decode",
            "geometry",
        ],
        capsys,
    )
    line = one_error_line(err)
    assert status == 2 and "no verdict" in line and "simulated failure" in line and "VERDICT" not in stdout
