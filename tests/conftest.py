"""Shared pytest fixtures.

``tiny_scene``: a 32 px Blender-format dataset (6 train / 2 val / 2 test views, seed 0) generated once per
session with the plugin's own scene generator. ``shared_dir``: the project's shared data folder
(``../shared`` beside the repository root), or a skip when it is missing.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

# Host quirk: after pyvista/VTK has rendered off screen in a process (Mesa's llvmpipe loads its LLVM), the first
# import of triton's libtriton in that process segfaults -- and torch._dynamo imports triton through
# torchvision.ops, i.e. every Nerfstudio model import does. Loading triton first avoids the clash.
try:
    import triton  # noqa: F401
except Exception:  # triton is optional (CPU-only torch wheels)
    pass

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = REPO_ROOT.parent / "shared"


@pytest.fixture(scope="session", autouse=True)
def owner_keys_dir(tmp_path_factory) -> Path:
    """Owner keys written by default go to a per-session folder, never the user's own keys folder."""
    import os

    folder = tmp_path_factory.mktemp("owner-keys")
    old = os.environ.get("GSTICKER_KEYS_DIR")
    os.environ["GSTICKER_KEYS_DIR"] = str(folder)  # inherited by the ns-* subprocesses
    yield folder
    if old is None:
        os.environ.pop("GSTICKER_KEYS_DIR", None)
    else:
        os.environ["GSTICKER_KEYS_DIR"] = old


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A tiny generated scene (32 px; 6 train, 2 val, 2 test views; seed 0), made once per test session."""
    out = tmp_path_factory.mktemp("tiny_scene") / "scene"
    # In a subprocess: no OpenGL context (nor VTK's libraries) in the test process.
    cmd = [sys.executable, "-m", "gsticker_plugin.scene", "--output-dir", str(out), "--resolution", "32",
           "--num-train", "6", "--num-val", "2", "--num-test", "2", "--seed", "0"]
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
