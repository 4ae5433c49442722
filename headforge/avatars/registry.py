"""Methods by name: ``register`` a :class:`~headforge.avatars.base.Method` subclass, ``get`` an
instance. The built-in methods register on first lookup, so importing this module stays cheap."""

from __future__ import annotations

from headforge.avatars.base import Method
from headforge.errors import HeadforgeError

_METHODS: dict[str, type[Method]] = {}
_BUILTIN = {"nha": "headforge.avatars.nha.method", "pointavatar": "headforge.avatars.pointavatar.method"}


def register(cls: type[Method]) -> type[Method]:
    """Class decorator: make ``cls`` available as ``cls.name`` (``headforge fit NAME``)."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    _METHODS[cls.name] = cls
    return cls


def names() -> list[str]:
    return sorted(set(_METHODS) | set(_BUILTIN))


def get(name: str) -> Method:
    """An instance of the method registered as ``name``."""
    if name not in _METHODS and name in _BUILTIN:
        import importlib

        importlib.import_module(_BUILTIN[name])
    if name not in _METHODS:
        raise HeadforgeError(f"unknown avatar method {name!r}; known: {', '.join(names())}")
    return _METHODS[name]()
