"""Integration tests of ``ns-train geometrysticker`` on tiny scenes, on the CPU, for each base model.

Each base (nerfacto through the ``gsticker-nerfacto-small`` preset, stock ``vanilla-nerf``, TensoRF through
``gsticker-tensorf-small``; all shrunk further with CLI flags) is trained for a few steps with the real
``ns-train`` in a subprocess, once per test session; then ``ns-train geometrysticker`` sticks a message onto
each, once per base. The three runs of a stage run concurrently (each process gets one thread).

What is checked, per base: the wrap changes density only where the gate is open; gradients reach only the
sticker, the gates and the heads; the base weights are bit-identical after training; the shareable
checkpoint holds no secret heads while the owner key does (and detects tampering); the run loads strictly
with the stock ``eval_setup`` and renders with and without the sticker. Then, on one base: a short run lowers
the message loss, ``ns-render dataset`` renders the run, resuming continues from the saved step, and every
bad input stops ``ns-train`` before training with one line ``error: ...`` and exit status 2 (through
``ns-train``'s entry point in this process, and once through the console script).

Over 600 lines on purpose: every test here shares the module's three bases and three sticker runs (minutes of
training); a second module would train them again or need them as session fixtures for all the other tests too.
"""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Dict, List

import pytest
import torch
from conftest import TINY_POOL_ARGS, console_script, run_parallel, subprocess_env

from gsticker_plugin.decoders import geometric as G
from gsticker_plugin.decoders import reference as R

REPO_ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent

BASES = ("nerfacto", "vanilla-nerf", "tensorf")
BASE_STEPS = 2  # ns-train saves step-000000001.ckpt
GS_STEPS = 10  # ns-train geometrysticker saves step-000000009.ckpt

# Stock method + flags that keep each base tiny (fewer samples and rays; same model classes).
BASE_ARGS: Dict[str, List[str]] = {
    "nerfacto": [
        "gsticker-nerfacto-small",
        "--pipeline.model.num-nerf-samples-per-ray",
        "16",
        "--pipeline.model.num-proposal-samples-per-ray",
        "32",
        "16",
        "--pipeline.datamanager.train-num-rays-per-batch",
        "256",
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
    ],
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
        # grow the grids during the base's 2 steps (32 -> 40), as every real TensoRF run does (2000, 3000, ...):
        "--pipeline.model.upsampling-iters",
        "1",
        "--pipeline.model.final-resolution",
        "40",
    ],
}
# A distinct 48-bit message per base.
MESSAGES = {
    "nerfacto": "101100111000111100001111100000111111000000111111",
    "vanilla-nerf": "010011000111000011110000011111000000111111000000",
    "tensorf": "110010101111000010100101001011010110100101101001",
}
# The small sticker stage: a 4 + 1 view pool, 2 views per step, narrow heads.
GS_FLAGS = [
    *TINY_POOL_ARGS,
]
COMMON = ["--machine.device-type", "cpu", "--vis", "tensorboard"]


# ---------------------------------------------------------------------------------------------- helpers


def ckpt_of(run_dir: Path) -> Path:
    ckpts = sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    assert ckpts, f"no checkpoint in {run_dir}"
    return ckpts[-1]


def load_raw(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.float() - b.float()) ** 2).mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def fail_msg(proc: subprocess.CompletedProcess) -> str:
    return f"exit {proc.returncode}\n--- stdout ---\n{proc.stdout[-4000:]}\n--- stderr ---\n{proc.stderr[-4000:]}"


def gs_command(base_ckpt: Path, output_dir: Path, message: str, *extra: str) -> List[str]:
    return [
        str(console_script("ns-train")),
        "geometrysticker",
        "--load-checkpoint",
        str(base_ckpt),
        *COMMON,
        "--output-dir",
        str(output_dir),
        "--experiment-name",
        "gs",
        "--timestamp",
        "run",
        "--max-num-iterations",
        str(GS_STEPS),
        "--pipeline.message",
        message,
        *GS_FLAGS,
        *extra,
    ]


# ---------------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("geometrysticker")


@pytest.fixture(scope="module")
def base_runs(tiny_scene: Path, work: Path) -> Dict[str, Path]:
    """Each base trained BASE_STEPS steps by the real ``ns-train`` (the three concurrently)."""
    out = work / "bases"
    commands = [
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
            "--max-num-iterations",
            str(BASE_STEPS),
            "--steps-per-save",
            str(BASE_STEPS),
            "blender-data",
            "--data",
            str(tiny_scene),
        ]
        for b in BASES
    ]
    runs = {}
    for b, proc in zip(BASES, run_parallel(commands, work / "logs-bases")):
        assert proc.returncode == 0, f"ns-train {b} failed: {fail_msg(proc)}"
        (run_dir,) = [p.parent for p in (out / b).glob("*/base/config.yml")]
        runs[b] = run_dir
    return runs


@pytest.fixture(scope="module")
def gs_runs(base_runs: Dict[str, Path], work: Path) -> Dict[str, dict]:
    """``ns-train geometrysticker`` on each base (the three concurrently), with a pool cache for in-process reuse."""
    commands, outs = [], {}
    for b in BASES:
        outs[b] = work / "gs" / b
        commands.append(
            gs_command(
                ckpt_of(base_runs[b]),
                outs[b],
                MESSAGES[b],
                "--pipeline.pool-cache",
                str(work / f"pool-{b}.pt"),
                "--pipeline.key-path",
                str(work / "keys" / f"{b}.gskey"),
            )
        )
    runs = {}
    for b, proc in zip(BASES, run_parallel(commands, work / "logs-gs")):
        assert proc.returncode == 0, f"ns-train geometrysticker on {b} failed: {fail_msg(proc)}"
        run_dir = outs[b] / "gs" / "geometrysticker" / "run"
        runs[b] = {
            "run_dir": run_dir,
            "config": run_dir / "config.yml",
            "ckpt": ckpt_of(run_dir),
            "key": work / "keys" / f"{b}.gskey",
            "base_ckpt": ckpt_of(base_runs[b]),
            "message": MESSAGES[b],
            "stdout": proc.stdout,
        }
    return runs


