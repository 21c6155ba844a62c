"""What a suspect run's config.yml may build: the classes and functions a Nerfstudio run can contain.

A config.yml is a tree of config dataclasses whose ``_target`` fields (and a few other fields, such as a data
manager's ``collate_fn``) name code that ``setup()`` later calls. A suspect file may name any code, so a tree is
accepted only when, for every config object in it,

* every attribute is one of its class's fields (no extra state);
* a config object sits in a field whose declared type allows its class (a dataparser where a dataparser goes);
* every class or function it holds is what that field holds in the class's own defaults or in an installed
  Nerfstudio method's config (the *census*): a dataparser config's ``_target`` is its own dataparser, never
  another function of a trusted package.

Plain values (numbers, strings, paths, enums, tuples, lists and dicts of them) are not code and pass.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import typing
from pathlib import PurePath
from typing import Any, Dict, Iterator, List, Optional, Set, Tuple

from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.models.base_model import ModelConfig

from gsticker_plugin.errors import GStickerError

Census = Dict[Tuple[type, str], Set[Any]]

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


def _record(census: Census, root: Any) -> None:
    for obj in _config_objects(root):
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name, None)
            if _code(v):
                census.setdefault((type(obj), f.name), set()).add(_origin(v))


@functools.lru_cache(maxsize=1)
def installed_census() -> Census:
    """(config class, field) -> the classes and functions that field holds in an installed Nerfstudio method."""
    # deferred: all_methods imports every installed method's entry point, this plugin's among them
    from nerfstudio.configs.method_configs import all_methods

    census: Census = {}
    for cfg in all_methods.values():
        _record(census, cfg)
    return census


@functools.lru_cache(maxsize=None)
def _default_of(cls: type) -> Optional[Any]:
    try:
        return cls()
    except Exception:  # a config class without defaults for every field
        return None


def _allowed_code(cls: type, name: str) -> Set[Any]:
    """What field ``name`` of config class ``cls`` may name: its default and what installed methods put there."""
    allowed = set(installed_census().get((cls, name), set()))
    default = _default_of(cls)
    if default is not None and _code(getattr(default, name, None)):
        allowed.add(_origin(getattr(default, name)))
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
                if _origin(value) not in _allowed_code(cls, name):
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
