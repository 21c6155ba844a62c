"""The quick start a new user copies: README's block is docs/getting-started.md's, and its lines, run verbatim in a
fresh folder with a fresh home on the CPU, end in an OWNED verdict."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path
from typing import List

import pytest
from conftest import BIN, subprocess_env

ROOT = Path(__file__).resolve().parent.parent


def quick_start(page: Path) -> List[str]:
    """The command lines of the first ``bash`` block after the heading that starts with "Quick start"."""
    text = page.read_text()
    start = re.search(r"^#+ Quick start.*$", text, re.M)
    assert start, f"{page} has no 'Quick start' heading"
    block = re.search(r"```bash\n(.*?)```", text[start.end() :], re.S)
    assert block, f"{page} has no bash block after its 'Quick start' heading"
    return [line for line in block.group(1).splitlines() if line.strip()]


def test_readme_and_getting_started_give_the_same_quick_start():
    lines = quick_start(ROOT / "docs" / "getting-started.md")
    assert lines == quick_start(ROOT / "README.md")
    assert [line.split()[0] for line in lines] == ["ns-gsticker-scene", "ns-train", "ns-train", "ns-verify-owner"]


@pytest.mark.slow
@pytest.mark.timeout(1800)  # four commands, the base's 100 steps among them
def test_the_quick_start_copied_verbatim_reaches_an_owned_verdict_on_the_cpu(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    env = subprocess_env(1, HOME=str(home), PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    for name in ("XDG_DATA_HOME", "XDG_CACHE_HOME", "GSTICKER_KEYS_DIR", "GSTICKER_CACHE_DIR", "GSTICKER_IDENTITY"):
        env.pop(name, None)
    env["CUDA_VISIBLE_DEVICES"] = ""  # a CPU-only machine: the presets must pick the CPU themselves
    for line in quick_start(ROOT / "README.md"):
        proc = subprocess.run(["bash", "-c", line], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=1200)
        assert proc.returncode == 0, f"{line}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    assert "VERDICT: OWNED" in proc.stdout