_PIPELINES: Dict[str, object] = {}


@pytest.fixture(scope="module")
def val_pipeline(gs_runs):
    """The run rebuilt in-process by the stock ``eval_setup`` (train/val mode: heads present), one per base."""
    from nerfstudio.utils.eval_utils import eval_setup

    def get(base: str):
        if base not in _PIPELINES:
            from gsticker_plugin.key import OwnerKey

            _, pipeline, _, _ = eval_setup(gs_runs[base]["config"], test_mode="val")
            pipeline.restore_owner(OwnerKey.load(gs_runs[base]["key"]), heads=False)  # the owner's sticker, message
            _PIPELINES[base] = pipeline
        return _PIPELINES[base]

    yield get
    _PIPELINES.clear()


def _zero_grads(pipeline) -> None:
    for p in list(pipeline.parameters()) + list(pipeline.heads.parameters()):
        p.grad = None


# ---------------------------------------------------------------------------------------------- per base


@pytest.mark.parametrize("base", BASES)
def test_run_writes_checkpoint_config_and_key(gs_runs, base):
    run = gs_runs[base]
    assert run["config"].is_file() and run["key"].is_file()
    assert int(run["ckpt"].stem.split("-")[1]) == GS_STEPS - 1
    assert "base loaded strictly" in run["stdout"]
    assert "[gsticker]" in run["stdout"], "the [gsticker] prefix of the log lines is swallowed by rich markup"
    assert "held-out bit acc" in run["stdout"]  # the monitor ran


def test_tensorf_grids_grown_during_base_training_are_rebuilt_at_the_base_step(gs_runs):
    """TensoRF's planes grow during training; the watermarked run rebuilds its base at the base's step."""
    from gsticker_plugin import runs

    run = gs_runs["tensorf"]
    state = runs.model_state_from_pipeline_state(runs.load_checkpoint_state(run["base_ckpt"])["pipeline"])
    grown = [k for k, v in state.items() if k.endswith("plane_coef")]
    assert grown and all(state[k].shape[-1] == 40 for k in grown)  # grown from init-resolution 32
    cfg = runs.load_run_config(run["config"])
    assert cfg.pipeline.model.base_step == BASE_STEPS - 1
    wm = runs.model_state_from_pipeline_state(runs.load_checkpoint_state(run["ckpt"])["pipeline"])
    assert all(wm["base." + k].shape[-1] == 40 for k in grown)


@pytest.mark.parametrize("base", BASES)
def test_wrap_changes_density_only_where_the_gate_is_open(gs_runs, val_pipeline, base):
    pipeline = val_pipeline(base)
    model = pipeline.model
    assert model.calibrated
    assert len(model.wraps) == (2 if base == "vanilla-nerf" else 1)  # vanilla-nerf: coarse and fine fields
    camera = pipeline.datamanager.train_dataset.cameras[0:1]
    # Record the real ray samples each wrapped field sees while rendering a camera.
    recorded: Dict[int, list] = {i: [] for i in range(len(model.wraps))}
    originals = []
    for i, wrap in enumerate(model.wraps):
        originals.append(wrap.original)

        def recorder(ray_samples, *args, _i=i, _orig=wrap.original, **kwargs):
            recorded[_i].append(ray_samples)
            return _orig(ray_samples, *args, **kwargs)

        wrap.original = recorder
    try:
        with torch.no_grad():
            model.get_outputs_for_camera(camera)
    finally:
        for wrap, orig in zip(model.wraps, originals):
            wrap.original = orig

    model.wrap_state.message = model.message
    try:
        for i, wrap in enumerate(model.wraps):
            assert recorded[i], f"field {wrap.name} was never asked for density"
            for forced in (False, True):
                if forced:  # a sticker output of 1 everywhere: every open sample must change
                    model.sticker.forward = lambda positions01, message: torch.ones_like(positions01[:, :1])
                n_open = n_changed = 0
                for rs in recorded[i]:
                    with torch.no_grad():
                        with model.sticker_enabled(False):
                            off = wrap.field.get_density(rs)
                        outside = wrap.field.get_density(rs)  # a direct query, outside the final rendering pass
                        model.wrap_state.in_final = True  # as inside the final field's forward (model.final_pass)
                        try:
                            on = wrap.field.get_density(rs)
                        finally:
                            model.wrap_state.in_final = False
                    off = off[0] if isinstance(off, tuple) else off
                    on = on[0] if isinstance(on, tuple) else on
                    outside = outside[0] if isinstance(outside, tuple) else outside
                    assert off.shape == on.shape and off.shape[-1] == 1
                    # only the final pass is marked (mark_sampling_passes=False): sampling passes see the base
                    assert torch.equal(outside, off), f"{wrap.name}: density changed outside the final pass"
                    if not wrap.is_final:  # vanilla-nerf's coarse field only places samples
                        assert torch.equal(on, off), f"{wrap.name}: the sampling field's density changed"
                        continue
                    psi = wrap.gate(off)
                    closed = psi <= wrap.gate_threshold
                    assert torch.equal(on[closed], off[closed]), (
                        f"{wrap.name}: density changed where the gate is closed"
                    )
                    n_open += int((~closed).sum())
                    n_changed += int((on != off).sum())
                    # on = relu(off + psi * scale * sticker(gamma(x), M)) at the open samples
                    pos = rs.frustums.get_positions().reshape(*off.shape[:-1], 3)
                    with torch.no_grad():
                        m = model.sticker(wrap.normalize(pos[~closed.squeeze(-1)]), model.message)
                    expected = torch.relu(off[~closed] + psi[~closed] * wrap.gate.scale * m.squeeze(-1))
                    assert torch.allclose(on[~closed], expected, rtol=1e-5, atol=1e-6)
                    if forced:
                        assert float((on[~closed] > off[~closed]).float().mean()) > 0.99
                if not wrap.is_final:
                    continue
                assert n_open > 0, f"{wrap.name}: the gate is closed at every sample (calibration failed?)"
                if forced:
                    assert n_changed > 0, f"{wrap.name}: a big sticker output changed no density"
    finally:
        model.sticker.__dict__.pop("forward", None)


