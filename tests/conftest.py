"""Shared pytest fixtures.

``tiny_scene``: a 32 px Blender-format dataset (6 train / 2 val / 2 test views, seed 0) generated once per
session with the plugin's own scene generator. ``tiny_base`` (a 2-step nerfacto base on it) and ``tiny_sticker``
(a 10-step geometrysticker run on that base carrying ``TINY_MESSAGE``) are trained once per session by the real
``ns-train``; modules that rewrite a key get their own copy (:func:`copy_key`). ``shared_dir``: the project's
shared data folder (``../shared`` beside the repository root), or a skip when it is missing.

Under pytest-xdist (``make test`` runs two workers, a test file per worker) each worker uses one thread, and the
session's scene and tiny runs are built once for all workers (:func:`built_once`).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Dict, List, Sequence

import pytest
from filelock import FileLock

WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if WORKER:  # two workers on the CPU's cores: one thread each, inherited by their ns-* subprocesses
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")

# Host quirk: after pyvista/VTK has rendered off screen in a process (Mesa's llvmpipe loads its LLVM), the first
# import of triton's libtriton in that process segfaults -- and torch._dynamo imports triton through
# torchvision.ops, i.e. every Nerfstudio model import does. Loading triton first avoids the clash.
try:
    import triton  # noqa: F401
except Exception:  # triton is optional (CPU-only torch wheels)
    pass

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = REPO_ROOT.parent / "shared"
BIN = Path(sys.executable).parent
TINY_MESSAGE = "101100111000111100001111100000111111000000111111"
NERFACTO_TINY = [
    "gsticker-nerfacto-small",
    "--pipeline.model.num-nerf-samples-per-ray",
    "16",
    "--pipeline.model.num-proposal-samples-per-ray",
    "32",
    "16",
    "--pipeline.datamanager.train-num-rays-per-batch",
    "256",
]
CPU_ARGS = ["--machine.device-type", "cpu", "--vis", "tensorboard"]
from gsticker_plugin.bench import TINY_POOL  # noqa: E402  (light: no torch, after the triton import above)

STICKER_SEED_ARGS = ["--pipeline.sticker-seed", "0"]
"""The tests' sticker runs start from one fixed sticker (a user's runs draw it with `secrets`): their small, short
runs read the same way on every test session."""
TINY_POOL_ARGS = [*TINY_POOL, *STICKER_SEED_ARGS]
TINY_STICKER_ARGS = ["--max-num-iterations", "10", *TINY_POOL_ARGS]


def subprocess_env(threads: int = 0, **extra: str) -> dict:
    """The environment of an ns-* subprocess: offline LPIPS, wide logs, no warnings; ``threads``: BLAS threads."""
    env = dict(os.environ)
    env.update({"GSTICKER_NO_DOWNLOAD": "1", "COLUMNS": "200", "PYTHONWARNINGS": "ignore"})
    if threads:
        env.update({"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)})
    env.update(extra)
    return env


def console_script(name: str) -> Path:
    """The console script ``name`` installed beside this Python (fails the test when it is missing)."""
    path = BIN / name
    if not path.exists():
        pytest.fail(f"console script {name} is not installed next to {sys.executable} (pip install -e .)")
    return path


def run_parallel(
    commands: Sequence[Sequence[str]], cwd: Path, timeout: float = 600
) -> List[subprocess.CompletedProcess]:
    """Run the commands concurrently (one thread each when several), wait for all; output goes to files in ``cwd``."""
    cwd.mkdir(parents=True, exist_ok=True)
    threads = 1 if len(commands) > 1 else 0
    procs = []
    t0 = time.time()
    for i, cmd in enumerate(commands):
        out = open(cwd / f"cmd{i}.stdout", "w+")
        err = open(cwd / f"cmd{i}.stderr", "w+")
        procs.append(
            (cmd, subprocess.Popen(list(cmd), stdout=out, stderr=err, cwd=cwd, env=subprocess_env(threads)), out, err)
        )
    deadline = time.time() + timeout
    results = []
    for cmd, proc, out, err in procs:
        try:
            proc.wait(timeout=max(1.0, deadline - time.time()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        out.seek(0)
        err.seek(0)
        results.append(subprocess.CompletedProcess(list(cmd), proc.returncode, out.read(), err.read()))
        print(f"{time.time() - t0:6.1f} s  {' '.join(str(c) for c in cmd[1:3])}")
        out.close()
        err.close()
    return results


def ns_train(args: List[str], cwd: Path, timeout: int = 900) -> subprocess.CompletedProcess:
    """The real ``ns-train`` in a subprocess (one thread, offline); fails the test with its log tail."""
    proc = subprocess.run(
        [str(BIN / "ns-train"), *args], capture_output=True, text=True, env=subprocess_env(1), cwd=cwd, timeout=timeout
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def copy_key(key: Path, folder: Path) -> Path:
    """A module's own copy of a session key (calibrate and export-key rewrite keys in place)."""
    folder.mkdir(parents=True, exist_ok=True)
    return Path(shutil.copy(key, folder / key.name))


