"""What a suspect run's config.yml may build: the classes and functions a Nerfstudio run can contain.

A config.yml is a tree of config dataclasses whose ``_target`` fields (and a few other fields, such as a data
manager's ``collate_fn``) name code that ``setup()`` later calls. A suspect file may name any code, so a tree is
accepted only when, for every config object in it,

* every attribute is one of its class's fields (no extra state);
* a config object sits in a field whose declared type allows its class (a dataparser where a dataparser goes);
* every class or function it holds is what that field holds in the class's own defaults or in an installed
  Nerfstudio method's config (the *census*): a dataparser config's ``_target`` is its own dataparser, never
  another function of a trusted package; a lambda or a local function (whose name is not unique) is never accepted.

Plain values (numbers, strings, paths, enums, tuples, lists and dicts of them) are not code and pass.

The census names code by ``module:qualname``. Taking it imports every installed method (seconds), so it is kept in
``census-<fingerprint>.json`` in the cache folder (``$GSTICKER_CACHE_DIR``, else ``$XDG_CACHE_HOME/gsticker``, else
``~/.cache/gsticker``), where the fingerprint is the sha256 of what the census is drawn from: the Python
environment (prefix, version, every installed distribution and version), the ``nerfstudio.method_configs`` entry
points, the files that define them (path, size, modification time) and ``NERFSTUDIO_METHOD_CONFIGS``. Any change
there names another file, and the census is taken again.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import importlib.metadata
import importlib.util
import json
import os
import sys
import tempfile
import typing
from pathlib import Path, PurePath
from typing import Any, Dict, Iterator, List, Optional, Set, Tuple

from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.models.base_model import ModelConfig

from gsticker_plugin.errors import GStickerError

Census = Dict[Tuple[str, str], Set[str]]
"""(config class name, field) -> names of the classes and functions that field holds (names: :func:`code_name`)."""

CENSUS_FORMAT = 1

MODEL_CONFIG_FIELDS = ("base_model", "inner_model")
"""Fields typed ``Any`` for tyro's sake that hold a wrapped run's model config (the sticker's base, a recolor's
inner run): a :class:`ModelConfig` is required there."""


def _code(value: Any) -> bool:
    """Whether ``value`` names code: a class or a function (not a config object, enum member or path)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return False
    if isinstance(value, (enum.Enum, PurePath)):
        return False
    return isinstance(value, type) or callable(value) or hasattr(value, "__origin__")


def _origin(value: Any) -> Any:
    """A generic alias's class (``ParallelDataManager[DepthDataset]`` -> ``ParallelDataManager``)."""
    return getattr(value, "__origin__", value)


def _config_objects(value: Any, seen: Optional[Set[int]] = None) -> Iterator[Any]:
    """Every dataclass instance in ``value`` (through fields, lists, tuples and dict values)."""
    seen = set() if seen is None else seen
    if id(value) in seen:
        return
    seen.add(id(value))
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        yield value
        for f in dataclasses.fields(value):
            yield from _config_objects(getattr(value, f.name, None), seen)
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _config_objects(v, seen)
    elif isinstance(value, dict):
        for v in value.values():
            yield from _config_objects(v, seen)


def code_name(value: Any) -> str:
    """``module:qualname`` of a class or function (of a generic alias's class)."""
    value = _origin(value)
    return f"{getattr(value, '__module__', '?')}:{getattr(value, '__qualname__', repr(value))}"


def _record(census: Census, root: Any) -> None:
    for obj in _config_objects(root):
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name, None)
            if _code(v):
                census.setdefault((code_name(type(obj)), f.name), set()).add(code_name(v))