@pytest.mark.parametrize("base", BASES)
@pytest.mark.parametrize("fast_path", [True, False], ids=["fast", "naive"])
def test_gradients_reach_only_sticker_gates_and_heads(gs_runs, val_pipeline, base, fast_path):
    pipeline = val_pipeline(base)
    model = pipeline.model
    old = (pipeline.config.fast_path, pipeline.config.patch_size, pipeline.config.train_heads)
    pipeline.config.fast_path, pipeline.config.patch_size, pipeline.config.train_heads = fast_path, 8, True
    _zero_grads(pipeline)
    try:
        _, loss_dict, metrics_dict = pipeline.get_train_loss_dict(0)
        loss = sum(loss_dict.values())
        assert torch.isfinite(loss)
        loss.backward()
        base_params = list(model.base.named_parameters())
        assert base_params
        for name, p in base_params:
            assert not p.requires_grad, f"base parameter {name} is trainable"
            assert p.grad is None, f"base parameter {name} received a gradient"
        for name, p in model.sticker.named_parameters():
            assert p.grad is not None, f"sticker parameter {name} has no gradient"
        for name, p in pipeline.heads.named_parameters():
            assert p.grad is not None, f"heads parameter {name} has no gradient"
        if fast_path:  # the fast path trains the final field's gate (vanilla-nerf's coarse gate only places samples)
            assert model.final_wrap.gate.log_beta.grad is not None, "the final field's gate has no gradient"
        allowed = {id(p) for group in pipeline.get_param_groups().values() for p in group}
        for name, p in pipeline.named_parameters():
            if p.grad is not None:
                assert id(p) in allowed, f"{name} received a gradient but is not trained"
        assert set(pipeline.get_param_groups()) == {"sticker", "heads"}
    finally:
        pipeline.config.fast_path, pipeline.config.patch_size, pipeline.config.train_heads = old
        _zero_grads(pipeline)


@pytest.mark.parametrize(
    "train_heads, weights", [(False, (1.0, 0.5, 0.1)), (True, (0.0, 0.0, 0.0))], ids=["default", "weights-0"]
)
def test_unless_asked_no_step_runs_the_heads(gs_runs, val_pipeline, train_heads, weights):
    """By default (--pipeline.train-heads False), and with the message, honesty and classifier weights all 0 (the
    sweep's heads-none): content and sparsity losses only, the sticker still learns, the heads get no gradient and
    are not run. Asked (train-heads and a weight above 0), they train."""
    pipeline = val_pipeline("nerfacto")
    cfg = pipeline.config
    old = (cfg.train_heads, cfg.msg_weight, cfg.negative_weight, cfg.cls_weight)
    cfg.train_heads = train_heads
    cfg.msg_weight, cfg.negative_weight, cfg.cls_weight = weights
    _zero_grads(pipeline)
    calls = []
    hooks = [
        m.register_forward_hook(lambda *a: calls.append(1))
        for m in (pipeline.heads.extractor, pipeline.heads.classifier)
    ]
    try:
        assert not pipeline.trains_heads
        _, loss_dict, metrics_dict = pipeline.get_train_loss_dict(10**6)
        assert set(loss_dict) == {"content_loss", "sparsity_loss"} and "bit_acc" not in metrics_dict
        sum(loss_dict.values()).backward()
        assert any(p.grad is not None for p in pipeline.model.sticker.parameters())
        assert all(p.grad is None for p in pipeline.heads.parameters()) and not calls
        cfg.train_heads, cfg.msg_weight = True, 1.0
        assert pipeline.trains_heads
    finally:
        for h in hooks:
            h.remove()
        cfg.train_heads, cfg.msg_weight, cfg.negative_weight, cfg.cls_weight = old
        _zero_grads(pipeline)


