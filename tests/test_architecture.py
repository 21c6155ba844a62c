"""docs/architecture.md's layers are the code's: every module of the package has a layer there, and no import (at the
top of a file or inside a function) reaches a layer above its own."""

from __future__ import annotations

import ast
import re
from pathlib import Path
from typing import Dict, List, Optional, Tuple

ROOT = Path(__file__).resolve().parent.parent
SOURCES = ("gsticker_plugin", "method_configs")


def layers(page: Path = ROOT / "docs" / "architecture.md") -> List[Tuple[str, List[str]]]:
    """The Layers table, top down: ``(layer, paths)``; a bare file name in a cell lies beside the cell's last path."""
    out = []
    for line in page.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or not cells[1].startswith("`"):
            continue
        paths: List[str] = []
        for item in re.findall(r"`([^`]+)`", cells[1]):
            if "/" not in item and paths:
                item = paths[-1].rsplit("/", 1)[0] + "/" + item
            paths.append(item)
        out.append((cells[0], paths))
    return out


def layer_of(path: str, table: List[Tuple[str, List[str]]]) -> Optional[int]:
    """Index of the layer holding ``path`` (the longest matching path wins), or None."""
    best, depth = None, -1
    for i, (_, paths) in enumerate(table):
        for p in paths:
            if (path == p or (p.endswith("/") and path.startswith(p))) and len(p) > depth:
                best, depth = i, len(p)
    return best


def module_file(name: str) -> Optional[str]:
    """The repository path of module ``name`` (``a.b.c`` -> ``a/b/c.py`` or ``a/b/c/__init__.py``), if it is ours."""
    parts = name.split(".")
    if parts[0] not in SOURCES:
        return None
    for n in range(len(parts), 0, -1):
        base = "/".join(parts[:n])
        for cand in (base + ".py", base + "/__init__.py"):
            if (ROOT / cand).is_file():
                return cand
    return None


def imports(path: Path, here: str) -> List[str]:
    """Every module the file ``path`` (at repository path ``here``) imports, absolute; ``from x import y`` also names
    ``x.y``, which may be a module."""
    package = here[: -len(".py")].replace("/", ".").rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([mod] if mod else []))
            out.append(mod)
            out += [f"{mod}.{a.name}" for a in node.names]
    return out


def upward_imports(files: List[Tuple[str, Path]], table: List[Tuple[str, List[str]]]) -> Dict[str, List[str]]:
    """For each ``(repository path, file)``, the imports that reach a layer above its own."""
    upward: Dict[str, List[str]] = {}
    for here, path in files:
        mine = layer_of(here, table)
        for name in imports(path, here):
            target = module_file(name)
            theirs = None if target is None or target == here else layer_of(target, table)
            if theirs is not None and mine is not None and theirs < mine:
                upward.setdefault(here, []).append(f"{target} ({table[theirs][0]})")
    return upward


def package_files() -> List[Tuple[str, Path]]:
    return sorted((str(p.relative_to(ROOT)), p) for src in SOURCES for p in (ROOT / src).rglob("*.py"))


def test_every_module_has_a_layer_on_the_architecture_page():
    table = layers()
    assert [name for name, _ in table][:2] == ["commands", "verdicts"] and len(table) >= 5
    assert [here for here, _ in package_files() if layer_of(here, table) is None] == []


def test_no_module_imports_from_a_layer_above_its_own():
    assert upward_imports(package_files(), layers()) == {}


def test_the_layer_check_catches_a_library_module_importing_a_verdict_module_inside_a_function(tmp_path):
    probe = tmp_path / "metrics.py"
    probe.write_text("def f():\n    from gsticker_plugin.verify.check import verify\n    from . import errors\n")
    found = upward_imports([("gsticker_plugin/metrics.py", probe)], layers())
    assert found == {"gsticker_plugin/metrics.py": ["gsticker_plugin/verify/check.py (verdicts)"] * 2}
