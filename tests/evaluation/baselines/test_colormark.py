"""The color-branch baseline (gsticker_plugin/evaluation/baselines/colormark.py): the owner's message in color instead of density.

A generic unit test of the color wrap on a stand-in field first; then real runs on the 32 px tiny scene: a
400-step nerfacto base (fewer steps render r = g = b exactly: the small nerfacto has not learned color yet, and a
hue rotation of gray is the identity), a 10-step ``geometrysticker`` run on it (real ``ns-train``) and the
color-marked run written from it. Checked: density is the base's bit for bit, the informed color decoder reads
the message, a model-level hue shift (``ns-recolor hue``, applied after the mark) takes the color decoder below
the owner threshold while the geometric decoder still reads the hue-shifted density sticker, and the run
round-trips through ``load_run``.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Dict

import pytest
import torch
import yaml
from conftest import CPU_ARGS, NERFACTO_TINY, TINY_POOL_ARGS
from conftest import TINY_MESSAGE as MESSAGE
from conftest import ns_train as _train

from gsticker_plugin import runs as RUNS
from gsticker_plugin import views as VW
from gsticker_plugin.decoders import geometric as G
from gsticker_plugin.decoders import reference as R
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.evaluation.baselines import colormark as C
from gsticker_plugin.key import OwnerKey, file_sha256
from gsticker_plugin.sticker import DensityWrap, Gate, Sticker, WrapState

BASE_STEPS = "400"
AMPLITUDE = 0.05
VIEWS = 6
CPU = torch.device("cpu")


def _quiet():
    return contextlib.redirect_stdout(sys.stderr)


# ---------------------------------------------------------------------------------------------- the wrap alone
class _Frustums:
    def __init__(self, positions: torch.Tensor) -> None:
        self.positions = positions

    def get_positions(self) -> torch.Tensor:
        return self.positions


class _TensoRFLikeField(torch.nn.Module):
    """get_density -> density tensor, get_outputs -> rgb tensor (TensoRF's layout)."""

    def get_density(self, ray_samples):
        return ray_samples.frustums.positions.norm(dim=-1, keepdim=True) * 2.0

    def get_outputs(self, ray_samples, density_embedding=None):
        return torch.full((*ray_samples.frustums.positions.shape[:-1], 3), 0.5)


def test_color_wrap_adds_a_gray_mark_where_the_gate_opens_and_leaves_density():
    torch.manual_seed(0)
    fld = _TensoRFLikeField()
    sticker = Sticker(48, 5, 16, 2, 0.5, "bilinear").requires_grad_(False)
    gate = Gate()
    gate.mu.fill_(2.0)
    gate.scale.fill_(20.0)
    gate.log_beta.data.fill_(float(torch.log(torch.tensor(0.2))))
    gate.calibrated.fill_(True)
    state = WrapState(enabled=True, message=torch.tensor([int(c) for c in MESSAGE]))
    wrap = DensityWrap(fld, "field", sticker, gate, state, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    wrap.remove()
    cw = C.ColorMarkWrap(wrap, state, lambda: 0.1)
    samples = SimpleNamespace(frustums=_Frustums(torch.rand(64, 8, 3) * 2 - 1))
    density = fld.get_density(samples)
    assert torch.equal(density, type(fld).get_density(fld, samples))
    rgb = fld.get_outputs(samples, None)
    delta = rgb - 0.5
    assert torch.equal(delta[..., 0], delta[..., 1]) and torch.equal(delta[..., 0], delta[..., 2])
    psi = gate(density)
    closed = (psi <= wrap.gate_threshold).squeeze(-1)
    assert closed.any() and (~closed).any()
    assert torch.all(delta[closed] == 0) and delta[~closed].abs().max() > 0
    assert float(delta.abs().max()) <= 0.1 + 1e-6
    expected = 0.1 * psi * sticker(wrap.normalize(samples.frustums.positions), state.message)
    assert torch.allclose(delta[..., :1][~closed], expected[~closed], atol=1e-6)
    # get_outputs without its own get_density call (other samples): the density is evaluated, same mark
    assert torch.allclose(fld.get_outputs(samples, None), rgb)
    state.enabled = False
    assert torch.equal(fld.get_outputs(samples, None), torch.full_like(rgb, 0.5))
    cw.remove()
    assert "get_density" not in fld.__dict__ and "get_outputs" not in fld.__dict__


@pytest.mark.parametrize("kind", ["tensorf", "vanilla-nerf"])
def test_tensorf_and_vanilla_nerf_bases_get_the_mark_with_their_density_unchanged(kind):
    """Real model classes, untrained and in memory (gates calibrated by hand on their own renders)."""
    from nerfstudio.cameras.cameras import Cameras
    from nerfstudio.data.scene_box import SceneBox
    from nerfstudio.models.tensorf import TensoRFModelConfig
    from nerfstudio.models.vanilla_nerf import VanillaModelConfig

    from gsticker_plugin import compat

    compat.apply()  # the host fixes the ns-* commands apply

    torch.manual_seed(0)
    base = (
        TensoRFModelConfig(
            init_resolution=16,
            final_resolution=32,
            num_samples=32,
            num_uniform_samples=16,
            upsampling_iters=(),
            num_den_components=4,
            num_color_components=4,
            appearance_dim=9,
        )
        if kind == "tensorf"
        else VanillaModelConfig(num_coarse_samples=16, num_importance_samples=16)
    )
    model = C.ColorMarkModelConfig(base_model=base, color_amplitude=0.2).setup(
        scene_box=SceneBox(aabb=torch.tensor([[-1.5] * 3, [1.5] * 3])), num_train_data=2, metadata={}, device="cpu"
    )
    model.eval()
    if kind == "tensorf":  # untrained grids are ~0: give the density planes something to render
        for p in model.base.field.density_encoding.parameters():
            p.data.uniform_(0.0, 0.5)
    model.set_message(torch.tensor([int(c) for c in MESSAGE]))
    cam = Cameras(
        camera_to_worlds=torch.tensor([[[1.0, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0]]]),
        fx=20.0,
        fy=20.0,
        cx=8.0,
        cy=8.0,
        width=16,
        height=16,
    )
    with torch.no_grad():
        with model.capture_final_samples() as records:
            model.get_outputs_for_camera(cam)
        density = torch.cat([r["density"].reshape(-1) for r in records])
        for g in model.gates.values():
            g.calibrate(density, torch.ones_like(density))
        on = model.get_outputs_for_camera(cam)
        with model.sticker_enabled(False):
            off = model.get_outputs_for_camera(cam)
    geometry = [k for k in on if "accumulation" in k or "depth" in k]
    assert geometry and all(torch.equal(on[k], off[k]) for k in geometry), geometry
    assert float((on["rgb"] - off["rgb"]).abs().max()) > 1e-3


# ---------------------------------------------------------------------------------------------- real runs
@pytest.fixture(scope="module")
def runs(tiny_scene, tmp_path_factory) -> Dict[str, Path]:
    ws = tmp_path_factory.mktemp("colormark")
    out = ws / "runs"
    _train(
        [
            *NERFACTO_TINY,
            *CPU_ARGS,
            "--output-dir",
            str(out / "base"),
            "--experiment-name",
            "nerfacto",
            "--timestamp",
            "base",
            "--max-num-iterations",
            BASE_STEPS,
            "--steps-per-save",
            BASE_STEPS,
            "blender-data",
            "--data",
            str(tiny_scene),
        ],
        ws,
    )
    base = out / "base" / "nerfacto" / "gsticker-nerfacto-small" / "base"
    ckpt = max((base / "nerfstudio_models").glob("step-*.ckpt"))
    _train(
        [
            "geometrysticker",
            "--load-checkpoint",
            str(ckpt),
            *CPU_ARGS,
            "--output-dir",
            str(out / "gs"),
            "--experiment-name",
            "gs",
            "--timestamp",
            "run",
            "--max-num-iterations",
            "10",
            "--pipeline.message",
            MESSAGE,
            *TINY_POOL_ARGS,
            "--pipeline.key-path",
            str(ws / "keys" / "run.gskey"),
        ],
        ws,
    )
    run = out / "gs" / "gs" / "geometrysticker" / "run"
    color = C.write_color_marked_run(run / "config.yml", ws / "colormark", AMPLITUDE)
    return {
        "ws": ws,
        "base": base / "config.yml",
        "run": run / "config.yml",
        "key": ws / "keys" / "run.gskey",
        "color": color,
    }


@pytest.fixture(scope="module")
def loaded(runs):
    key = OwnerKey.load(runs["key"])
    with _quiet():
        ref = R.load_base_reference(key, runs["key"], None, None, CPU)
        _, pipe, ckpt = RUNS.load_run(runs["color"], device=CPU)
    return SimpleNamespace(key=key, ref=ref, pipe=pipe, model=pipe.model, ckpt=ckpt)


def test_written_run_round_trips_through_load_run(runs, loaded):
    color, run = runs["color"], runs["run"]
    assert color == runs["ws"] / "colormark" / "config.yml"
    cfg = yaml.load(color.read_text(), Loader=yaml.Loader)
    wm = yaml.load(run.read_text(), Loader=yaml.Loader)
    mc = cfg.pipeline.model
    assert type(mc) is C.ColorMarkModelConfig and mc._target is C.ColorMarkModel and mc.color_amplitude == AMPLITUDE
    for name in (
        "num_bits",
        "sticker_kind",
        "sticker_hidden_dim",
        "gate_threshold",
        "wrap_proposal_networks",
        "sticker_amplitude",
        "eval_num_rays_per_chunk",
    ):
        assert getattr(mc, name) == getattr(wm.pipeline.model, name), name
    assert yaml.dump(mc.base_model) == yaml.dump(wm.pipeline.model.base_model)
    (src,) = (run.parent / "nerfstudio_models").glob("step-*.ckpt")
    assert loaded.ckpt.name == src.name and file_sha256(loaded.ckpt) == file_sha256(src)
    model = loaded.model
    assert type(model) is C.ColorMarkModel and model.config.color_amplitude == AMPLITUDE
    # the shared form: the key's sticker folded with the key's message

    sc = loaded.key.geometry["sticker_config"]
    full = Sticker(sc["num_bits"], sc["num_frequencies"], sc["hidden_dim"], sc["num_layers"], kind=sc["kind"])
    full.load_state_dict(loaded.key.geometry["sticker_state"])
    assert bool(model.folded) and model.calibrated
    for k, v in full.fold(loaded.key.message).items():
        assert torch.allclose(model.folded_sticker.state_dict()[k].cpu(), v, atol=1e-6), k
    # the same state dict as the watermarked run (loaded strictly by load_run)
    with _quiet():
        _, wpipe, _ = RUNS.load_run(run, device=CPU)
    assert type(wpipe.model).__name__ == "GeometryStickerModel"
    from gsticker_plugin.model import shareable_state

    ws, cs = shareable_state(wpipe.model), shareable_state(model)  # what the checkpoint holds (no filler sticker)
    assert list(ws) == list(cs) and all(torch.equal(ws[k], cs[k]) for k in ws)
    # bad input: one line naming the fix
    cases = [
        (lambda: C.write_color_marked_run(run, runs["ws"] / "x", 0.0), "positive"),
        (lambda: C.write_color_marked_run(run, runs["ws"] / "colormark", AMPLITUDE), "--overwrite"),
        (lambda: C.write_color_marked_run(runs["base"], runs["ws"] / "y", AMPLITUDE), "geometrysticker"),
    ]
    for call, words in cases:
        with pytest.raises(GStickerError) as e:
            call()
        assert words in str(e.value) and "\n" not in str(e.value)
    assert not (runs["ws"] / "x").exists() and not (runs["ws"] / "y").exists()


def test_density_is_the_base_and_color_carries_the_mark(loaded):
    model, base = loaded.model, loaded.ref.pipeline.model  # base: the owner's unwatermarked base run
    assert type(base).__name__ == "NerfactoModel"
    for name, cam in VW.select_cameras(loaded.ref.pipeline, 2, 0.5, 0):
        cam = cam.to(CPU)
        with torch.no_grad():
            o_base = base.get_outputs_for_camera(cam)
            o_on = model.get_outputs_for_camera(cam)
            with model.sticker_enabled(False):
                o_off = model.get_outputs_for_camera(cam)
        for k in ("accumulation", "expected_depth", "depth"):
            assert torch.equal(o_on[k], o_base[k]) and torch.equal(o_off[k], o_base[k]), (name, k)
        assert torch.equal(o_off["rgb"], o_base["rgb"]), name
        d = (o_on["rgb"] - o_base["rgb"]).reshape(-1, 3)
        ref_view = R.reference_view(loaded.ref, name, cam, use_depth=False)
        gate_open = torch.zeros(d.shape[0], dtype=torch.bool)
        gate_open[ref_view.rays] = True
        changed = d.abs().amax(-1) > 0
        assert changed.any() and not changed[~gate_open].any(), name
        inside = ((o_on["rgb"] > 0) & (o_on["rgb"] < 1)).all(-1).reshape(-1)  # not clamped by the renderer
        assert torch.allclose(d[inside, 0], d[inside, 1], atol=1e-5) and torch.allclose(
            d[inside, 0], d[inside, 2], atol=1e-5
        )


def test_color_decoder_reads_the_owner_message(loaded):
    dec, views = C.decode_color_suspect(loaded.key, loaded.ref, loaded.model, VIEWS, 0.5, 0, amplitude=AMPLITUDE)
    m = dec["matches"].tolist()
    assert len(m) == VIEWS == len(views) and dec["scores"] is None and dec["pvalues"].shape == (VIEWS,)
    assert sum(x >= 41 for x in m) >= VIEWS - 1, m
    assert all(d["explained"] > 0.95 and d["undetermined"] == 0 for d in dec["color"]), dec["color"]
    # the mark off: nothing to fit, every bit a coin flip (chance), like the geometric decoder on the base
    dec, _ = C.decode_color_suspect(
        loaded.key, loaded.ref, loaded.model, VIEWS, 0.5, 0, amplitude=AMPLITUDE, sticker=False
    )
    m = dec["matches"].tolist()
    assert all(d["undetermined"] == 48 for d in dec["color"]) and max(m) < 41, m
    # the density sticker's decoder sees the base's geometry in the color-marked run
    dec, _ = G.decode_suspect(loaded.key, loaded.ref, loaded.model, 4, 0.5, 0)
    assert all(d["undetermined"] == 48 for d in dec["geometry"]) and max(dec["matches"].tolist()) < 41


def test_match_amplitude_hits_the_target_psnr(loaded):
    model = loaded.model
    target = 40.0
    a = C.match_amplitude(loaded.pipe, target, num_views=3)
    assert isinstance(a, float) and a > 0 and model.config.color_amplitude == AMPLITUDE
    cams = VW.select_cameras(loaded.pipe, 3, 0.0, 0)
    model.config.color_amplitude = a
    try:
        got = C.mark_psnr(model, cams)
    finally:
        model.config.color_amplitude = AMPLITUDE
    assert abs(float(got.mean()) - target) < 0.5, (a, got.tolist())


def test_hue_shift_defeats_the_color_decoder_not_the_geometric_one(runs, loaded):
    from gsticker_plugin.recolor import cli
    from gsticker_plugin.recolor import runs as R
    from gsticker_plugin.recolor.configs import HUE_METHOD

    dest = runs["ws"] / "colormark-hue"
    assert cli.run(["hue", "--load-config", str(runs["color"]), "--output-dir", str(dest), "--shift", "0.5"]) == 0
    (cfg,) = dest.glob("**/config.yml")
    with _quiet():
        _, pipe, _ = RUNS.load_run(cfg, device=CPU)
    rec = pipe.model
    marked = C.color_mark_model(rec)
    assert type(rec).__name__ == "RecolorModel" and float(rec.hue_shift) == 0.5
    # the recolor wraps the already-marked color: an edit that blacks out every sample removes the mark too
    (cw,) = [w for w in rec.color_wraps if w.field is marked.final_wrap.field]
    assert cw.original.__self__ is marked.color_wrap
    transform = cw.transform
    cw.transform = torch.zeros_like
    try:
        cam = VW.select_cameras(pipe, 1, 0.0, 0)[0][1].to(CPU)
        with torch.no_grad():
            on = rec.get_outputs_for_camera(cam)["rgb"]
            with rec.sticker_enabled(False):
                off = rec.get_outputs_for_camera(cam)["rgb"]
    finally:
        cw.transform = transform
    assert torch.equal(on, off)
    dec, _ = C.decode_color_suspect(loaded.key, loaded.ref, rec, VIEWS, 0.5, 0, amplitude=AMPLITUDE)
    m = dec["matches"].tolist()
    assert max(m) < 41 and sum(m) / len(m) <= 34, m  # below the owner threshold on every view
    # the density sticker under the same hue shift (model-level, in memory): the geometric decoder still reads it
    with _quiet():
        _, gpipe, _, _, _ = R.build_recolor_run(runs["run"], None, HUE_METHOD)
    gpipe.model.hue_shift.fill_(0.5)
    gpipe.model.recolor_enabled = False
    unedited, _ = G.decode_suspect(loaded.key, loaded.ref, gpipe.model, VIEWS, 0.5, 0)
    gpipe.model.recolor_enabled = True
    dec, _ = G.decode_suspect(loaded.key, loaded.ref, gpipe.model, VIEWS, 0.5, 0)
    m = dec["matches"].tolist()
    assert torch.equal(dec["bits"], unedited["bits"]), (m, unedited["matches"].tolist())  # density untouched
    assert sum(x >= 41 for x in m) >= VIEWS - 1, m  # a 10-step sticker: one view may read fewer bits