def test_the_conditioning_loss_trains_the_sticker_from_a_training_step(gs_runs, val_pipeline):
    """condition weight > 0 (scale-free, with the blurred change): the step reports the loss and the bits' noise std,
    and that loss alone reaches the sticker."""
    from gsticker_plugin.fastpath import noise_variance, sign_gram

    pipeline = val_pipeline("nerfacto")
    cfg = pipeline.config
    old = (cfg.condition_weight, cfg.condition_scale_free, cfg.condition_blur)
    cfg.condition_weight, cfg.condition_scale_free, cfg.condition_blur = 2.0, True, 1.0
    _zero_grads(pipeline)
    try:
        _, loss_dict, metrics_dict = pipeline.get_train_loss_dict(10**6)
        loss = loss_dict["condition_loss"]
        assert torch.isfinite(loss) and loss.requires_grad
        loss.backward()
        assert any(p.grad is not None and float(p.grad.abs().max()) > 0 for p in pipeline.model.sticker.parameters())
        assert all(p.grad is None for p in pipeline.heads.parameters())
        message = pipeline._last["messages"][0]
        gram = sign_gram(pipeline._views[0], pipeline.model.final_wrap, message, pipeline.model.background_color())
        want = noise_variance(gram.detach(), cfg.condition_noise).sqrt()
        assert abs(float(metrics_dict["sign_noise_std"]) - float(want)) <= 1e-4 * float(want)
    finally:
        cfg.condition_weight, cfg.condition_scale_free, cfg.condition_blur = old
        _zero_grads(pipeline)


@pytest.mark.parametrize("base", BASES)
def test_fast_path_matches_the_real_render(gs_runs, val_pipeline, base):
    """What the sticker is trained on (cached samples, re-composited) is what the model renders: the sticker marks
    only the final rendering pass (``mark_sampling_passes=False``, what ns-train writes), so TensoRF's uniform pass
    and vanilla-nerf's coarse field place the base's own samples."""
    from gsticker_plugin.fastpath import cache_view, render_cached

    pipeline = val_pipeline(base)
    model = pipeline.model
    camera = pipeline.datamanager.train_dataset.cameras[1:2]
    with torch.no_grad():
        view = cache_view(model, camera, False)
        fast, _ = render_cached(view, model.final_wrap, model.message, model.background_color())
        real = model.get_outputs_for_camera(camera)["rgb"]
        with model.sticker_enabled(False):
            clean = model.get_outputs_for_camera(camera)["rgb"]
    assert float((real - clean).abs().max()) > 1e-3  # the sticker is visible
    assert float((fast - real).abs().max()) < 2e-3, float((fast - real).abs().max())
    assert gs_runs[base]["config"].read_text().count("mark_sampling_passes: false") == 1
    if base != "nerfacto":  # the sampling passes of the run as it was before the option move its samples
        model.wrap_state.final_only = False
        try:
            with torch.no_grad():
                old = model.get_outputs_for_camera(camera)["rgb"]
        finally:
            model.wrap_state.final_only = True
        assert float((old - real).abs().max()) > 1e-4


@pytest.mark.parametrize("base", BASES)
def test_relinearized_view_at_the_true_message_predicts_the_marked_render(gs_runs, val_pipeline, base):
    """The geometric decoder's model around a message M (samples of the base marked with M, base density at them)
    reproduces the marked render's accumulation, also where the samples follow the wrapped density (TensoRF,
    vanilla-nerf, with the sampling passes marked as runs made before ``mark_sampling_passes`` were); the
    linearization around the unmarked base's samples does not, for those bases. With only the final pass marked
    (what ns-train writes now) the plain linearization is exact for every base."""
    from gsticker_plugin.decoders import reference as R

    pipeline = val_pipeline(base)
    model = pipeline.model
    camera0 = pipeline.datamanager.train_dataset.cameras[0:1]
    ref0 = R.BaseReference(
        config_path=gs_runs[base]["config"],
        checkpoint=gs_runs[base]["ckpt"],
        method=base,
        pipeline=pipeline,
        model=model,
    )
    with torch.no_grad():
        out0 = {
            k: v.float().cpu() for k, v in model.get_outputs_for_camera(camera0).items() if isinstance(v, torch.Tensor)
        }
        view0 = R.reference_view(ref0, "cam0", camera0, False)
        st0 = R.cpu_sticker(model)
        signs0 = model.message.float() * 2 - 1
        pred0 = view0.base_signal + G.predict_change(view0, st0, signs0) - G.predict_change(view0, st0, torch.zeros(48))
    sus0 = G.suspect_signal(out0, view0)
    assert float((sus0 - view0.base_signal).abs().max()) > 1e-3
    assert float((sus0 - pred0).abs().max()) < 1e-4, float((sus0 - pred0).abs().max())
    model.wrap_state.final_only = False  # from here: a run made with its sampling passes marked
    try:
        _relinearized_checks(gs_runs, pipeline, model, base)
    finally:
        model.wrap_state.final_only = True


def _relinearized_checks(gs_runs, pipeline, model, base):

    ref = R.BaseReference(
        config_path=gs_runs[base]["config"],
        checkpoint=gs_runs[base]["ckpt"],
        method=base,
        pipeline=pipeline,
        model=model,
    )
    camera = pipeline.datamanager.train_dataset.cameras[0:1]
    message = model.message.clone()
    st = R.cpu_sticker(model)
    with torch.no_grad():
        out = {
            k: v.float().cpu() for k, v in model.get_outputs_for_camera(camera).items() if isinstance(v, torch.Tensor)
        }
    signs = message.float() * 2 - 1

    def residual(view):
        with torch.no_grad():
            pred = view.base_signal + G.predict_change(view, st, signs) - G.predict_change(view, st, torch.zeros(48))
        sus = G.suspect_signal(out, view)
        return float((sus - pred).abs().max()), float((sus - view.base_signal).abs().max())

    relin, change = residual(G.relinearized_view(ref, "cam0", camera, False, message, st))
    assert torch.equal(model.message, message)  # restored after the capture
    assert change > 1e-3, "the sticker changes this view's accumulation"
    assert relin < 1e-4 * max(1.0, change * 100), (relin, change)
    plain, _ = residual(R.reference_view(ref, "cam0", camera, False))
    if base == "nerfacto":  # proposal samplers are not wrapped: the base's own samples are the marked model's
        assert plain < 1e-4, plain
    else:
        assert plain > 10 * relin, (plain, relin)