@pytest.fixture(scope="session", autouse=True)
def one_thread_per_worker() -> None:
    """Under pytest-xdist each worker computes on one thread (also when torch was imported before this file)."""
    if WORKER:
        import torch

        torch.set_num_threads(1)


@pytest.fixture(scope="session", autouse=True)
def owner_keys_dir(tmp_path_factory) -> Path:
    """Owner keys written by default go to a per-session folder, never the user's own keys folder."""
    folder = tmp_path_factory.mktemp("owner-keys")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("GSTICKER_KEYS_DIR", str(folder))  # inherited by the ns-* subprocesses
        yield folder


@pytest.fixture(scope="session", autouse=True)
def cache_dir(tmp_path_factory) -> Path:
    """What gsticker derives from the environment (the config census) is kept in one folder for the session and
    its workers and subprocesses, never the user's own cache."""
    root = tmp_path_factory.getbasetemp()
    folder = (root.parent if WORKER else root) / "gsticker-cache"
    folder.mkdir(exist_ok=True)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("GSTICKER_CACHE_DIR", str(folder))
        yield folder


def built_once(tmp_path_factory, name: str, build: Callable[[Path], Path]) -> Path:
    """``build(folder)`` run once per test session, also across pytest-xdist workers (the first worker builds
    under a file lock in the session's shared temporary folder, the others wait and read what it built)."""
    root = tmp_path_factory.getbasetemp()
    if WORKER:
        root = root.parent
    folder = root / f"built-{name}"
    done = folder / ".built"
    with FileLock(str(root / f"built-{name}.lock")):
        if done.is_file():
            return Path(done.read_text())
        if folder.exists():
            shutil.rmtree(folder)  # a worker that failed half way
        folder.mkdir(parents=True)
        out = build(folder)
        done.write_text(str(out))
    return out


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A tiny generated scene (32 px; 6 train, 2 val, 2 test views; seed 0), made once per test session."""
    return built_once(tmp_path_factory, "tiny_scene", make_tiny_scene)


def make_tiny_scene(folder: Path) -> Path:
    out = folder / "scene"
    # In a subprocess: no OpenGL context (nor VTK's libraries) in the test process.
    cmd = [
        sys.executable,
        "-m",
        "gsticker_plugin.scene",
        "--output-dir",
        str(out),
        "--resolution",
        "32",
        "--num-train",
        "6",
        "--num-val",
        "2",
        "--num-test",
        "2",
        "--seed",
        "0",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for split in ("train", "val", "test"):
        assert (out / f"transforms_{split}.json").is_file()
    return out


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The shared data folder (``../shared`` relative to the repository root); skips the test when missing."""
    if not SHARED.is_dir():
        pytest.skip(f"shared data folder {SHARED} is missing")
    return SHARED


def train_tiny_nerfacto(scene: Path, ws: Path, steps: int) -> Path:
    """config.yml of a ``steps``-step nerfacto base (``NERFACTO_TINY``) on ``scene``, trained in ``ws``."""
    ns_train(
        [
            *NERFACTO_TINY,
            *CPU_ARGS,
            "--output-dir",
            str(ws),
            "--experiment-name",
            "nerfacto",
            "--timestamp",
            "base",
            "--max-num-iterations",
            str(steps),
            "--steps-per-save",
            str(steps),
            "blender-data",
            "--data",
            str(scene),
        ],
        ws,
    )
    return ws / "nerfacto" / "gsticker-nerfacto-small" / "base" / "config.yml"


