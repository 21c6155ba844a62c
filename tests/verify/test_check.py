"""Tests of ``ns-verify-owner`` (gsticker_plugin/verify/) and the statistics it adds to ``metrics``.

Over 600 lines on purpose: the tests share one hand-built key and its image folders (module fixtures).

The verdict logic is tested with a *hand-built* owner key whose extractor truly reads bits from images in a
known way: a 7 x 7 grid of cells, cell ``i`` brighter than the image's average cell means bit ``i`` = 1 (a
1x1 "convolution" to luminance, GroupNorm, GELU, 7 x 7 grid pooling and a linear read-out, all set by hand).
Images that carry a message in that grid decode to it exactly; random images and renders of a scene decode at
chance (checked below). Nothing is faked: the CLI loads the key, reads the files and decodes them.

"Recolored" images here are luminance-preserving palette maps of the grid images (two palette colours per
image, from the paper's ten reference colours) and hue shifts of those (kornia HSV hue shift via ``--attack``
and as files): stand-ins for the output of a recolorization of a marked model, whose geometry (here: the
brightness pattern) is kept.

The end-to-end tests train a tiny nerfacto base and a tiny ``geometrysticker`` run on the 32 px tiny scene
(like tests/test_geometrysticker.py) and check that ``verify`` and ``calibrate`` run on real runs and write
sane reports. The blind extractor of such a 10-step run has not learned the message (docs/experiments/sticker-notes.md,
"Status"), so on it ``--decode extractor`` must answer exactly "not shown" (exit 1) with every view below the
threshold and the median at chance: it claims nothing it cannot show. The informed geometric decoder
(``--decode geometry``, the default for a model with a version-2 key whose base is reachable; more in
tests/test_geometry.py) reads the message from the geometry: "owned", also on the runs recolored by ``ns-recolor``.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path
from typing import List

import numpy as np
import pytest
import torch
from conftest import TINY_MESSAGE, copy_key

from gsticker_plugin import metrics
from gsticker_plugin import runs as RUNS
from gsticker_plugin.key import OwnerKey, fingerprint
from gsticker_plugin.verify import cli as V

BIN = Path(sys.executable).parent
G, CELL = 7, 8  # 7 x 7 cells (48 bits + 1 neutral cell) of 8 px: 56 px images
PALETTES = [
    ((0.05, 0.1, 0.45), (1.0, 0.85, 0.2)),
    ((0.35, 0.05, 0.4), (0.2, 1.0, 0.6)),
    ((0.3, 0.05, 0.05), (1.0, 0.6, 0.85)),
    ((0.0, 0.25, 0.3), (1.0, 0.55, 0.1)),
]


# ---------------------------------------------------------------------------------------------- helpers
def make_key(message, owner_id: str = "alice") -> OwnerKey:
    """An owner key whose extractor reads bit i as 'grid cell i brighter than the mean cell' (see module doc)."""
    from gsticker_plugin.heads import HeadConfig, Heads

    cfg = dict(backbone="small", width=4, depth=0, pooling="grid", grid=G)
    heads = Heads(HeadConfig(**cfg), 48)
    sd = {k: torch.zeros_like(v) for k, v in heads.state_dict().items()}
    for name in ("extractor", "classifier"):
        sd[f"{name}.backbone.0.weight"][0, :, 1, 1] = 1.0 / 3.0  # channel 0 = luminance
        sd[f"{name}.backbone.1.weight"][:] = 1.0  # GroupNorm scale
    for i in range(48):  # logit_i = 10 * (cell_i - mean cell) of channel 0
        sd["extractor.head.weight"][i, : G * G] = -10.0 / (G * G)
        sd["extractor.head.weight"][i, i] += 10.0
    return OwnerKey(owner_id=owner_id, message=torch.as_tensor(message).long(), heads_config=cfg, heads_state=sd)


def msg(seed: int) -> torch.Tensor:
    return metrics.random_message(48, torch.Generator().manual_seed(seed))


def grid_values(message) -> torch.Tensor:
    vals = torch.full((G * G,), 0.5)
    vals[:48] = torch.where(torch.as_tensor(message).bool(), 0.75, 0.25)
    return vals.view(G, G)


def bit_image(message, seed: int = 0, noise: float = 0.02) -> np.ndarray:
    """H W 3 float image carrying ``message`` in the grid (mild noise)."""
    g = torch.Generator().manual_seed(seed)
    img = grid_values(message).repeat_interleave(CELL, 0).repeat_interleave(CELL, 1)
    img = img[None].expand(3, -1, -1) + noise * torch.randn(3, G * CELL, G * CELL, generator=g)
    return img.clamp(0, 1).permute(1, 2, 0).numpy()


def palette(img: np.ndarray, which: int) -> np.ndarray:
    lo, hi = (np.array(c, dtype=np.float32) for c in PALETTES[which % len(PALETTES)])
    v = img.mean(axis=-1, keepdims=True)
    return np.clip(lo + (hi - lo) * v, 0, 1)


def flip(message, n: int, offset: int = 0) -> torch.Tensor:
    m = torch.as_tensor(message).clone()
    idx = [(offset + 7 * j) % 48 for j in range(n)]
    m[idx] = 1 - m[idx]
    return m


def write_image(path: Path, arr: np.ndarray, fmt: str = "uint8") -> Path:
    import OpenImageIO as oiio

    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    h, w, c = arr.shape
    out = oiio.ImageOutput.create(str(path))
    assert out is not None, oiio.geterror()
    assert out.open(str(path), oiio.ImageSpec(w, h, c, fmt)), out.geterror()
    assert out.write_image(arr), out.geterror()
    out.close()
    return path


def write_big_png(path: Path, side: int, message) -> Path:
    """A side x side 8-bit grayscale PNG carrying ``message`` in the grid, written row by row (no big buffer)."""
    vals = (grid_values(message).numpy() * 255).round().astype(np.uint8)
    edges = [round(i * side / G) for i in range(G + 1)]

    def chunk(t: bytes, d: bytes) -> bytes:
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)

    co = zlib.compressobj(1)
    parts = []
    for r in range(G):
        row = np.concatenate([np.full(edges[c + 1] - edges[c], vals[r, c], np.uint8) for c in range(G)])
        line = b"\x00" + row.tobytes()
        for _ in range(edges[r + 1] - edges[r]):
            parts.append(co.compress(line))
    parts.append(co.flush())
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)))
        f.write(chunk(b"IDAT", b"".join(parts)) + chunk(b"IEND", b""))
    return path


def run_cli(argv: List[str], capsys):
    """``ns-verify-owner`` in this process: (status, stdout, stderr)."""
    status = V.main([*argv, "--no-progress"] if "--help" not in argv else argv)
    cap = capsys.readouterr()
    return status, cap.out, cap.err


def report_of(out_dir: Path) -> dict:
    return json.loads((out_dir / "report.json").read_text())


def direct_tail(m: int, k: int = 48) -> float:
    return sum(math.comb(k, i) for i in range(m, k + 1)) / 2**k


def one_error_line(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


# ---------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("verify")


@pytest.fixture(scope="module")
def alice(ws) -> dict:
    m = msg(1)
    path = make_key(m, "alice").save(ws / "keys" / "alice.gskey")
    return {"message": m, "path": path}


@pytest.fixture(scope="module")
def dirs(ws, alice) -> dict:
    m = alice["message"]
    d = {name: ws / name for name in ("marked", "palette", "hue", "random", "other", "near44")}
    for p in d.values():
        p.mkdir()
    for i in range(6):
        img = bit_image(m, seed=i)
        write_image(d["marked"] / f"view{i}.png", img)
        pal = palette(img, i)
        write_image(d["palette"] / f"view{i}.png", pal)
        from gsticker_plugin.attacks import hue_shift

        hued = hue_shift(torch.from_numpy(pal).permute(2, 0, 1)[None], 0.15 + 0.05 * i)[0].permute(1, 2, 0).numpy()
        write_image(d["hue"] / f"view{i}.jpg", hued)
        write_image(d["near44"] / f"view{i}.png", bit_image(flip(m, 4, offset=i), seed=10 + i))
    g = torch.Generator().manual_seed(5)
    for i in range(8):
        write_image(d["random"] / f"rand{i}.png", torch.rand(56, 56, 3, generator=g).numpy())
    return d


# ---------------------------------------------------------------------------------------------- metrics additions
def test_empirical_threshold_rule():
    assert metrics.empirical_threshold([20, 30, 42], 1e-6, 48) == 43  # fpr < 1/n: one above the null's max
    assert metrics.empirical_threshold(list(range(100)), 0.1, 200) == 90  # 10 of 100 samples reach 90
    assert metrics.empirical_threshold([48] * 5, 1e-6, 48) == 49  # never
    with pytest.raises(ValueError):
        metrics.empirical_threshold([], 1e-6, 48)


def test_vote_pvalue_and_clopper_pearson_against_scipy():
    stats = pytest.importorskip("scipy.stats")
    m = [48, 41, 10, 10]
    assert metrics.vote_statistic(m, 0.5) == 41
    assert metrics.vote_pvalue(m, 48, 0.5) == pytest.approx(direct_tail(41) / 0.5, rel=1e-12)
    assert metrics.vote_pvalue([10, 10, 10], 48, 0.5) == 1.0
    for x, n in ((0, 100), (3, 100), (7, 20)):
        assert metrics.clopper_pearson_upper(x, n) == pytest.approx(stats.beta.ppf(0.95, x + 1, n - x), rel=1e-9)
    assert metrics.clopper_pearson_upper(5, 5) == 1.0


def test_the_summary_names_views_with_nothing_to_read_instead_of_a_bare_zero():
    """An image whose camera shows no ray the gate reads decodes every bit undetermined (0 matches): the summary says
    so, rather than leave a 0/48 that reads like an anti-watermark."""
    from gsticker_plugin.verify.report import nothing_read, summary_text

    def view(name, matches, undetermined):
        return {"name": name, "matches": matches, "pvalue": 1.0, "image_fit": {"undetermined": undetermined}}

    key = {
        "owner_id": "alice",
        "key": "a.gskey",
        "verdict": "not shown",
        "decoder": "image",
        "num_bits": 48,
        "thresholds": {"used": 41, "theoretical": 41, "per_view_fpr_target": 1e-6, "empirical": None},
        "empirical_null": None,
        "views_passing": 0,
        "views": 2,
        "share_passing": 0.0,
        "views_needed": 1,
        "min_share": 0.5,
        "matches_min": 0,
        "matches_median": 12,
        "matches_max": 24,
        "mean_bit_accuracy": 0.25,
        "mean_score": None,
        "model_pvalue": 1.0,
        "model_fpr_bound": 1.0,
        "per_view": [view("a.png", 24, 0), view("b.png", 0, 48)],
    }
    report = {
        "verdict": "not shown",
        "owned_by": [],
        "settings": {"attack": ""},
        "keys": [key],
        "input": {"kind": "images", "source": "dir", "views": 2, "skipped": []},
    }
    assert nothing_read(key) == 1
    assert "1 view(s) with nothing to read" in summary_text(report)
    key["per_view"][1]["image_fit"]["undetermined"] = 47
    assert nothing_read(key) == 0 and "nothing to read" not in summary_text(report)
    assert "seconds:" not in summary_text(report)  # cameras given: no search to time


def test_the_summary_gives_the_seconds_of_the_view_bank_apart_from_each_images_camera_search():
    from gsticker_plugin.verify.report import timing_line

    fits = [
        {"seconds": 30.0, "search_seconds": 20.0, "view_bank_seconds": 12.5},
        {"seconds": 10.0, "search_seconds": 6.0},
        {"seconds": 14.0, "search_seconds": 8.0},
    ]
    line = timing_line({"per_view": [{"image_fit": f} for f in fits]})
    assert line.strip() == "seconds: view bank 12.5 (once), then per image median 14.0 of which the camera search 8.0"


# ---------------------------------------------------------------------------------------------- hand-built key
def test_hand_built_extractor_reads_the_grid_and_sits_at_chance_on_random_images(alice):
    key = OwnerKey.load(alice["path"])
    heads = key.build_heads()
    imgs = torch.stack([torch.from_numpy(bit_image(alice["message"], seed=s)).permute(2, 0, 1) for s in range(3)])
    assert metrics.count_matches(metrics.decode_bits(heads.decode(imgs)), key.message).tolist() == [48, 48, 48]
    rand = torch.rand(300, 3, 56, 56, generator=torch.Generator().manual_seed(0))
    m = metrics.count_matches(metrics.decode_bits(heads.decode(rand)), key.message).float()
    assert abs(float(m.mean()) - 24) < 1.0 and 2.5 < float(m.std()) < 4.5 and int(m.max()) < 41


@pytest.mark.parametrize("case", ["marked", "palette", "hue", "palette+hue-attack"])
def test_owned_on_marked_and_recolored_images(alice, dirs, ws, capsys, case):
    folder = dirs["palette" if case == "palette+hue-attack" else case]
    out = ws / f"rep-{case}"
    extra = ["--attack", "hue=0.3"] if case == "palette+hue-attack" else []
    status, stdout, _ = run_cli(
        ["--images", str(folder), "--key", str(alice["path"]), "--output", str(out), *extra], capsys
    )
    assert status == 0, stdout
    assert stdout.startswith("VERDICT: OWNED by alice")
    rep = report_of(out)
    assert rep["verdict"] == "owned" and rep["exit_status"] == 0 and rep["owned_by"] == ["alice"]
    (r,) = rep["keys"]
    assert r["views"] == 6 and r["views_passing"] == 6 and r["share_passing"] == 1.0
    assert r["thresholds"] == {
        "theoretical": 41,
        "empirical": None,
        "used": 41,
        "per_view_fpr_target": 1e-6,
        "per_view_fpr_at_used": pytest.approx(direct_tail(41), rel=1e-12),
    }
    assert min(v["matches"] for v in r["per_view"]) >= 46
    assert r["soft_score_pvalue"] < 1e-6  # the soft correlation score agrees
    assert "soft correlation score over all views" in stdout
    assert (out / "report.png").stat().st_size > 10_000


@pytest.mark.parametrize("case", ["random", "other", "wrong-owner"])
def test_not_shown_on_random_images_another_scene_and_another_owners_images(alice, dirs, ws, tiny_scene, capsys, case):
    folder = {"random": dirs["random"], "other": tiny_scene / "train", "wrong-owner": None}[case]
    key = alice["path"]
    if case == "wrong-owner":  # images marked for alice, key of bob
        folder = dirs["marked"]
        key = make_key(msg(2), "bob").save(ws / "bob-only" / "bob.gskey")
    out = ws / f"rep-{case}"
    status, stdout, _ = run_cli(["--images", str(folder), "--key", str(key), "--output", str(out)], capsys)
    assert status == 1, stdout
    assert stdout.startswith("VERDICT: NOT SHOWN")
    rep = report_of(out)
    assert rep["verdict"] == "not shown" and rep["owned_by"] == [] and rep["exit_status"] == 1
    (r,) = rep["keys"]
    assert r["views"] >= 6 and r["views_passing"] == 0 and r["matches_max"] < 41
    assert r["soft_score_pvalue"] > 1e-3  # unmarked (for this key): the soft score's bound stays far from evidence


def test_pvalues_match_a_direct_binomial_computation(alice, dirs, ws, capsys):
    stats = pytest.importorskip("scipy.stats")
    seen = set()
    for name in ("marked", "random", "near44"):
        out = ws / f"rep-p-{name}"
        run_cli(["--images", str(dirs[name]), "--key", str(alice["path"]), "--output", str(out)], capsys)
        (r,) = report_of(out)["keys"]
        for v in r["per_view"]:
            m = v["matches"]
            seen.add(m)
            assert v["pvalue"] == pytest.approx(direct_tail(m), rel=1e-9, abs=1e-300)
            assert v["pvalue"] == pytest.approx(float(stats.binom.sf(m - 1, 48, 0.5)), rel=1e-9)
            assert v["bit_accuracy"] == pytest.approx(m / 48)
            assert v["passed"] == (m >= 41)
        ms = sorted((v["matches"] for v in r["per_view"]), reverse=True)
        t = ms[math.ceil(0.5 * len(ms)) - 1]
        assert r["model_pvalue"] == pytest.approx(min(1.0, direct_tail(t) / 0.5), rel=1e-9)
    assert len(seen) >= 4  # several different match counts were checked


def test_min_share_vote_and_fpr_option(alice, dirs, ws, capsys):
    mixed = ws / "mixed-vote"
    mixed.mkdir()
    for i, src in enumerate(sorted(dirs["marked"].iterdir())[:2] + sorted(dirs["random"].iterdir())[:4]):
        shutil.copy(src, mixed / f"{i}-{src.name}")
    out = ws / "rep-vote"
    status, _, _ = run_cli(["--images", str(mixed), "--key", str(alice["path"]), "--output", str(out)], capsys)
    r = report_of(out)["keys"][0]
    assert status == 1 and r["views_passing"] == 2 and r["views_needed"] == 3  # 2/6 < 50 %
    status, _, _ = run_cli(
        ["--images", str(mixed), "--key", str(alice["path"]), "--output", str(out), "--min-share", "0.3"], capsys
    )
    r = report_of(out)["keys"][0]
    assert status == 0 and r["views_needed"] == 2 and r["model_fpr_bound"] == pytest.approx(direct_tail(41) / 0.3)
    status, _, _ = run_cli(
        ["--images", str(dirs["near44"]), "--key", str(alice["path"]), "--output", str(out), "--fpr", "1e-9"], capsys
    )  # 44 matches: passes at 1e-9 (>= 44)
    assert status == 0 and report_of(out)["keys"][0]["thresholds"]["used"] == 44


def test_attack_option(alice, dirs, ws, capsys):
    out = ws / "rep-attack"
    status, _, _ = run_cli(
        [
            "--images",
            str(dirs["marked"]),
            "--key",
            str(alice["path"]),
            "--output",
            str(out),
            "--attack",
            "noise=0.05,blur=1,jpeg=50",
        ],
        capsys,
    )
    assert status == 0 and report_of(out)["settings"]["attack"] == "noise=0.05,blur=1,jpeg=50"
    status, _, err = run_cli(
        ["--images", str(dirs["marked"]), "--key", str(alice["path"]), "--output", str(out), "--attack", "bogus=1"],
        capsys,
    )
    assert status == 2 and "unknown attack" in one_error_line(err)


# ---------------------------------------------------------------------------------------------- many owners
def test_many_keys_are_corrected_for_multiple_testing(alice, dirs, ws, capsys):
    kdir = ws / "many-keys"
    kdir.mkdir()
    shutil.copy(alice["path"], kdir / "alice.gskey")
    for i, name in enumerate(["bob", "carol", "dave", "erin"]):
        make_key(msg(10 + i), name).save(kdir / f"{name}.gskey")
    for correction in ("holm", "bonferroni"):
        out = ws / f"rep-many-{correction}"
        status, stdout, _ = run_cli(
            ["--images", str(dirs["marked"]), "--keys", str(kdir), "--output", str(out), "--correction", correction],
            capsys,
        )
        assert status == 0 and stdout.startswith("VERDICT: OWNED by alice")
        rep = report_of(out)
        assert rep["owned_by"] == ["alice"] and len(rep["keys"]) == 5
        raw = [r["model_pvalue"] for r in rep["keys"]]
        expected = metrics.holm(raw) if correction == "holm" else metrics.bonferroni(raw)
        assert [r["adjusted_pvalue"] for r in rep["keys"]] == pytest.approx(expected)
        assert rep["multiple_testing"]["family_wise_fpr"] == pytest.approx(2e-6)
        assert {r["owner_id"]: r["verdict"] for r in rep["keys"]}["bob"] == "not shown"
    out = ws / "rep-many-random"
    status, _, _ = run_cli(["--images", str(dirs["random"]), "--keys", str(kdir), "--output", str(out)], capsys)
    assert status == 1 and report_of(out)["owned_by"] == []


# ---------------------------------------------------------------------------------------------- empirical null
def test_calibrate_stores_the_null_and_verify_uses_the_stricter_threshold(alice, dirs, ws, capsys):
    key = ws / "calib" / "alice.gskey"
    key.parent.mkdir()
    shutil.copy(alice["path"], key)
    original = key.read_bytes()
    out = ws / "rep-calib"
    # 44 of 48 bits: owned against the binomial alone (>= 41)
    status, _, _ = run_cli(["--images", str(dirs["near44"]), "--key", str(key), "--output", str(out)], capsys)
    assert status == 0
    # a null in which unmarked views reach 44 matches: the empirical threshold (45) is stricter
    status, stdout, _ = run_cli(
        ["calibrate", "--key", str(key), "--images", str(dirs["near44"]), "--random-images", "32"], capsys
    )
    assert status == 0, stdout
    assert "calibrated" in stdout and "empirical 45" in stdout
    # the null says how many distinct sources it rests on (views of one source are not independent)
    assert "from 0 distinct models, 1 image folders and 32 synthetic random images" in stdout
    assert (key.parent / "alice.gskey.bak").read_bytes() == original
    loaded = OwnerKey.load(key)  # rewritten with its HMAC recomputed under the key's secret
    assert len(loaded.null["matches"]) == 6 + 32 and max(loaded.null["matches"]) == 44
    assert {s["kind"] for s in loaded.null["sources"]} == {"images", "random"}
    status, stdout, _ = run_cli(["--images", str(dirs["near44"]), "--key", str(key), "--output", str(out)], capsys)
    assert status == 1, stdout
    r = report_of(out)["keys"][0]
    assert r["thresholds"]["theoretical"] == 41 and r["thresholds"]["empirical"] == 45 and r["thresholds"]["used"] == 45
    assert r["empirical_null"]["n"] == 38 and r["empirical_null"]["max_matches"] == 44
    assert "empirical 45" in stdout and "theoretical 41" in stdout
    # the marked images still pass the stricter threshold
    status, _, _ = run_cli(["--images", str(dirs["marked"]), "--key", str(key), "--output", str(out)], capsys)
    assert status == 0
    # --append adds to the stored null; a chance-level null keeps the binomial threshold
    run_cli(["calibrate", "--key", str(key), "--random-images", "8", "--append", "--no-base"], capsys)
    assert len(OwnerKey.load(key).null["matches"]) == 46
    run_cli(["calibrate", "--key", str(key), "--random-images", "64", "--no-base"], capsys)
    assert len(OwnerKey.load(key).null["matches"]) == 64
    run_cli(["--images", str(dirs["near44"]), "--key", str(key), "--output", str(out)], capsys)
    t = report_of(out)["keys"][0]["thresholds"]
    assert t["empirical"] < 41 and t["used"] == 41
    status, _, err = run_cli(["calibrate", "--key", str(key), "--random-images", "0", "--no-base"], capsys)
    assert status == 2 and "no unmarked view" in one_error_line(err)


# ---------------------------------------------------------------------------------------------- bad input
def test_key_errors_wrong_format_version_tampered_missing(alice, dirs, ws, capsys):
    bad = ws / "badkeys"
    bad.mkdir()
    payload = torch.load(alice["path"], weights_only=True)
    wrong_format = dict(payload, format="something-else")
    torch.save(wrong_format, bad / "format.gskey")
    wrong_version = dict(payload, version=99)
    wrong_version["fingerprint"] = fingerprint(wrong_version)
    torch.save(wrong_version, bad / "version.gskey")
    tampered = dict(payload, message=1 - payload["message"])  # HMAC kept: must fail
    torch.save(tampered, bad / "tampered.gskey")
    forged = dict(tampered)  # the unkeyed fingerprint recomputed, as older keys' check accepted: must fail too
    forged["fingerprint"] = fingerprint(forged)
    torch.save(forged, bad / "forged.gskey")
    (bad / "text.gskey").write_text("not a key")
    expect = {
        "format.gskey": "wrong format",
        "version.gskey": "version 99",
        "tampered.gskey": "integrity check",
        "forged.gskey": "integrity check",
        "text.gskey": "not a readable",
        "missing.gskey": "does not exist",
    }
    for name, words in expect.items():
        status, stdout, err = run_cli(
            ["--images", str(dirs["marked"]), "--key", str(bad / name), "--output", str(ws / "rep-bad")], capsys
        )
        assert status == 2 and words in one_error_line(err) and "VERDICT" not in stdout, (name, err)
    # a tampered key among many stops the run (the family of keys must be intact)
    status, _, err = run_cli(
        ["--images", str(dirs["marked"]), "--keys", str(bad), "--output", str(ws / "rep-bad")], capsys
    )
    assert status == 2
    status, _, err = run_cli(
        ["--images", str(dirs["marked"]), "--keys", str(ws / "marked"), "--output", str(ws / "rep-bad")], capsys
    )
    assert status == 2 and "no *.gskey" in one_error_line(err)


def test_bad_images_are_skipped_with_reasons_or_refused(alice, dirs, ws, capsys):
    m = alice["message"]
    mixed = ws / "mixed"
    (mixed / "sub").mkdir(parents=True)
    img = bit_image(m, seed=3)
    write_image(mixed / "rgb8.png", img)
    write_image(mixed / "gray16.png", img.mean(axis=-1), "uint16")  # grayscale, 16 bit
    rgba = np.concatenate([img, np.ones_like(img[..., :1])], axis=-1)
    rgba[:4, :4, 3] = 0.0  # a transparent corner, composited on white
    write_image(mixed / "rgba.png", rgba)
    write_image(mixed / "sub" / "hdr.exr", img * 1.5, "half")  # float, out of [0, 1]: clamped
    write_image(mixed / "tiny.png", np.full((1, 1, 3), 0.5, np.float32))  # 1 x 1
    write_big_png(mixed / "huge.png", 20000, m)  # 20000 x 20000: streamed area downscale
    (mixed / "notes.txt").write_text("not an image")
    (mixed / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + os.urandom(200))
    out = ws / "rep-mixed"
    status, stdout, _ = run_cli(["--images", str(mixed), "--key", str(alice["path"]), "--output", str(out)], capsys)
    assert status == 0, stdout
    rep = report_of(out)
    skipped = {s["name"]: s["reason"] for s in rep["input"]["skipped"]}
    assert set(skipped) == {"tiny.png", "notes.txt", "corrupt.png"}, skipped
    assert "too small" in skipped["tiny.png"] and "not an image" in skipped["notes.txt"]
    views = {v["name"]: v for v in rep["keys"][0]["per_view"]}
    assert set(views) == {"rgb8.png", "gray16.png", "rgba.png", "sub/hdr.exr", "huge.png"}
    assert all(v["matches"] >= 46 for v in views.values()), {k: v["matches"] for k, v in views.items()}
    assert "grayscale" in views["gray16.png"]["note"] and "uint16" in views["gray16.png"]["note"]
    assert "alpha" in views["rgba.png"]["note"] and "clamped" in views["sub/hdr.exr"]["note"]
    assert "downscaled from 20000x20000" in views["huge.png"]["note"]
    assert "3 skipped" in stdout
    # a pixel guard below the huge image's size: a documented skip, read from the header only
    status, _, _ = run_cli(
        ["--images", str(mixed), "--key", str(alice["path"]), "--output", str(out), "--max-pixels", "100000000"], capsys
    )
    assert "too large" in {s["name"]: s["reason"] for s in report_of(out)["input"]["skipped"]}["huge.png"]
    # nothing usable: one line, exit 2, no verdict
    junk = ws / "junk"
    junk.mkdir()
    shutil.copy(mixed / "notes.txt", junk)
    shutil.copy(mixed / "tiny.png", junk)
    empty = ws / "empty"
    empty.mkdir()
    for folder, words in ((junk, "no usable image"), (empty, "holds no files"), (ws / "nope", "does not exist")):
        status, stdout, err = run_cli(
            ["--images", str(folder), "--key", str(alice["path"]), "--output", str(ws / "rep-junk")], capsys
        )
        assert status == 2 and words in one_error_line(err) and "VERDICT" not in stdout


def test_usage_errors_and_help(alice, dirs, ws, capsys):
    for argv, words in (
        (["--key", str(alice["path"])], "exactly one input"),
        (["--images", str(dirs["marked"]), "--load-config", "x.yml", "--key", str(alice["path"])], "exactly one input"),
        (["--images", str(dirs["marked"])], "no owner key"),
        (["--images", str(dirs["marked"]), "--key", str(alice["path"]), "--fpr", "0.7"], "--fpr"),
        (["--load-config", str(ws / "nope.yml"), "--key", str(alice["path"])], "does not exist"),
    ):
        status, _, err = run_cli([*argv, "--output", str(ws / "rep-usage")], capsys)
        assert status == 2 and words in one_error_line(err), (argv, err)
    status, stdout, _ = run_cli(["--help"], capsys)
    assert status == 0 and all(sub in stdout for sub in ("verify", "calibrate", "export-key", "commit"))
    status, stdout, _ = run_cli(["verify", "--help"], capsys)
    assert status == 0 and "--images" in stdout and "--keys" in stdout
    status, _, _ = run_cli([], capsys)
    assert status == 2  # no subcommand and no input: a usage error, not a verdict
    status, stdout, _ = run_cli(["calibrate", "--help"], capsys)
    assert status == 0 and "--random-images" in stdout and "--append" in stdout


@pytest.mark.slow  # starts subprocesses
def test_console_script_exit_codes(alice, dirs, ws):
    script = BIN / "ns-verify-owner"
    if not script.exists():
        pytest.fail(f"console script ns-verify-owner is not installed next to {sys.executable} (pip install -e .)")
    env = dict(os.environ, OMP_NUM_THREADS="1", GSTICKER_NO_DOWNLOAD="1")
    for folder, code, first in ((dirs["marked"], 0, "VERDICT: OWNED"), (dirs["random"], 1, "VERDICT: NOT SHOWN")):
        proc = subprocess.run(
            [
                str(script),
                "--images",
                str(folder),
                "--key",
                str(alice["path"]),
                "--output",
                str(ws / "rep-script"),
                "--no-progress",
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
        )
        assert proc.returncode == code and proc.stdout.startswith(first), proc.stdout + proc.stderr
    proc = subprocess.run(
        [str(script), "verify", "--images", str(ws / "nope"), "--key", str(alice["path"])],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert proc.returncode == 2 and one_error_line(proc.stderr)


# ---------------------------------------------------------------------------------------------- real runs (slow)
MESSAGE = TINY_MESSAGE


@pytest.fixture(scope="module")
def real_runs(tiny_sticker, ws) -> dict:
    """The session's 2-step nerfacto base and 10-step geometrysticker run on it (real ns-train, on the CPU), with
    this module's own copy of the key."""
    return {**tiny_sticker, "key": copy_key(tiny_sticker["key"], ws / "keys")}