@pytest.mark.parametrize("base", BASES)
def test_decoding_from_the_read_rays_only_equals_decoding_whole_renders(gs_runs, val_pipeline, base):
    """``full_renders=False`` renders the suspect only at the rays the fit reads: those pixels equal a whole
    render's, and the decoded bits, fits and matches are the whole render's (TensoRF and vanilla-nerf refit on
    the rays of the relinearized view, which the first view may not hold); the view without depth is derived."""
    from gsticker_plugin.evaluation.baselines.colormark import decode_color_suspect
    from gsticker_plugin.key import OwnerKey

    pipeline = val_pipeline(base)
    model = pipeline.model
    ref = R.BaseReference(
        config_path=gs_runs[base]["config"],
        checkpoint=gs_runs[base]["ckpt"],
        method=base,
        pipeline=pipeline,
        model=model,
        samples_follow_sticker=base != "nerfacto",
    )
    key = OwnerKey.load(gs_runs[base]["key"])
    cams = pipeline.datamanager.train_dataset.cameras
    cameras = [(f"cam{i}", cams[i : i + 1]) for i in range(1)]
    with torch.no_grad():
        whole = model.get_outputs_for_camera(cams[0:1])
    rays = torch.tensor([0, 5, 17, whole["rgb"].shape[0] * whole["rgb"].shape[1] - 1])
    part = G.render_rays(model, cams[0:1], rays)
    for k, v in part.items():
        flat, ref_flat = v.reshape(-1, v.shape[-1]), whole[k].reshape(-1, v.shape[-1])
        assert torch.allclose(flat[rays], ref_flat[rays], atol=1e-6), k
        assert torch.isnan(flat[1]).all()  # not rendered
    more = torch.tensor([0, 1, 2, 17, 40])  # a relinearized view may keep rays the first one did not
    done = G.complete_rays(model, cams[0:1], {k: v.cpu() for k, v in part.items()}, more)
    for k, v in done.items():
        flat = v.reshape(-1, v.shape[-1])
        assert torch.allclose(flat[more], whole[k].reshape(-1, v.shape[-1])[more], atol=1e-6), k
        assert torch.allclose(flat[rays], whole[k].reshape(-1, v.shape[-1])[rays], atol=1e-6), k
        assert torch.isnan(flat[3]).all()
    results = {}
    for full in (True, False):
        for sticker in (True, False):
            cache: dict = {}
            dec, views = G.decode_suspect(
                key,
                ref,
                model,
                len(cameras),
                0.0,
                0,
                sticker=sticker,
                cameras=cameras,
                ref_cache=cache,
                full_renders=full,
            )
            assert len(views) == (len(cameras) if full else 0)
            results[full, sticker] = dec
    for sticker in (True, False):
        a, b = results[True, sticker], results[False, sticker]
        assert torch.equal(a["bits"], b["bits"]) and torch.equal(a["matches"], b["matches"])
        for x, y in zip(a["geometry"], b["geometry"]):
            assert x["undetermined"] == y["undetermined"] and x["rays"] == y["rays"]
            assert abs(x["explained"] - y["explained"]) < 1e-6 and abs(x["signs_abs_mean"] - y["signs_abs_mean"]) < 1e-6
    assert results[True, True]["matches"].float().mean() > results[True, False]["matches"].float().mean()
    # the view without depth is the one with depth less its second signal
    with_depth = R.reference_view(ref, "cam0", cams[0:1], True)
    plain, derived = R.reference_view(ref, "cam0", cams[0:1], False), R.without_depth(with_depth)
    assert plain.signals == derived.signals == ("accumulation",)
    assert torch.equal(plain.rays, derived.rays) and torch.equal(plain.base_signal, derived.base_signal)
    # the color decoder reads the same pixels either way
    c_full, _ = decode_color_suspect(
        key, ref, model, len(cameras), 0.0, 0, amplitude=0.5, sticker=True, full_renders=True
    )
    c_part, v_part = decode_color_suspect(
        key, ref, model, len(cameras), 0.0, 0, amplitude=0.5, sticker=True, full_renders=False
    )
    assert torch.equal(c_full["bits"], c_part["bits"]) and v_part == []


def test_a_base_without_expected_depth_reads_a_suspect_that_has_it(gs_runs, val_pipeline):
    """A vanilla-nerf base renders no expected depth, a nerfacto suspect does (decoding another model of the scene
    with the vanilla-nerf owner's key): the reference keeps accumulation only, and so does the suspect's signal."""

    pipeline = val_pipeline("vanilla-nerf")
    ref = R.BaseReference(
        config_path=gs_runs["vanilla-nerf"]["config"],
        checkpoint=gs_runs["vanilla-nerf"]["ckpt"],
        method="vanilla-nerf",
        pipeline=pipeline,
        model=pipeline.model,
    )
    camera = pipeline.datamanager.train_dataset.cameras[0:1]
    suspect = val_pipeline("nerfacto").model
    with torch.no_grad():
        out = {
            k: v.float().cpu() for k, v in suspect.get_outputs_for_camera(camera).items() if isinstance(v, torch.Tensor)
        }
    assert R.has_expected_depth(out)
    view = R.reference_view(ref, "cam0", camera, use_depth=R.has_expected_depth(out))
    assert view.signals == ("accumulation",) and view.base_signal.shape[0] == 1
    assert G.suspect_signal(out, view).shape == view.base_signal.shape
    own = val_pipeline("nerfacto")
    ref_n = R.BaseReference(
        config_path=gs_runs["nerfacto"]["config"],
        checkpoint=gs_runs["nerfacto"]["ckpt"],
        method="nerfacto",
        pipeline=own,
        model=own.model,
    )
    assert R.reference_view(ref_n, "cam0", camera, use_depth=True).signals == ("accumulation", "expected_depth")


