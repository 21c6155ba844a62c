"""Every background Nerfstudio's RGB renderer supports: the re-compositing of cached samples (fast path, gate
calibration, image decoder) equals the host renderer's, and a tiny nerfacto base with stock nerfacto's ``last_sample``
or with ``random`` background is watermarked, palette-recolored and verified end to end."""

from __future__ import annotations

from pathlib import Path
from typing import Dict

import pytest
import torch
from conftest import CPU_ARGS, NERFACTO_TINY, TINY_MESSAGE, TINY_POOL_ARGS, run_parallel
from nerfstudio.model_components.renderers import RGBRenderer

from gsticker_plugin.background import Background, background_of
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.sticker import composite, render_weights
from gsticker_plugin.verify import cli as V

BACKGROUNDS = ("last_sample", "random")


@pytest.mark.parametrize("spec", ["white", "black", "random", "last_sample", "color"])
def test_composite_equals_nerfstudios_renderer_in_eval_mode(spec):
    """The fast path's quadrature + background is what ``RGBRenderer`` (eval mode, as every render gsticker reads)
    returns: ``random`` adds no background (black), ``last_sample`` each ray's last sample colour."""
    g = torch.Generator().manual_seed(0)
    density = torch.rand(64, 12, 1, generator=g) * 3
    deltas = torch.rand(64, 12, 1, generator=g) * 0.1
    rgb = torch.rand(64, 12, 3, generator=g)
    host = torch.tensor([0.2, 0.5, 0.9]) if spec == "color" else spec
    renderer = RGBRenderer(background_color=host).eval()
    expected = renderer(rgb=rgb, weights=render_weights(density, deltas))
    ours, _ = composite(density, rgb, deltas, Background.of(host))
    assert torch.allclose(ours.clamp(0, 1), expected, atol=1e-6), (ours - expected).abs().max()
    if spec in ("random", "last_sample"):  # not white: the background really differs
        white, _ = composite(density, rgb, deltas, Background.of("white"))
        assert float((white - ours).abs().max()) > 1e-2


def test_unknown_background_names_the_choices():
    with pytest.raises(GStickerError, match="one of white, black, random, last_sample"):
        Background.of("transparent")


@pytest.fixture(scope="module")
def runs(tiny_scene: Path, tmp_path_factory) -> Dict[str, Dict[str, Path]]:
    """Per background: a 2-step tiny nerfacto base and a 10-step geometrysticker run on it (the two concurrently)."""
    ws = tmp_path_factory.mktemp("backgrounds")
    bases = [
        [
            "ns-train",
            *NERFACTO_TINY,
            *CPU_ARGS,
            "--pipeline.model.background-color",
            bg,
            "--output-dir",
            str(ws),
            "--experiment-name",
            bg,
            "--timestamp",
            "base",
            "--max-num-iterations",
            "2",
            "--steps-per-save",
            "2",
            "blender-data",
            "--data",
            str(tiny_scene),
        ]
        for bg in BACKGROUNDS
    ]
    out: Dict[str, Dict[str, Path]] = {}
    for bg, proc in zip(BACKGROUNDS, run_parallel([_bin(c) for c in bases], ws / "logs-base")):
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
        base = ws / bg / "gsticker-nerfacto-small" / "base"
        out[bg] = {"base": base / "config.yml", "ckpt": max((base / "nerfstudio_models").glob("step-*.ckpt"))}
    stickers = [
        [
            "ns-train",
            "geometrysticker",
            "--load-checkpoint",
            str(out[bg]["ckpt"]),
            *CPU_ARGS,
            "--output-dir",
            str(ws),
            "--experiment-name",
            bg,
            "--timestamp",
            "wm",
            "--max-num-iterations",
            "10",
            *TINY_POOL_ARGS,
            "--pipeline.message",
            TINY_MESSAGE,
            "--pipeline.key-path",
            str(ws / "keys" / f"{bg}.gskey"),
        ]
        for bg in BACKGROUNDS
    ]
    for bg, proc in zip(BACKGROUNDS, run_parallel([_bin(c) for c in stickers], ws / "logs-wm")):
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
        out[bg]["run"] = ws / bg / "geometrysticker" / "wm" / "config.yml"
        out[bg]["key"] = ws / "keys" / f"{bg}.gskey"
    out["_ws"] = {"dir": ws}
    return out


def _bin(cmd):
    import sys

    return [str(Path(sys.executable).parent / cmd[0]), *cmd[1:]]


@pytest.mark.parametrize("bg", BACKGROUNDS)
def test_fast_path_renders_what_the_model_renders_on_its_background(runs, bg):
    """The sticker is trained on cached samples re-composited on the base's background: equal to the real render
    (the marked samples included), and not what a white background would give."""
    from nerfstudio.utils.eval_utils import eval_setup

    from gsticker_plugin.fastpath import cache_view, render_cached
    from gsticker_plugin.key import OwnerKey

    _, pipeline, _, _ = eval_setup(runs[bg]["run"], test_mode="val")
    pipeline.restore_owner(OwnerKey.load(runs[bg]["key"]), heads=False)
    model = pipeline.model
    assert background_of(model).name == bg and model.background_color().name == bg
    camera = pipeline.datamanager.train_dataset.cameras[1:2]
    with torch.no_grad():
        view = cache_view(model, camera, False)
        fast, _ = render_cached(view, model.final_wrap, model.message, model.background_color())
        on_white, _ = render_cached(view, model.final_wrap, model.message, Background.of("white"))
        real = model.get_outputs_for_camera(camera)
        with model.sticker_enabled(False):
            clean = model.get_outputs_for_camera(camera)
    assert float((real["accumulation"] - clean["accumulation"]).abs().max()) > 1e-4  # the sticker marks these rays
    assert float((fast - real["rgb"]).abs().max()) < 2e-3, float((fast - real["rgb"]).abs().max())
    assert float((on_white - real["rgb"]).abs().max()) > 5e-3  # the background matters in this view


@pytest.mark.parametrize("bg", BACKGROUNDS)
def test_watermarked_and_recolored_runs_are_owned_and_the_base_is_not(runs, bg, capsys):
    """ns-train geometrysticker -> ns-recolor palette -> ns-verify-owner on a base with this background."""
    from gsticker_plugin.recolor import cli as recolor

    ws = runs["_ws"]["dir"]
    dest = ws / f"recolored-{bg}"
    assert (
        recolor.run(["palette", "--set", "0=blue", "--load-config", str(runs[bg]["run"]), "--output-dir", str(dest)])
        == 0
    )
    (recolored,) = dest.glob("**/config.yml")
    capsys.readouterr()
    for suspect, status_expected in ((runs[bg]["run"], 0), (recolored, 0), (runs[bg]["base"], 1)):
        out = ws / f"rep-{bg}-{suspect.parent.name}-{status_expected}"
        argv = ["--load-config", str(suspect), "--key", str(runs[bg]["key"]), "--output", str(out), "--num-views", "4"]
        status = V.main([*argv, "--no-progress"])
        stdout = capsys.readouterr().out
        assert status == status_expected, (suspect, stdout[-2000:])
        first = "VERDICT: OWNED" if status_expected == 0 else "VERDICT: NOT SHOWN"
        assert stdout.startswith(first), stdout[:300]