def _check_model_report(rep: dict, n_views: int) -> dict:
    assert rep["input"]["kind"] == "model" and rep["input"]["views"] == n_views
    d = rep["input"]["details"]
    assert d["own_cameras"] + d["sampled_poses"] == n_views and d["sampled_poses"] >= n_views // 2
    (r,) = rep["keys"]
    assert r["views"] == n_views and len(r["per_view"]) == n_views
    for v in r["per_view"]:
        assert 0 <= v["matches"] <= 48 and 0.0 <= v["bit_accuracy"] <= 1.0 and 0.0 < v["pvalue"] <= 1.0
        assert len(v["decoded"]) == 48
        if rep["decoder"]["kind"] == "extractor":
            assert 0.0 <= v["score"] <= 1.0
        else:  # the classifier reads images; the geometric decoder does not use it
            assert v["score"] is None and v["geometry"]["rays"] > 0
        assert v["pvalue"] == pytest.approx(direct_tail(v["matches"]), rel=1e-9)
    assert 0.0 < r["model_pvalue"] <= 1.0 and 0.0 <= r["share_passing"] <= 1.0
    assert rep["verdict"] in ("owned", "not shown")
    return r


@pytest.mark.slow
def test_real_watermarked_run_is_owned_by_geometric_decoding(real_runs, ws, capsys):
    """The default decoder for a model (the key is version 2, its base is here): informed, from the geometry."""
    out = ws / "rep-real-geometry"
    status, stdout, err = run_cli(
        [
            "--load-config",
            str(real_runs["run"]),
            "--key",
            str(real_runs["key"]),
            "--output",
            str(out),
            "--num-views",
            "8",
        ],
        capsys,
    )
    assert status == 0 and stdout.startswith("VERDICT: OWNED"), err[-2000:]
    rep = report_of(out)
    assert rep["decoder"]["kind"] == "geometry" and "informed" in stdout
    r = _check_model_report(rep, 8)
    assert r["verdict"] == "owned" and r["matches_min"] >= 41
    out_b = ws / "rep-real-geometry-base"
    status, _, _ = run_cli(
        [
            "--load-config",
            str(real_runs["base"]),
            "--key",
            str(real_runs["key"]),
            "--output",
            str(out_b),
            "--num-views",
            "8",
        ],
        capsys,
    )
    assert status == 1
    assert _check_model_report(report_of(out_b), 8)["matches_max"] < 41