@pytest.mark.parametrize("base", BASES)
def test_base_weights_are_bit_identical_after_training(gs_runs, base):
    ours = load_raw(gs_runs[base]["ckpt"])["pipeline"]
    theirs = load_raw(gs_runs[base]["base_ckpt"])["pipeline"]
    base_keys = {k[len("_model.") :] for k in theirs if k.startswith("_model.")}
    our_base_keys = {k[len("_model.base.") :] for k in ours if k.startswith("_model.base.")}
    assert base_keys and base_keys == our_base_keys
    for k in sorted(base_keys):
        a, b = ours["_model.base." + k], theirs["_model." + k]
        assert a.dtype == b.dtype and torch.equal(a, b), f"base weight {k} changed"
    # The sticker did train (its folded form is in the checkpoint).
    assert any(k.startswith("_model.folded_sticker.") for k in ours) and bool(ours["_model.folded"])


@pytest.mark.parametrize("base", BASES)
def test_checkpoint_is_shareable_and_owner_key_holds_the_heads(gs_runs, base):
    from gsticker_plugin.errors import GStickerError
    from gsticker_plugin.heads import HeadConfig, Heads
    from gsticker_plugin.key import OwnerKey, bits_to_str

    run = gs_runs[base]
    state = load_raw(run["ckpt"])
    secret = {"extractor", "classifier", "heads"}  # (vanilla-nerf's own "field_heads" are base weights)
    assert not [k for k in state["pipeline"] if secret & set(k.split("."))]
    assert set(state["optimizers"]) == set()  # the sticker's optimizer state is the owner's (in the key)
    assert not secret & set(state.get("schedulers", {}))

    key = OwnerKey.load(run["key"])
    assert key.num_bits == 48 and bits_to_str(key.message) == run["message"]
    # no message and no per-bit sticker in the shared checkpoint; the key's sticker folded with its message is the
    # shared one
    assert not [k for k in state["pipeline"] if k.startswith(("_model.message", "_model.sticker."))]
    from gsticker_plugin.sticker import Sticker

    sc = key.geometry["sticker_config"]
    full = Sticker(sc["num_bits"], sc["num_frequencies"], sc["hidden_dim"], sc["num_layers"], kind=sc["kind"])
    full.load_state_dict(key.geometry["sticker_state"])
    for k, v in full.fold(key.message).items():
        assert torch.allclose(state["pipeline"]["_model.folded_sticker." + k], v, atol=1e-6), k
    assert key.heads_config["width"] == 8
    # The heads rebuilt from the key compute what the run's own heads compute: the pipeline's construction (the
    # run's config.yml) loaded with the key's state, as the trainer resumes them; a fresh initialization does not.
    import yaml

    run_cfg = yaml.load(Path(run["config"]).read_text(), Loader=yaml.Loader).pipeline
    assert key.heads_config == dict(vars(run_cfg.heads))
    pipeline_heads = Heads(run_cfg.heads, run_cfg.model.num_bits)
    pipeline_heads.load_state_dict(key.heads_state, strict=True)
    rebuilt = key.build_heads()
    assert not rebuilt.training  # eval mode
    x = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        logits = rebuilt.decode(x)
        assert logits.shape == (2, 48) and torch.isfinite(logits).all()
        assert torch.equal(logits, pipeline_heads.eval().decode(x))
        assert torch.equal(rebuilt.classify(x), pipeline_heads.classify(x))
        torch.manual_seed(1)
        assert not torch.allclose(logits, Heads(HeadConfig(**key.heads_config), key.num_bits).eval().decode(x))
    assert key.training_state["step"] == GS_STEPS - 1
    assert key.base["checkpoint_sha256"]

    # One flipped byte in one tensor: the fingerprint check must catch it.
    raw = torch.load(run["key"], map_location="cpu", weights_only=False)
    name = sorted(raw["heads_state"])[0]
    tensor = raw["heads_state"][name].clone()
    tensor.reshape(-1).view(torch.uint8)[0] ^= 0x01
    raw["heads_state"][name] = tensor
    tampered = run["key"].with_name("tampered.gskey")
    torch.save(raw, tampered)
    with pytest.raises(GStickerError, match="integrity check"):
        OwnerKey.load(tampered)