def cache_dir() -> Path:
    """Where gsticker keeps what it derives from the installed environment."""
    if os.environ.get("GSTICKER_CACHE_DIR"):
        return Path(os.environ["GSTICKER_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "gsticker"


def _file_stamp(module: str) -> List[Any]:
    """(path, size, mtime) of the file that defines ``module`` (importing its parent packages, not it)."""
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        return [module, None]
    origin = getattr(spec, "origin", None) if spec is not None else None
    if not origin or not os.path.isfile(origin):
        return [module, None]
    st = os.stat(origin)
    return [origin, st.st_size, st.st_mtime_ns]


def census_fingerprint() -> str:
    """sha256 (hex) of what :func:`installed_census` is drawn from (the module's docstring lists it)."""
    dists = sorted(
        {(d.metadata["Name"] or "?", d.version or "?") for d in importlib.metadata.distributions()},
        key=lambda nv: (nv[0].lower(), nv[1]),
    )
    points = sorted((ep.name, ep.value) for ep in importlib.metadata.entry_points(group="nerfstudio.method_configs"))
    modules = ["nerfstudio.configs.method_configs"] + [value.split(":")[0] for _, value in points]
    what = {
        "format": CENSUS_FORMAT,
        "prefix": sys.prefix,
        "python": sys.version,
        "distributions": dists,
        "entry_points": points,
        "files": [_file_stamp(m) for m in modules],
        "env": os.environ.get("NERFSTUDIO_METHOD_CONFIGS"),
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()


def take_census() -> Census:
    """The census of every installed Nerfstudio method's config (imports them all)."""
    # deferred: all_methods imports every installed method's entry point, this plugin's among them
    from nerfstudio.configs.method_configs import all_methods

    census: Census = {}
    for cfg in all_methods.values():
        _record(census, cfg)
    return census


def _read_census(path: Path) -> Optional[Census]:
    try:
        rows = json.loads(path.read_text())
        return {(str(c), str(f)): {str(n) for n in names} for c, f, names in rows}
    except (OSError, ValueError, TypeError):
        return None


def _write_census(path: Path, census: Census) -> None:
    rows = sorted([c, f, sorted(names)] for (c, f), names in census.items())
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    except OSError:
        return
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(rows, f)
        os.replace(tmp, path)
    except OSError:
        Path(tmp).unlink(missing_ok=True)


@functools.lru_cache(maxsize=1)
def installed_census() -> Census:
    """(config class, field) -> the classes and functions that field holds in an installed Nerfstudio method, read
    from the cache folder when the environment is the one it was taken in (else taken, and kept there)."""
    path = cache_dir() / f"census-{census_fingerprint()}.json"
    census = _read_census(path)
    if census is None:
        census = take_census()
        _write_census(path, census)
    return census


@functools.lru_cache(maxsize=None)
def _default_of(cls: type) -> Optional[Any]:
    try:
        return cls()
    except Exception:  # a config class without defaults for every field
        return None


def _allowed_code(cls: type, name: str) -> Set[str]:
    """What field ``name`` of config class ``cls`` may name (:func:`code_name`): its default and what installed
    methods put there."""
    allowed = set(installed_census().get((code_name(cls), name), set()))
    default = _default_of(cls)
    if default is not None and _code(getattr(default, name, None)):
        allowed.add(code_name(getattr(default, name)))
    return allowed


def _classes_of(annotation: Any) -> Optional[Tuple[type, ...]]:
    """The classes a declared field type allows (None: any, e.g. ``Any``)."""
    if annotation is Any:
        return None
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _classes_of(typing.get_args(annotation)[0])
    if origin is typing.Union or str(origin) == "types.UnionType":
        out: List[type] = []
        for a in typing.get_args(annotation):
            got = _classes_of(a)
            if got is None:
                return None
            out += list(got)
        return tuple(out)
    if origin is not None:
        return (origin,) if isinstance(origin, type) else None
    return (annotation,) if isinstance(annotation, type) else None


@functools.lru_cache(maxsize=None)
def _hints(cls: type) -> Dict[str, Any]:
    try:
        return typing.get_type_hints(cls, include_extras=True)
    except Exception:  # forward references that do not resolve: no declared types to check
        return {}


def _declared_classes(cls: type, name: str) -> Optional[Tuple[type, ...]]:
    if name in MODEL_CONFIG_FIELDS:
        return (ModelConfig,)
    hint = _hints(cls).get(name)
    if hint is None:
        return None
    classes = _classes_of(hint)
    # tyro.conf markers wrap the type in Annotated; Optional adds NoneType
    return tuple(c for c in classes if c is not type(None)) if classes is not None else None


def refusal(config: Any) -> Optional[str]:
    """Why the config tree ``config`` is refused (None: it builds only what a Nerfstudio run can contain)."""
    for obj in _config_objects(config):
        cls = type(obj)
        names = {f.name for f in dataclasses.fields(obj)}
        extra = sorted(set(vars(obj)) - names)
        if extra:
            return f"{cls.__name__} has fields that it does not declare ({', '.join(extra[:3])})"
        for name in sorted(names):
            value = getattr(obj, name, None)
            if _code(value):
                if "<" in code_name(value) or code_name(value) not in _allowed_code(cls, name):
                    what = getattr(value, "__qualname__", repr(value))
                    return (
                        f"{cls.__name__}.{name} names {getattr(value, '__module__', '?')}.{what}, "
                        "which neither its defaults nor an installed method put there"
                    )
            elif dataclasses.is_dataclass(value) and not isinstance(value, type):
                if not isinstance(value, InstantiateConfig) and not cls.__module__.startswith("nerfstudio"):
                    continue
                declared = _declared_classes(cls, name)
                if declared is not None and declared and not isinstance(value, declared):
                    return f"{cls.__name__}.{name} holds a {type(value).__name__}, not a {declared[0].__name__}"
            elif isinstance(value, dict):
                for v in value.values():
                    if _code(v):
                        return f"{cls.__name__}.{name} names code inside a dict"
            elif isinstance(value, (list, tuple)):
                for v in value:
                    if _code(v):
                        return f"{cls.__name__}.{name} names code inside a list"
    return None


def check(config: Any, source: str) -> None:
    """Raise a one-line :class:`GStickerError` when ``config`` (read from ``source``) is refused."""
    if not isinstance(config, InstantiateConfig):
        raise GStickerError(f"{source} is not a Nerfstudio run config; pass RUN/config.yml")
    why = refusal(config)
    if why is not None:
        raise GStickerError(f"{source} is refused: {why}; only config.yml files written by Nerfstudio are read")