@pytest.fixture(scope="session")
def tiny_base(tiny_scene, tmp_path_factory) -> Path:
    """config.yml of a 2-step nerfacto base on the tiny scene (read-only: copy it before changing it)."""
    return built_once(tmp_path_factory, "tiny_base", lambda ws: train_tiny_nerfacto(tiny_scene, ws, 2))


@pytest.fixture(scope="session")
def tiny_trained_base(tiny_scene, tmp_path_factory) -> Path:
    """config.yml of a 100-step nerfacto base on the tiny scene (some geometry for the field mark to ride on;
    read-only)."""
    return built_once(tmp_path_factory, "tiny_trained_base", lambda ws: train_tiny_nerfacto(tiny_scene, ws, 100))


@pytest.fixture(scope="session")
def tiny_sticker(tiny_base, tmp_path_factory) -> Dict[str, Path]:
    """A 10-step geometrysticker run on ``tiny_base`` carrying ``TINY_MESSAGE``: ``{base, run, key}`` (config.yml
    paths and the owner key; read-only: :func:`copy_key` before calibrating or exporting into a key)."""
    run = built_once(tmp_path_factory, "tiny_sticker", lambda ws: train_tiny_sticker(tiny_base, ws))
    return {"base": tiny_base, "run": run, "key": run.parent.parent / "run.gskey"}


def train_tiny_sticker(tiny_base: Path, ws: Path) -> Path:
    ckpt = max((tiny_base.parent / "nerfstudio_models").glob("step-*.ckpt"))
    key = ws / "gs" / "geometrysticker" / "run.gskey"
    ns_train(
        [
            "geometrysticker",
            "--load-checkpoint",
            str(ckpt),
            *CPU_ARGS,
            "--output-dir",
            str(ws),
            "--experiment-name",
            "gs",
            "--timestamp",
            "run",
            "--pipeline.message",
            TINY_MESSAGE,
            *TINY_STICKER_ARGS,
            "--pipeline.key-path",
            str(key),
        ],
        ws,
    )
    return ws / "gs" / "geometrysticker" / "run" / "config.yml"


# Fixtures that train with ns-train, render a scene or run an ns-* command: a test that uses one (directly or through
# another fixture) is marked ``slow`` here, so ``make test-fast`` (``-m "not slow"``) trains nothing.
SLOW_FIXTURES = {"tiny_scene", "tiny_base", "tiny_trained_base", "tiny_sticker", "shared_dir"}


# The longest test files, longest first (seconds measured under ``make test``): ``make test`` hands whole files to
# two workers in collection order (``--dist loadfile --no-loadscope-reorder``), so starting the long ones first keeps
# both workers busy to the end instead of leaving one long file running alone.
LONGEST_FILES = (
    "tests/test_geometrysticker.py",  # 247 s
    "tests/decoders/test_geometric.py",  # 228
    "tests/test_quickstart.py",  # 218
    "tests/test_shared.py",  # 210
    "tests/test_capture.py",  # 165
    "tests/recolor/test_edits.py",  # 147
    "tests/attacks/test_recipient.py",  # 125
    "tests/evaluation/test_evaluation.py",  # 105
    "tests/verify/test_check.py",  # 87
    "tests/bench/test_presets.py",  # 76
    "tests/evaluation/baselines/test_colormark.py",  # 68
    "tests/test_backgrounds.py",  # 52
)


def pytest_collection_modifyitems(config, items):
    for item in items:
        if SLOW_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
    rank = {name: i for i, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))


