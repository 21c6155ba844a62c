"""``ns-recolor`` on tiny scenes, on the CPU.

Over 600 lines on purpose: the tests share bases trained once per module (module fixtures).

Bases (trained once per module by the real ``ns-train``, concurrently): a TensoRF trained 300 steps (it learns
the scene's red/green/blue objects, so edits can be measured), 2-step nerfacto and vanilla-nerf (for the
per-model mechanics), and a 3-step ``geometrysticker`` run on the TensoRF (watermarked vs unwatermarked).
Recolor commands run in this process (``gsticker_plugin.recolor.cli.run``), plus once through the console script.

Checked: palette extraction is deterministic and finds the scene's dominant colors; an edit moves only the chosen
region (measured: hue error in the region, PSNR outside it); density and geometry outputs are bit-identical
before and after recolor (per model type); recolored runs load through Nerfstudio's ``eval_setup`` (and
``ns-render``), with live viewer controls; the same edit on a watermarked and an unwatermarked model differs
only by the watermark; the fine-tune changes only color parameters; bad input gives one ``error:`` line.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Dict, List

import pytest
import torch
from conftest import TINY_POOL_ARGS, console_script, run_parallel, subprocess_env

from gsticker_plugin.errors import GStickerError

BIN = Path(sys.executable).parent
MESSAGE = "101100111000111100001111100000111111000000111111"
COMMON = ["--machine.device-type", "cpu", "--vis", "tensorboard"]
BASE_ARGS: Dict[str, List[str]] = {
    "tensorf": [
        "gsticker-tensorf-small",
        "--pipeline.model.init-resolution",
        "32",
        "--pipeline.model.num-samples",
        "32",
        "--pipeline.model.num-uniform-samples",
        "16",
        "--pipeline.datamanager.train-num-rays-per-batch",
        "256",
        "--max-num-iterations",
        "300",
        "--steps-per-save",
        "300",
    ],
    "nerfacto": [
        "gsticker-nerfacto-small",
        "--pipeline.model.num-nerf-samples-per-ray",
        "16",
        "--pipeline.model.num-proposal-samples-per-ray",
        "32",
        "16",
        "--pipeline.datamanager.train-num-rays-per-batch",
        "256",
        "--max-num-iterations",
        "2",
        "--steps-per-save",
        "2",
    ],
    "vanilla-nerf": [
        "vanilla-nerf",
        "--pipeline.model.num-coarse-samples",
        "16",
        "--pipeline.model.num-importance-samples",
        "16",
        "--pipeline.datamanager.train-num-rays-per-batch",
        "256",
        "--pipeline.model.eval-num-rays-per-chunk",
        "1024",
        "--max-num-iterations",
        "2",
        "--steps-per-save",
        "2",
    ],
}
BASES = ("tensorf", "nerfacto", "vanilla-nerf")


def _fail(proc) -> str:
    return f"exit {proc.returncode}\n--- stdout ---\n{proc.stdout[-3000:]}\n--- stderr ---\n{proc.stderr[-3000:]}"


def recolor(*argv: str) -> None:
    """ns-recolor in this process."""
    from gsticker_plugin.recolor import cli

    assert cli.run([str(a) for a in argv]) == 0


def run_config(out: Path) -> Path:
    (cfg,) = list(out.glob("*/*/*/config.yml"))
    return cfg


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.float() - b.float()) ** 2).mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


# ---------------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("recolor")


@pytest.fixture(scope="module")
def runs(tiny_scene: Path, work: Path) -> Dict[str, Path]:
    """{base: RUN/config.yml} for the three bases, and "gs": a geometrysticker run on the TensoRF."""
    out = work / "bases"
    cmds = [
        [
            str(console_script("ns-train")),
            *BASE_ARGS[b],
            *COMMON,
            "--output-dir",
            str(out),
            "--experiment-name",
            b,
            "--timestamp",
            "base",
            "blender-data",
            "--data",
            str(tiny_scene),
        ]
        for b in BASES
    ]
    found: Dict[str, Path] = {}
    for b, proc in zip(BASES, run_parallel(cmds, work / "logs")):
        assert proc.returncode == 0, f"ns-train {b}: {_fail(proc)}"
        (found[b],) = list((out / b).glob("*/base/config.yml"))
    ckpt = sorted((found["tensorf"].parent / "nerfstudio_models").glob("*.ckpt"))[-1]
    gs = [
        str(console_script("ns-train")),
        "geometrysticker",
        "--load-checkpoint",
        str(ckpt),
        *COMMON,
        "--output-dir",
        str(work / "gs"),
        "--experiment-name",
        "gs",
        "--timestamp",
        "run",
        "--max-num-iterations",
        "3",
        "--pipeline.message",
        MESSAGE,
        *TINY_POOL_ARGS,
    ]
    (proc,) = run_parallel([gs], work / "logs-gs")
    assert proc.returncode == 0, f"ns-train geometrysticker: {_fail(proc)}"
    found["gs"] = work / "gs" / "gs" / "geometrysticker" / "run" / "config.yml"
    return found


_LOADED: Dict[str, object] = {}


def load(config: Path):
    """Stock eval_setup (what ns-viewer / ns-render use), cached per config."""
    from nerfstudio.utils.eval_utils import eval_setup

    key = str(config)
    if key not in _LOADED:
        _, pipeline, _, _ = eval_setup(Path(config), test_mode="inference")
        _LOADED[key] = pipeline
    return _LOADED[key]


@torch.no_grad()
def render(pipeline, n: int = 3, keys=("rgb", "depth", "accumulation")) -> Dict[str, torch.Tensor]:
    cams = pipeline.datamanager.train_dataparser_outputs.cameras
    outs = [pipeline.model.get_outputs_for_camera(cams[i : i + 1]) for i in range(n)]
    res = {}
    for k in keys:
        kk = k if k in outs[0] else f"{k}_fine"
        res[k] = torch.stack([o[kk] for o in outs])
    if "sticker_delta" in outs[0]:
        res["sticker_delta"] = torch.stack([o["sticker_delta"] for o in outs])
    return res


def dataset_palette(tiny_scene: Path, k=None):
    import numpy as np
    from PIL import Image

    from gsticker_plugin.recolor import palette as P

    ims = [
        torch.from_numpy(np.asarray(Image.open(p))).float() / 255
        for p in sorted((tiny_scene / "train").glob("r_*.png"))
        if not p.stem.endswith("depth")
    ]
    px = torch.cat([im[..., :3][im[..., 3] > 0.5] for im in ims])
    return P.extract_palette(px, k=k), px


def index_near(pal, rgb) -> int:
    from gsticker_plugin.recolor.bench import hue_distance_deg, lch_hue_deg

    hue = lch_hue_deg(torch.tensor([rgb]))[0]
    chroma = P_chroma(pal.rgb)
    score = hue_distance_deg(lch_hue_deg(pal.rgb), hue) - 0.2 * chroma
    return int(score.argmin())


def P_chroma(rgb: torch.Tensor) -> torch.Tensor:
    from gsticker_plugin.recolor import palette as P

    lab = P.rgb_to_lab(rgb)
    return lab[..., 1:].norm(dim=-1)


# ---------------------------------------------------------------------------------------------- palette (pure)


def test_palette_is_deterministic_and_finds_the_dominant_colors(tiny_scene):
    from gsticker_plugin.recolor import palette as P
    from gsticker_plugin.recolor.bench import hue_distance_deg, lch_hue_deg

    pal, px = dataset_palette(tiny_scene)
    again = P.extract_palette(px.clone())
    assert P.K_MIN <= pal.k <= P.K_MAX
    assert torch.equal(pal.rgb, again.rgb) and torch.equal(pal.share, again.share)
    assert abs(float(pal.share.sum()) - 1.0) < 1e-5 and bool((pal.share[:-1] >= pal.share[1:]).all())
    # the red sphere, green torus and blue box: one saturated entry each (chroma > 40, hue within 25 degrees)
    hues, chroma = lch_hue_deg(pal.rgb), P_chroma(pal.rgb)
    for name in ("red", "green", "blue"):
        ref = float(lch_hue_deg(torch.tensor([P.parse_color(name)]))[0])
        ok = (hue_distance_deg(hues, ref) < 25) & (chroma > 40)
        assert bool(ok.any()), f"no {name} entry in {pal.describe()}"
    for k in (3, 8):
        assert P.extract_palette(px, k=k).k == k
    assert torch.equal(P.extract_palette(px, k=6).rgb, P.extract_palette(px, k=6).rgb)


def test_palette_of_the_same_pixels_is_extracted_once_per_process(monkeypatch):
    from gsticker_plugin.recolor import palette as P

    g = torch.Generator().manual_seed(0)
    px = torch.cat(
        [
            torch.rand(400, 3, generator=g) * 0.1 + torch.tensor(c)
            for c in ([0.8, 0.1, 0.1], [0.1, 0.7, 0.2], [0.1, 0.2, 0.8], [0.9, 0.9, 0.9])
        ]
    ).clamp(0, 1)
    first = P.extract_palette(px, seed=3)
    calls = []
    real = P._kmeans_palette
    monkeypatch.setattr(P, "_kmeans_palette", lambda *a: calls.append(a) or real(*a))
    again = P.extract_palette(px.clone(), seed=3)
    assert not calls, "the same pixels, k and seed must not run k-means again"
    assert torch.equal(first.rgb, again.rgb) and torch.equal(first.share, again.share) and first.curve == again.curve
    again.rgb[0] = -1.0  # a copy: editing it leaves the remembered palette alone
    assert torch.equal(P.extract_palette(px, seed=3).rgb, first.rgb)
    other = P.extract_palette(px[:-1], seed=3)  # other pixels (or k, or seed): computed
    assert len(calls) == 1 and other.k >= P.K_MIN
    P.extract_palette(px, k=4, seed=3)
    assert len(calls) == 2


def test_color_parsing_presets_and_recolor_identity():
    from gsticker_plugin.recolor import palette as P

    assert P.parse_color("#1E90FF") == P.parse_color("dodger blue") == P.parse_color("DodgerBlue")
    assert P.parse_color("#fff") == (1.0, 1.0, 1.0) and P.parse_color("red") == (1.0, 0.0, 0.0)
    for name in P.PRESET_NAMES:  # the paper's 10 reference colors
        P.parse_color(name)
    assert P.parse_edits(["2=#1E90FF", "0=red"], [], 4) == {2: P.parse_color("#1E90FF"), 0: (1.0, 0.0, 0.0)}
    assert set(P.parse_edits([], ["keep", "blue", "-", "cyan"], 4)) == {1, 3}
    for bad, words in [
        (lambda: P.parse_color("reddish"), "unknown color name"),
        (lambda: P.parse_color("#12G45Z"), "malformed hex"),
        (lambda: P.parse_color("#12345"), "malformed hex"),
        (lambda: P.parse_edits(["5=red"], [], 5), "out of range"),
        (lambda: P.parse_edits(["x=red"], [], 5), "INDEX=COLOR"),
        (lambda: P.parse_edits([], ["red"], 3), "exactly 3"),
        (lambda: P.check_k(9), "outside 3..8"),
        (lambda: P.check_k(2), "outside 3..8"),
    ]:
        with pytest.raises(GStickerError, match=words):
            bad()
    rgb = torch.rand(100, 3)
    lab = P.rgb_to_lab(torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]))
    assert torch.equal(P.recolor(rgb, lab, lab.clone(), 5.0), rgb)  # nothing edited: bit-identical


# ---------------------------------------------------------------------------------------------- palette runs


@pytest.fixture(scope="module")
def palette_edit(runs, work, tiny_scene) -> Dict[str, object]:
    """The red entry set to blue on the TensoRF and on its geometrysticker run (same palette, same edit)."""
    pal, _ = dataset_palette(tiny_scene)
    red = index_near(pal, (1.0, 0.0, 0.0))
    out = {}
    for name in ("tensorf", "gs"):
        recolor(
            "palette", "--load-config", runs[name], "--output-dir", work / f"palette-{name}", "--set", f"{red}=blue"
        )
        out[name] = run_config(work / f"palette-{name}")
    return {"red": red, "palette": pal, **out}


def test_palette_list_prints_and_writes_a_swatch(runs, work, capsys):
    swatch = work / "swatch.png"
    recolor("palette", "--load-config", runs["tensorf"], "--list", "--swatch", swatch)
    out = capsys.readouterr().out
    assert swatch.is_file()
    from PIL import Image

    img = Image.open(swatch)
    k = img.size[0] // 48
    assert 3 <= k <= 8 and img.size[1] == 48
    assert sum(1 for line in out.splitlines() if line.strip()[:2].rstrip(":").isdigit() and "#" in line) == k


def test_edit_moves_only_the_chosen_region(palette_edit, runs):
    """Red entry -> blue: the red region turns blue; the rest (incl. the green torus) stays (measured, tiny TensoRF)."""
    from gsticker_plugin.recolor import palette as P
    from gsticker_plugin.recolor.bench import edit_region, fidelity

    before = render(load(runs["tensorf"]), n=6)
    after = render(load(palette_edit["tensorf"]), n=6)
    pal, red = palette_edit["palette"], palette_edit["red"]
    region = edit_region(before["rgb"], before["accumulation"], pal.lab, red)
    m = fidelity(before["rgb"], after["rgb"], region, before["accumulation"], P.parse_color("blue"))
    print(json.dumps(m, indent=1))
    assert m["region_share"] > 0.01
    assert m["hue_error_before_deg"] > 60 and m["hue_error_deg"] < 15 and m["moved"] > 0.9, m
    assert m["psnr_outside"] > 20.0, m  # measured 22 dB on this 300-step model (docs/recolor.md)
    green = edit_region(before["rgb"], before["accumulation"], pal.lab, index_near(pal, (0.0, 1.0, 0.0)))
    g = fidelity(before["rgb"], after["rgb"], green, before["accumulation"], P.parse_color("blue"))
    assert g["psnr_region"] > 28.0, g  # the green torus is left alone (measured 32 dB)
    # the recolored run records its edit (config) and its palette (buffers) consistently
    model = load(palette_edit["tensorf"]).model
    assert model.config.palette_target[red] == "#0000FF" and torch.equal(
        model.palette_target[red], torch.tensor([0.0, 0, 1])
    )
    assert (Path(palette_edit["tensorf"]).parent / "palette.png").is_file()


def test_recolored_run_loads_with_eval_setup_and_has_live_viewer_controls(palette_edit):
    from nerfstudio.utils.eval_utils import eval_setup
    from nerfstudio.viewer.utils import parse_object
    from nerfstudio.viewer.viewer_elements import ViewerElement, ViewerRGB

    from gsticker_plugin.recolor.model import RecolorModel

    config, pipeline, ckpt, step = eval_setup(Path(palette_edit["tensorf"]), test_mode="test")
    assert config.method_name == "gsticker-palette" and step == 299  # the wrapped run's step (TensoRF grid size)
    model = pipeline.model
    assert isinstance(model, RecolorModel)
    elements = dict(parse_object(pipeline, ViewerElement, "Custom Elements"))
    colors = [e for e in elements.values() if isinstance(e, ViewerRGB)]
    assert len(colors) == len(model.config.palette_source)
    red = palette_edit["red"]
    assert tuple(colors[red].default_value) == (0, 0, 255)
    a = render(pipeline, n=1)["rgb"]
    colors[red].value = (0, 255, 0)  # what the viewer's callback receives
    colors[red].cb_hook(colors[red])
    b = render(pipeline, n=1)["rgb"]
    assert not torch.equal(a, b)
    assert torch.equal(model.palette_target[red], torch.tensor([0.0, 1.0, 0.0]))


@pytest.mark.parametrize("base", BASES)
def test_density_and_geometry_are_bit_identical_after_recolor(runs, work, base):
    from nerfstudio.field_components.field_heads import FieldHeadNames

    from gsticker_plugin.recolor.model import color_fields, unwrap

    out = work / f"hue-{base}"
    recolor("hue", "--load-config", runs[base], "--output-dir", out, "--shift", "0.3")
    results = []
    for cfg in (runs[base], run_config(out)):
        pipeline = load(cfg)
        fields = color_fields(unwrap(pipeline.model))
        assert fields
        records: List[torch.Tensor] = []
        for _, f in fields:
            orig = f.forward

            def fwd(rs, *a, _orig=orig, **k):
                o = _orig(rs, *a, **k)
                records.append(o[FieldHeadNames.DENSITY].detach().clone())
                return o

            object.__setattr__(f, "forward", fwd)
        try:
            r = render(pipeline, n=1)
        finally:
            for _, f in fields:
                del f.__dict__["forward"]
        results.append((r, records))
    (ra, da), (rb, db) = results
    assert len(da) == len(db) and all(torch.equal(x, y) for x, y in zip(da, db)), "density changed"
    assert torch.equal(ra["depth"], rb["depth"]) and torch.equal(ra["accumulation"], rb["accumulation"])
    if base == "tensorf":  # the only trained base: its colors visibly rotate
        assert psnr(ra["rgb"], rb["rgb"]) < 30


def test_model_level_hue_matches_image_level_hue(runs, work):
    from gsticker_plugin.attacks import hue_shift

    out = work / "hue-tensorf"
    if not out.exists():
        recolor("hue", "--load-config", runs["tensorf"], "--output-dir", out, "--shift", "0.3")
    before = render(load(runs["tensorf"]), n=3)
    after = render(load(run_config(out)), n=3)
    image_level = hue_shift(before["rgb"].permute(0, 3, 1, 2), 0.3).permute(0, 2, 3, 1)
    # per-sample rotation then compositing is close to compositing then rotation (not equal: blending)
    assert psnr(after["rgb"], image_level) > 25.0
    assert psnr(after["rgb"], before["rgb"]) < psnr(after["rgb"], image_level) - 5


def test_image_level_hue_jitter_writes_jittered_renders(runs, work):
    out = work / "jitter"
    recolor(
        "hue",
        "--load-config",
        runs["tensorf"],
        "--output-dir",
        out,
        "--image-level",
        "--shift",
        "0.5",
        "--split",
        "train",
        "--limit",
        "4",
        "--seed",
        "3",
    )
    meta = json.loads((out / "hue_jitter.json").read_text())
    shifts = [im["hue_shift_turns"] for im in meta["images"]]
    assert len(shifts) == 4 and all(abs(s) <= 0.5 for s in shifts) and len(set(shifts)) == 4
    assert sorted(p.name for p in out.glob("*.png")) == [f"train_{i:04d}.png" for i in range(4)]


def test_ns_render_renders_a_recolored_run(palette_edit, work):
    out = work / "render"
    proc = subprocess.run(
        [
            str(console_script("ns-render")),
            "dataset",
            "--load-config",
            str(palette_edit["tensorf"]),
            "--split",
            "test",
            "--rendered-output-names",
            "rgb",
            "--output-path",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=subprocess_env(),
        cwd=work,
    )
    assert proc.returncode == 0, _fail(proc)
    assert len(sorted(out.rglob("*.jpg")) + sorted(out.rglob("*.png"))) == 2


def test_same_edit_on_watermarked_and_unwatermarked_differs_only_by_the_watermark(palette_edit):
    plain = render(load(palette_edit["tensorf"]), n=3)
    gs_pipeline = load(palette_edit["gs"])
    marked = render(gs_pipeline, n=3)
    with gs_pipeline.model.sticker_enabled(False):  # delegated to the wrapped geometrysticker model
        unmarked = render(gs_pipeline, n=3)
    for k in ("rgb", "depth", "accumulation"):
        assert torch.equal(unmarked[k], plain[k]), f"{k}: sticker off, the recolored runs differ"
    assert not torch.equal(marked["rgb"], plain["rgb"])  # the watermark is there after the recolor
    touched = marked["sticker_delta"][..., 0] > 0
    diff = (marked["rgb"] - plain["rgb"]).abs().amax(-1)
    # where the sticker touched no sample the images agree (TensoRF re-places a few samples: allow 1 %)
    assert float((diff[~touched] > 1e-5).float().mean()) < 0.01


# ---------------------------------------------------------------------------------------------- fine-tune


@pytest.mark.parametrize("base", ["gs", "nerfacto", "vanilla-nerf"])
def test_finetune_changes_only_color_parameters(runs, work, base):
    out = work / f"finetune-{base}"
    if base == "gs":
        target = ["--set", "0=blue"]
    elif base == "nerfacto":
        target = ["--hue-shift", "0.4"]
    else:  # a folder of edited images: the renders' image-level hue jitter, one per training view, in order
        jit = work / "targets-vanilla"
        recolor(
            "hue",
            "--load-config",
            runs[base],
            "--output-dir",
            jit,
            "--image-level",
            "--fixed",
            "--shift",
            "0.4",
            "--split",
            "train",
        )
        target = ["--targets", str(jit)]
    recolor(
        "finetune",
        "--load-config",
        runs[base],
        "--output-dir",
        out,
        *target,
        "--steps",
        "8",
        "--rays-per-step",
        "256",
        "--lr",
        "1e-2",
    )
    cfg = run_config(out)
    info = json.loads((cfg.parent / "finetune.json").read_text())
    color = {"_model." + n for n in info["color_parameters"]}
    old_ckpt = sorted((Path(runs[base]).parent / "nerfstudio_models").glob("*.ckpt"))[-1]
    old = torch.load(old_ckpt, map_location="cpu", weights_only=False)["pipeline"]
    (new_ckpt,) = list((cfg.parent / "nerfstudio_models").glob("*.ckpt"))
    new = torch.load(new_ckpt, map_location="cpu", weights_only=False)["pipeline"]
    model_keys = {k for k in old if k.startswith("_model.")}
    assert model_keys == set(new), "the fine-tuned run must hold exactly the input run's weights"
    changed = {k for k in model_keys if not torch.equal(old[k], new[k])}
    assert changed and changed <= color, f"non-color weights changed: {sorted(changed - color)}"
    assert not any("density" in k or "mlp_base" in k or "proposal" in k or "sticker" in k for k in color), sorted(color)
    # the fine-tuned run opens with the stock loader, geometry bit-identical, colors changed
    a, b = render(load(runs[base]), n=1), render(load(cfg), n=1)
    assert torch.equal(a["depth"], b["depth"]) and torch.equal(a["accumulation"], b["accumulation"])
    assert not torch.equal(a["rgb"], b["rgb"])
    assert load(cfg).model.__class__ is load(runs[base]).model.__class__


def test_finetune_save_at_writes_the_runs_a_shorter_finetune_writes(runs, work):
    """--save-at N: the snapshot after N of M steps holds the weights of an N-step fine-tune (same seed)."""
    common = ["--load-config", runs["nerfacto"], "--hue-shift", "0.3", "--rays-per-step", "128", "--max-views", "4"]
    recolor("finetune", *common, "--output-dir", work / "ft-long", "--steps", "5", "--save-at", "2", "3")
    recolor("finetune", *common, "--output-dir", work / "ft-short", "--steps", "2")

    def weights(out):
        (ckpt,) = list((run_config(out).parent / "nerfstudio_models").glob("*.ckpt"))
        return torch.load(ckpt, map_location="cpu", weights_only=False)["pipeline"]

    short, snap2, snap3, long = (weights(work / n) for n in ["ft-short", "ft-long-step2", "ft-long-step3", "ft-long"])
    assert set(short) == set(snap2) == set(long)
    assert all(torch.equal(short[k], snap2[k]) for k in short)
    assert any(not torch.equal(snap2[k], snap3[k]) for k in short) and any(
        not torch.equal(snap3[k], long[k]) for k in short
    )
    assert json.loads((run_config(work / "ft-long-step3").parent / "finetune.json").read_text())["steps"] == 3


def test_ray_targets_are_the_full_renders_pixels_and_train_the_same(runs):
    """The fine-tune's targets rendered only at the pixels it visits equal those pixels of full renders, and a
    fine-tune from them matches one from the full images (the images' path draws the same rays)."""
    import copy

    from gsticker_plugin.recolor import runs as R
    from gsticker_plugin.recolor.finetune import RayTargets, finetune_color, ray_schedule, render_ray_targets

    loaded = R.load_run(Path(runs["nerfacto"]), None)
    model, cams = loaded.pipeline.model, loaded.pipeline.datamanager.train_dataset.cameras[:3]
    hw = (int(cams.height[0]), int(cams.width[0]))
    sched = ray_schedule(3, hw, steps=4, rays_per_step=64, seed=5)
    assert sched.shape == (4, 64, 3) and int(sched[..., 0].max()) < 3
    assert int(sched[..., 1].max()) < hw[0] and int(sched[..., 2].max()) < hw[1]
    assert torch.equal(sched, ray_schedule(3, hw, 4, 64, seed=5)) and not torch.equal(
        sched, ray_schedule(3, hw, 4, 64, 6)
    )
    full = torch.stack(R.render_views(model, cams, range(3), progress=False)["rgb"])
    sparse = render_ray_targets(model, cams, sched, chunk=50, progress=False)
    assert torch.allclose(sparse.values, full[sched[..., 0], sched[..., 1], sched[..., 2]], atol=1e-5)
    a, b = copy.deepcopy(model), copy.deepcopy(model)
    ha = finetune_color(a, cams, list(full), 4, rays_per_step=64, seed=5, progress=False)
    hb = finetune_color(b, cams, sparse, 4, rays_per_step=64, seed=5, progress=False)
    assert ha["loss"] == pytest.approx(hb["loss"], rel=1e-4)
    with pytest.raises(GStickerError, match="needs 5 of 64"):
        finetune_color(b, cams, RayTargets(sched, sparse.values), 5, rays_per_step=64, progress=False)


# ---------------------------------------------------------------------------------------------- bad input


BAD = {
    # case: (argv after the subcommand's --load-config RUN, words naming the problem, words naming the fix)
    "unknown-name": (["palette", "--output-dir", "{out}", "--set", "0=reddish"], "unknown color name", "#RRGGBB"),
    "malformed-hex": (["palette", "--output-dir", "{out}", "--set", "0=#12G45Z"], "malformed hex", "#RRGGBB"),
    "index-range": (["palette", "--output-dir", "{out}", "--set", "42=blue"], "out of range", "--list"),
    "k-range": (["palette", "--output-dir", "{out}", "--k", "12", "--set", "0=blue"], "outside 3..8", "--k"),
    "palette-length": (["palette", "--output-dir", "{out}", "--k", "3", "--palette", "red"], "exactly 3", "--set"),
    "no-edit": (["palette", "--output-dir", "{out}"], "no edit given", "--set"),
    "exists": (["hue", "--output-dir", "{exists}"], "exists", "--overwrite"),
    "inside-input": (["hue", "--output-dir", "{run}/recolored", "--overwrite"], "inside the input run", "--output-dir"),
    "is-input": (["hue", "--output-dir", "{run}", "--overwrite"], "never overwritten", "--output-dir"),
    "contains-input": (["hue", "--output-dir", "{base_root}", "--overwrite"], "contains the input run", "--output-dir"),
    "hue-range": (["hue", "--output-dir", "{out}", "--shift", "0.7"], "outside [-0.5, 0.5]", "--shift"),
    "no-targets": (["finetune", "--output-dir", "{out}"], "exactly one kind of target", "--targets"),
    "save-at-range": (
        ["finetune", "--output-dir", "{out}", "--hue-shift", "0.2", "--steps", "4", "--save-at", "4"],
        "must be between 1 and --steps",
        "--output-dir itself",
    ),
    "missing-config": (
        ["hue", "--output-dir", "{out}", "--load-config", "{work}/nowhere/config.yml"],
        "does not exist",
        "--load-config",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_is_one_line_naming_the_fix(runs, work, case, capsys):
    from gsticker_plugin.recolor import cli

    argv, problem, fix = BAD[case]
    exists = work / "exists"
    exists.mkdir(exist_ok=True)
    run_dir = Path(runs["tensorf"]).parent
    paths = {
        "out": work / "bad" / case,
        "exists": exists,
        "run": run_dir,
        "work": work,
        "base_root": run_dir.parent.parent,
    }
    argv = [a.format(**paths) for a in argv]
    if "--load-config" not in argv:
        argv = [argv[0], "--load-config", str(runs["tensorf"]), *argv[1:]]
    before = sorted(p.name for p in run_dir.rglob("*"))
    with pytest.raises(SystemExit) as exc:
        cli.run(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1 and problem in lines[0] and fix in lines[0], err[-2000:]
    assert "Traceback" not in err
    assert not paths["out"].exists()
    assert sorted(p.name for p in run_dir.rglob("*")) == before  # the input run is untouched


def test_model_without_color_output_is_refused():
    from gsticker_plugin.recolor.model import require_color_fields

    with pytest.raises(GStickerError, match="no field with a separable color output"):
        require_color_fields(torch.nn.Sequential(torch.nn.Linear(3, 3)))


def test_bad_input_through_the_console_script(runs, work):
    proc = subprocess.run(
        [
            str(console_script("ns-recolor")),
            "palette",
            "--load-config",
            str(runs["tensorf"]),
            "--output-dir",
            str(work / "bad-script"),
            "--set",
            "0=notacolor",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=subprocess_env(),
        cwd=work,
    )
    assert proc.returncode == 2, _fail(proc)
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "unknown color name" in errors[0], _fail(proc)


def test_companion_methods_are_registered():
    import importlib.metadata

    from nerfstudio.plugins.types import MethodSpecification

    eps = {ep.name: ep for ep in importlib.metadata.entry_points(group="nerfstudio.method_configs")}
    for name in ("gsticker-palette", "gsticker-hue"):
        assert name in eps, f"{name} is not registered (pip install -e .)"
        spec = eps[name].load()
        assert isinstance(spec, MethodSpecification) and spec.config.method_name == name