def _check_extractor_at_chance(rep: dict, n_views: int) -> dict:
    """The blind extractor's answer on a tiny run: "not shown", no view at the threshold, the median at chance."""
    assert rep["decoder"]["kind"] == "extractor" and rep["verdict"] == "not shown"
    r = _check_model_report(rep, n_views)
    m = sorted(v["matches"] for v in r["per_view"])
    # 12..36 of 48: chance (24) +- 3.5 binomial standard deviations; far below the verdict's threshold (41)
    assert r["verdict"] == "not shown" and r["views_passing"] == 0 and max(m) < r["thresholds"]["used"], m
    assert 12 <= m[len(m) // 2] <= 36, m
    return r


@pytest.mark.slow
def test_real_watermarked_run_end_to_end(real_runs, ws, capsys):
    """The blind extractor on renders (--decode extractor) of a 10-step run, which it cannot read yet: exactly
    "not shown" (exit 1) at chance, on the watermarked run and on its unmarked base alike; report files written."""
    out = ws / "rep-real"
    status, stdout, err = run_cli(
        [
            "--load-config",
            str(real_runs["run"]),
            "--key",
            str(real_runs["key"]),
            "--output",
            str(out),
            "--decode",
            "extractor",
        ],
        capsys,
    )
    assert status == 1 and stdout.startswith("VERDICT: NOT SHOWN"), stdout[-2000:] + err[-2000:]
    rep = report_of(out)
    _check_extractor_at_chance(rep, 24)
    assert rep["input"]["details"]["method"] == "geometrysticker" and rep["input"]["details"]["sticker"] == "on"
    assert (out / "report.png").is_file()
    # the stock base (nerfacto, never marked) with the run's key: not shown
    out_b = ws / "rep-real-base"
    status, _, _ = run_cli(
        [
            "--load-config",
            str(real_runs["base"]),
            "--key",
            str(real_runs["key"]),
            "--output",
            str(out_b),
            "--num-views",
            "8",
            "--decode",
            "extractor",
        ],
        capsys,
    )
    assert status == 1
    _check_extractor_at_chance(report_of(out_b), 8)


@pytest.mark.slow
def test_real_run_calibrate_missing_checkpoint_and_other_scene(real_runs, ws, tiny_scene, capsys):
    key = ws / "real-calib.gskey"
    shutil.copy(real_runs["key"], key)
    status, stdout, err = run_cli(
        [
            "calibrate",
            "--key",
            str(key),
            "--num-views",
            "4",
            "--random-images",
            "8",
            "--images",
            str(tiny_scene / "test"),
        ],
        capsys,
    )
    assert status == 0, err
    null = OwnerKey.load(key).null
    # 4 base views + the test folder's 2 renders and 2 depth EXRs (any image OpenImageIO reads) + 8 random
    assert len(null["matches"]) == 4 + 4 + 8 and null["sources"][0]["kind"] == "model"
    assert null["sources"][0]["details"]["method"] == "gsticker-nerfacto-small"  # the key's recorded base
    status, _, _ = run_cli(
        [
            "--images",
            str(tiny_scene / "train"),
            "--key",
            str(key),
            "--decode",
            "extractor",  # the decoder calibrate measured (auto would search the images' cameras for the image decoder)
            "--output",
            str(ws / "rep-real-other"),
        ],
        capsys,
    )
    assert status == 1
    t = report_of(ws / "rep-real-other")["keys"][0]["thresholds"]
    assert t["used"] == max(t["theoretical"], t["empirical"])
    # a run whose checkpoint is missing: one line, exit 2
    import yaml

    moved = ws / "moved-run"
    moved.mkdir()
    cfg = yaml.load(real_runs["run"].read_text(), Loader=yaml.Loader)
    cfg.output_dir = moved / "elsewhere"
    (moved / "config.yml").write_text(yaml.dump(cfg))
    status, stdout, err = run_cli(
        ["--load-config", str(moved / "config.yml"), "--key", str(key), "--output", str(ws / "rep-moved")], capsys
    )
    assert status == 2 and "no checkpoint" in one_error_line(err) and "VERDICT" not in stdout


@pytest.mark.slow
@pytest.mark.parametrize("edit", ["palette", "hue"])
def test_real_recolored_runs(real_runs, ws, capsys, edit):
    """Runs recolored with ``ns-recolor`` (console script) keep their verdicts: owned by geometric decoding (every
    view >= 41 of 48), "not shown" at chance by the blind extractor, as for the source run. A failing
    ``ns-recolor`` fails the test."""
    script = BIN / "ns-recolor"
    if not script.exists():
        pytest.fail(f"console script ns-recolor is not installed next to {sys.executable} (pip install -e .)")
    env = dict(os.environ, OMP_NUM_THREADS="1", GSTICKER_NO_DOWNLOAD="1", PYTHONWARNINGS="ignore")
    args = ["--set", "0=blue"] if edit == "palette" else ["--shift", "0.25"]
    out_dir = ws / f"recolored-{edit}"
    proc = subprocess.run(
        [str(script), edit, "--load-config", str(real_runs["run"]), "--output-dir", str(out_dir), *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, f"ns-recolor {edit} failed: {proc.stdout[-1500:]}{proc.stderr[-1500:]}"
    (cfg,) = out_dir.glob("**/config.yml")
    out = ws / f"rep-recolored-{edit}"
    status, stdout, err = run_cli(
        ["--load-config", str(cfg), "--key", str(real_runs["key"]), "--output", str(out), "--num-views", "8"], capsys
    )
    assert status == 0 and stdout.startswith("VERDICT: OWNED"), err[-2000:]  # geometric decoding (the default)
    r = _check_model_report(report_of(out), 8)
    assert report_of(out)["decoder"]["kind"] == "geometry" and r["matches_min"] >= 41
    status, stdout, err = run_cli(
        [
            "--load-config",
            str(cfg),
            "--key",
            str(real_runs["key"]),
            "--output",
            str(out),
            "--num-views",
            "8",
            "--decode",
            "extractor",
        ],
        capsys,
    )
    assert status == 1 and stdout.startswith("VERDICT: NOT SHOWN"), stdout[-2000:] + err[-2000:]
    _check_extractor_at_chance(report_of(out), 8)


def test_load_run_keeps_stock_nerfacto_in_process(shared_dir):
    """A stock nerfacto run (ParallelDataManager) is loaded with nerfstudio's in-process data manager: no worker
    process samples training rays for verification, and its cameras and ground truth are the run's own."""
    import multiprocessing

    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager
    from nerfstudio.data.datamanagers.parallel_datamanager import ParallelDataManager

    assert RUNS.spawns_workers(ParallelDataManager) and not RUNS.spawns_workers(VanillaDataManager)
    config = shared_dir / "checkpoints" / "lego100-nerfacto-small" / "nerfacto" / "base" / "config.yml"
    _, pipe, ckpt = RUNS.load_run(config, data=shared_dir / "data" / "lego100", device=torch.device("cpu"))
    dm = pipe.datamanager
    assert type(dm) is VanillaDataManager and ckpt.name.startswith("step-")
    assert not multiprocessing.active_children()
    assert len(dm.train_dataset) == 100 and len(dm.eval_dataset) == 200  # test mode: the test split
    assert dm.eval_dataset[0]["image"].shape[:2] == (100, 100)


def test_a_field_mark_key_is_read_by_the_geometric_decoder_from_a_model_and_the_image_decoder_from_images(tmp_path):
    from conftest import field_mark_key, small_key

    from gsticker_plugin.errors import GStickerError
    from gsticker_plugin.verify.check import choose_decoder
    from gsticker_plugin.verify.configs import VerifyConfig

    field = [(tmp_path / "f.gskey", field_mark_key())]
    model = VerifyConfig(load_config=tmp_path / "config.yml", key=tmp_path / "f.gskey")
    assert choose_decoder(model, field) == ("geometry", [])
    assert choose_decoder(VerifyConfig(images=tmp_path, key=tmp_path / "f.gskey"), field) == ("image", [])
    cases = [
        (VerifyConfig(images=tmp_path, decode="geometry"), field, "image decoder from images: drop --decode geometry"),
        (VerifyConfig(images=tmp_path, decode="extractor"), field, "drop --decode extractor"),
        (VerifyConfig(load_config=tmp_path / "c.yml", decode="extractor"), field, "drop --decode extractor"),
        (VerifyConfig(load_config=tmp_path / "c.yml", decode="image"), field, "drop --decode image"),
        (VerifyConfig(load_config=tmp_path / "c.yml"), field + [(tmp_path / "s.gskey", small_key())], "apart"),
    ]
    for config, keys, fix in cases:
        with pytest.raises(GStickerError, match=fix):
            choose_decoder(config, keys)