@pytest.mark.parametrize("base", BASES)
def test_eval_setup_loads_strictly_and_renders_with_and_without_sticker(gs_runs, base):
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, ckpt_path, step = eval_setup(gs_runs[base]["config"], test_mode="inference")
    assert step == GS_STEPS - 1 and pipeline.heads is None  # no secret in the shareable model
    model = pipeline.model
    assert model.calibrated
    camera = pipeline.datamanager.train_dataparser_outputs.cameras[0:1]
    with torch.no_grad():
        on = model.get_outputs_for_camera(camera)
        with model.sticker_enabled(False):
            off = model.get_outputs_for_camera(camera)
    assert on["rgb"].shape == (32, 32, 3) and on["sticker_delta"].shape == (32, 32, 1)
    assert float(on["sticker_delta"].max()) > 0 and float(off["sticker_delta"].abs().max()) == 0
    assert not torch.equal(on["rgb"], off["rgb"]), "the sticker changes nothing in the render"
    # (no PSNR bound: a 10-step run is inside the warm-up, before the content loss trims the randomly initialised mark)

    # Strict: a checkpoint with a key missing does not load (the host would silently load it non-strictly).
    state = load_raw(Path(ckpt_path))["pipeline"]
    state.pop(next(k for k in state if k.startswith("_model.folded_sticker.")))
    with pytest.raises(RuntimeError, match="Missing key"):
        pipeline.load_pipeline(state, step)


# ---------------------------------------------------------------------------------------------- one base


def test_short_training_lowers_the_message_loss(gs_runs):
    """80 steps of the pipeline's own training step (fast path) + Adam, on the 4-view pool, in this process.

    Each render carries the owner's message or its complement (not uniformly random messages: on a 2-step
    base and a 4-view pool, 48 random bits stay at BCE = ln 2 for hundreds of steps). Telling the two apart
    still needs the extractor to read the sticker from the render: the views are drawn at random.
    """
    from nerfstudio.utils.eval_utils import eval_setup

    torch.manual_seed(0)  # the heads' initialisation
    _, pipeline, _, _ = eval_setup(gs_runs["nerfacto"]["config"], test_mode="val")
    from gsticker_plugin.key import OwnerKey

    pipeline.restore_owner(OwnerKey.load(gs_runs["nerfacto"]["key"]), heads=False)
    pipeline.config.views_per_step = 4
    pipeline.config.steps_per_monitor = 10**9
    pipeline.config.train_heads = True
    generator = torch.Generator().manual_seed(0)
    owner = pipeline.owner_message.cpu()

    def owner_or_complement(n: int) -> torch.Tensor:
        flip = torch.randint(0, 2, (n, 1), generator=generator)
        return (owner[None] ^ flip).to(pipeline.device)

    pipeline.sample_messages = owner_or_complement
    groups = pipeline.get_param_groups()
    optimizer = torch.optim.Adam([{"params": groups["sticker"], "lr": 2e-3}, {"params": groups["heads"], "lr": 1e-3}])
    losses, accs = [], []
    for step in range(80):
        optimizer.zero_grad()
        _, loss_dict, metrics_dict = pipeline.get_train_loss_dict(step)
        sum(loss_dict.values()).backward()
        optimizer.step()
        losses.append(float(loss_dict["message_loss"]))
        accs.append(float(metrics_dict["bit_acc"]))
    first, last = sum(losses[:10]) / 10, sum(losses[-10:]) / 10
    assert last < first - 0.1, f"message loss did not fall: first 10 steps {first:.4f}, last 10 {last:.4f}"
    assert last < math.log(2) - 0.1 and sum(accs[-10:]) / 10 > 0.75, (last, accs[-10:])


