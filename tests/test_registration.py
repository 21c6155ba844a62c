"""The plugin is registered with Nerfstudio: ``ns-train`` lists its methods, the entry points load, the scene CLI runs.

Each check runs the real console scripts of the active environment (found next to ``sys.executable``) in a
subprocess, so what is tested is what a user's shell runs.
"""

from __future__ import annotations

import importlib.metadata
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from conftest import console_script, subprocess_env

REPO_ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
METHODS = (
    "geometrysticker",
    "geometrysticker-robust",
    "gsticker-nerfacto-small",
    "gsticker-tensorf-small",
    "gsticker-vanilla-nerf-small",
)


@pytest.mark.slow  # starts subprocesses
def test_ns_train_help_lists_plugin_methods():
    proc = subprocess.run(
        [str(console_script("ns-train")), "--help"],
        capture_output=True,
        text=True,
        timeout=300,
        env=subprocess_env(),
        cwd=REPO_ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    # The usage line's subcommand choices name every registered method exactly.
    choices = set()
    for group in re.findall(r"\{([^{}]*)\}", proc.stdout):
        choices |= {c.strip() for c in group.replace("\n", "").split(",")}
    for method in METHODS:
        assert method in choices, f"{method} missing from ns-train's methods: {sorted(choices)}"
    assert "[gsticker]" in proc.stdout  # our descriptions are shown


def test_method_config_entry_points_load_to_method_specifications():
    from nerfstudio.engine.trainer import TrainerConfig
    from nerfstudio.plugins.types import MethodSpecification

    eps = {ep.name: ep for ep in importlib.metadata.entry_points(group="nerfstudio.method_configs")}
    for method in METHODS:
        assert method in eps, f"entry point {method} is not registered (reinstall: pip install -e .)"
        spec = eps[method].load()
        assert isinstance(spec, MethodSpecification), f"{method} loads to {type(spec)}"
        assert isinstance(spec.config, TrainerConfig)
        assert spec.config.method_name == method
        assert spec.description.startswith("[gsticker]")


def test_the_robust_preset_is_the_measured_images_alone_operating_point_and_leaves_the_default_alone():
    from method_configs.geometrysticker import geometrysticker, geometrysticker_robust

    robust, default = geometrysticker_robust.config, geometrysticker.config
    p = robust.pipeline
    assert (p.model.sticker_amplitude, p.mark_psnr, p.target_psnr) == (30.0, 36.0, 35.0)
    assert (p.condition_weight, p.condition_scale_free, p.condition_blur) == (3.0, True, 1.0)
    assert (p.pool_train_views, p.pool_novel_views, p.warmup_steps) == (16, 16, 50)
    assert robust.max_num_iterations == 2000
    assert robust.optimizers["sticker"]["scheduler"].max_steps == 1500
    assert default.pipeline.condition_weight == 0 and default.pipeline.model.sticker_amplitude == 10.0
    assert default.pipeline.pool_train_views == 48 and default.max_num_iterations == 1500


def test_presets_are_cpu_sized_blender_recipes():
    from method_configs.presets import nerfacto_small, tensorf_small

    for spec in (nerfacto_small, tensorf_small):
        config = spec.config
        model = config.pipeline.model
        assert model.background_color == "white"
        assert config.pipeline.datamanager.train_num_rays_per_batch <= 1024
        assert config.save_only_latest_checkpoint
        assert not config.mixed_precision
        assert config.vis == "tensorboard"
    assert nerfacto_small.config.pipeline.model.implementation == "torch"
    assert nerfacto_small.config.pipeline.model.log2_hashmap_size <= 16


def test_ns_gsticker_scene_help():
    proc = subprocess.run(
        [str(console_script("ns-gsticker-scene")), "--help"],
        capture_output=True,
        text=True,
        timeout=120,
        env=subprocess_env(),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "--output-dir" in proc.stdout and "--resolution" in proc.stdout


@pytest.mark.slow  # starts subprocesses
def test_importing_method_configs_needs_no_cuda_and_no_network():
    """``import method_configs.presets`` (what Nerfstudio does for every ns-* command) opens no socket, touches
    no GPU, builds no model and tries no LPIPS download; it costs little beyond importing Nerfstudio itself."""
    code = textwrap.dedent(
        """
        import socket, sys, time

        def _no_network(*args, **kwargs):
            raise AssertionError("network access during import: %r" % (args,))

        socket.socket.connect = _no_network
        socket.create_connection = _no_network
        socket.getaddrinfo = _no_network
        t0 = time.perf_counter()
        import torch, nerfstudio.engine.trainer, torchmetrics  # the host's own imports
        t1 = time.perf_counter()
        import method_configs.presets
        t2 = time.perf_counter()
        from gsticker_plugin import compat
        assert not torch.cuda.is_initialized(), "CUDA was initialised by the import"
        assert compat._availability == {}, "an LPIPS backbone lookup happened at import time"
        assert compat._PATCHED
        assert "nerfstudio.configs.method_configs" not in sys.modules, "imported every stock method"
        print("HOST %.2f PLUGIN %.2f" % (t1 - t0, t2 - t1))
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        env=subprocess_env(0, CUDA_VISIBLE_DEVICES=""),
        cwd=REPO_ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    host, plugin = (float(x) for x in proc.stdout.split()[1::2])
    # Beyond the host's own imports, the plugin's configs cost seconds at most (a loaded 2-core box included).
    assert plugin < max(10.0, 2 * host), f"method_configs import took {plugin:.1f} s (host imports {host:.1f} s)"