def synthetic_reference_view(st, r: int = 600, s: int = 24, seed: int = 0, with_rgb: bool = False):
    """A random reference view of ``r`` rays x ``s`` samples for sticker ``st`` (both signals; with ``with_rgb``
    also random sample colours, drawn last from the same generator)."""
    import torch

    from gsticker_plugin.decoders.reference import ReferenceView

    g = torch.Generator().manual_seed(seed)
    dens = torch.rand(r, s, 1, generator=g) * 5 * (torch.rand(r, s, 1, generator=g) > 0.6)
    psi = torch.sigmoid((dens - 2.5) * 4).reshape(-1, 1)
    open_index = (psi[:, 0] > 1e-3).nonzero().squeeze(-1)
    pos = torch.rand(r * s, 3, generator=g)
    rgb = torch.rand(r, s, 3, generator=g) if with_rgb else None
    with torch.no_grad():
        feats = st.features(pos[open_index])
    return ReferenceView(
        name="v",
        hw=(1, r),
        rays=torch.arange(r),
        density=dens,
        deltas=torch.full((r, s, 1), 0.1),
        steps=torch.linspace(2, 6, s).expand(r, s)[..., None].clone(),
        open_index=open_index,
        psi_scale=psi[open_index] * 2.0,
        features=feats,
        base_signal=torch.zeros(2, r),
        depth_scale=4.0,
        signals=("accumulation", "expected_depth"),
        rgb=rgb,
    )


def tiny_view_and_wrap(k=6, seed=0):
    """A 4x4 view whose 16 rays each cross 8 samples, a calibrated gate and a bilinear sticker (its weights drawn
    from ``seed``)."""
    import torch  # after triton (above)

    from gsticker_plugin.fastpath import ViewCache, render_signs
    from gsticker_plugin.sticker import DensityWrap, Gate, Sticker, WrapState

    g = torch.Generator().manual_seed(0)
    n, s = 16, 8
    density = torch.rand(n, s, 1, generator=g) * 4.0
    view = ViewCache(
        image=torch.zeros(4, 4, 3),
        active=torch.arange(n),
        positions=torch.rand(n, s, 3, generator=g) * 2 - 1,
        deltas=torch.full((n, s, 1), 0.1),
        density=density,
        rgb=torch.rand(n, s, 3, generator=g),
    )
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        sticker, gate = Sticker(num_bits=k, num_frequencies=2, hidden_dim=8, init_scale=0.5), Gate()
    gate.calibrate(density, torch.ones_like(density), quantile=0.3, amplitude=1.0)
    field = torch.nn.Module()
    field.get_density = lambda *a, **kw: None
    wrap = DensityWrap(field, "f", sticker, gate, WrapState(), torch.tensor([[-1.0] * 3, [1.0] * 3]))
    bg = torch.ones(3)
    # the cached clean image is the clean composite (as cache_view records it)
    view.image = render_signs(view, wrap, torch.zeros(k), bg)
    return view, wrap, bg


def one_error_line(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert lines and lines[-1].startswith("error: "), err
    assert sum(1 for ln in lines if ln.startswith("error: ")) == 1, err
    return lines[-1]


def small_key(message=None, **kw):
    """A key with 8-wide heads and a small bilinear sticker (weights from seed 0), message random unless given."""
    import torch

    from gsticker_plugin.heads import HeadConfig, Heads
    from gsticker_plugin.key import OwnerKey, random_message
    from gsticker_plugin.sticker import Sticker

    cfg = HeadConfig(width=8, depth=2)
    torch.manual_seed(0)
    heads = Heads(cfg, 48)
    sticker = Sticker(48, 2, 16, 2, 0.5, "bilinear")
    msg = random_message() if message is None else message
    return OwnerKey(
        owner_id="alice",
        message=msg,
        heads_config=vars(cfg),
        heads_state=heads.state_dict(),
        base={"checkpoint_sha256": "ab" * 32},
        geometry={"sticker_state": sticker.state_dict(), "null": None},
        **kw,
    )


def field_mark_key(**mark):
    """A field-mark key of owner alice (settings overridden by ``mark``)."""
    from gsticker_plugin.key import OwnerKey, message_from_owner_id

    return OwnerKey(
        owner_id="alice",
        message=message_from_owner_id("alice"),
        heads_config={},
        heads_state={},
        base={"checkpoint_sha256": "ab" * 32},
        field_mark={
            "table": "_model.t",
            "levels": [0, 1],
            "pattern_seed": 7,
            "amplitude": 0.01,
            "init_scale": 0.001,
            **mark,
        },
    )