def test_ns_render_dataset_renders_the_run(gs_runs, work):
    out = work / "render"
    proc = subprocess.run(
        [
            str(console_script("ns-render")),
            "dataset",
            "--load-config",
            str(gs_runs["nerfacto"]["config"]),
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
    assert proc.returncode == 0, fail_msg(proc)
    images = sorted(out.rglob("*.jpg")) + sorted(out.rglob("*.png"))
    assert len(images) == 2, sorted(out.rglob("*"))


def test_resume_continues_from_the_saved_step(gs_runs, work):
    from gsticker_plugin.key import OwnerKey

    run = gs_runs["nerfacto"]
    # Resume a copy (run folder + its key), so the other tests' run stays as it was.
    copy_dir = work / "resume-src" / "run"
    shutil.copytree(run["run_dir"], copy_dir)
    copy_key = copy_dir.with_name("run.gskey")
    shutil.copy2(run["key"], copy_key)
    out = work / "resumed"
    # Shapes (heads width, sticker size) come from the run being resumed: no need to repeat them.
    cmd = [
        str(console_script("ns-train")),
        "geometrysticker",
        "--load-dir",
        str(copy_dir / "nerfstudio_models"),
        *COMMON,
        "--output-dir",
        str(out),
        "--experiment-name",
        "gs",
        "--timestamp",
        "resumed",
        "--max-num-iterations",
        "3",
        "--pipeline.key-path",
        str(copy_key),
        "--pipeline.pool-train-views",
        "2",
        "--pipeline.pool-novel-views",
        "2",
        "--pipeline.monitor-views",
        "1",
        "--pipeline.views-per-step",
        "2",
        "--pipeline.pool-cache",
        str(work / "pool-nerfacto.pt"),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=400, env=subprocess_env(), cwd=work)
    assert proc.returncode == 0, fail_msg(proc)
    assert "pool reused" in proc.stdout  # same base, cameras, sizes and gate: the cached pool
    saved = GS_STEPS - 1
    assert "resumed from" in proc.stdout and f"(step {saved})" in proc.stdout, proc.stdout[-3000:]
    new_ckpt = ckpt_of(out / "gs" / "geometrysticker" / "resumed")
    state = load_raw(new_ckpt)
    assert state["step"] == saved + 3 and int(new_ckpt.stem.split("-")[1]) == saved + 3
    key = OwnerKey.load(copy_key)
    assert key.training_state["step"] == saved + 3 and key.heads_config["width"] == 8
    # The original run and its key are untouched; the base is still bit-identical.
    assert OwnerKey.load(run["key"]).training_state["step"] == saved
    theirs = load_raw(run["base_ckpt"])["pipeline"]
    for k, v in theirs.items():
        if k.startswith("_model."):
            assert torch.equal(state["pipeline"]["_model.base." + k[len("_model.") :]], v), k


# ---------------------------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def bad_inputs(base_runs, work) -> Dict[str, Path]:
    """A truncated base checkpoint, a checkpoint with no run folder around it, and a 4-view scene."""
    from gsticker_plugin import scene

    bad = work / "bad"
    bad.mkdir()
    truncated_run = bad / "truncated-run"
    shutil.copytree(base_runs["nerfacto"], truncated_run)
    truncated = ckpt_of(truncated_run)
    data = truncated.read_bytes()
    truncated.write_bytes(data[: len(data) // 2])
    base_ckpt = ckpt_of(base_runs["nerfacto"])
    lonely = bad / "lonely" / "nerfstudio_models" / base_ckpt.name
    lonely.parent.mkdir(parents=True)
    shutil.copy2(base_ckpt, lonely)
    four_views = bad / "scene4"
    assert (
        scene.main(
            scene.SceneConfig(output_dir=four_views, resolution=32, num_train=4, num_val=1, num_test=1, seed=1),
            progress=False,
        )
        == 0
    )
    return {"dir": bad, "base": base_ckpt, "truncated": truncated, "lonely": lonely, "scene4": four_views}


BAD_CASES = {
    # case: (arguments, words naming the problem, words naming the fix)
    "no-checkpoint-flag": ((), "needs a trained base", "--load-checkpoint"),
    "missing": (("--load-checkpoint", "{dir}/nowhere/step-000000002.ckpt"), "does not exist", "--load-checkpoint"),
    "truncated": (("--load-checkpoint", "{truncated}"), "truncated or corrupt", "copy it again"),
    "no-config": (("--load-checkpoint", "{lonely}"), "no config.yml", "intact Nerfstudio run folder"),
    "message": (("--load-checkpoint", "{base}", "--pipeline.message", "0101"), "exactly 48 bits", "--pipeline.message"),
    "other-data": (("--load-checkpoint", "{base}", "--data", "{scene4}"), "appearance embedding", "--data"),
}


def _bad_args(case: str, paths: Dict[str, Path]) -> List[str]:
    args, _, _ = BAD_CASES[case]
    out_dir = paths["dir"] / "out" / case
    return [
        "geometrysticker",
        *COMMON,
        "--output-dir",
        str(out_dir),
        "--max-num-iterations",
        "2",
        *GS_FLAGS,
        *[a.format(**paths) for a in args],
    ]


def _check_one_line_error(case: str, code, stdout: str, stderr: str, out_dir: Path) -> None:
    report = f"exit {code}\n--- stdout ---\n{stdout[-3000:]}\n--- stderr ---\n{stderr[-3000:]}"
    assert code == 2, report
    errors = [line for line in stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, report
    _, problem, fix = BAD_CASES[case]
    assert problem in errors[0] and fix in errors[0], errors[0]
    assert "Traceback" not in stdout + stderr, report
    assert "Step (% Done)" not in stdout  # stopped before training
    assert not list(out_dir.rglob("*.ckpt")) and not list(out_dir.rglob("*.gskey"))


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_input_stops_ns_train_before_training_with_one_line_error(bad_inputs, case, monkeypatch, capfd):
    """``ns-train``'s own entry point, in this process (a subprocess per case would cost ~15 s of imports each)."""
    import nerfstudio.scripts.train as ns_train

    args = _bad_args(case, bad_inputs)
    monkeypatch.setattr(sys, "argv", ["ns-train", *args])
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit) as exc:
        ns_train.entrypoint()
    out, err = capfd.readouterr()
    _check_one_line_error(case, exc.value.code, out, err, bad_inputs["dir"] / "out" / case)


def test_bad_input_through_the_ns_train_console_script(bad_inputs, work):
    """The same, once, through the real console script: exit status 2 and one line on stderr."""
    case = "message"
    proc = subprocess.run(
        [str(console_script("ns-train")), *_bad_args(case, bad_inputs)],
        capture_output=True,
        text=True,
        timeout=300,
        env=subprocess_env(),
        cwd=work,
    )
    _check_one_line_error(case, proc.returncode, proc.stdout, proc.stderr, bad_inputs["dir"] / "out" / case)


def test_the_shared_run_goes_under_the_base_runs_experiment_name_unless_one_is_given(tmp_path):
    from gsticker_plugin.trainer import GeometryStickerTrainerConfig

    run = tmp_path / "outputs" / "myscene" / "nerfacto" / "base"
    (run / "nerfstudio_models").mkdir(parents=True)
    (run / "config.yml").write_text("")
    ckpt = run / "nerfstudio_models" / "step-000000599.ckpt"
    ckpt.write_bytes(b"")
    cfg = GeometryStickerTrainerConfig(load_checkpoint=ckpt)
    cfg.set_experiment_name()
    assert cfg.experiment_name == "myscene"
    given = GeometryStickerTrainerConfig(load_checkpoint=ckpt, experiment_name="mine")
    given.set_experiment_name()
    assert given.experiment_name == "mine"
    missing = GeometryStickerTrainerConfig(load_checkpoint=tmp_path / "nope.ckpt")
    missing.set_experiment_name()  # no traceback here: setup() reports the missing checkpoint in one line
    assert missing.experiment_name == "unnamed"
