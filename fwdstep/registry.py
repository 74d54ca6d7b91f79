"""The explicit registry mapping YAML ``type:`` names to block classes.

Library modules register their classes with ``@register``; ``blocks/__init__.py`` imports
the library modules explicitly (no scanning, no ``eval``).
"""
from __future__ import annotations

import difflib

from .errors import UnknownBlockTypeError

REGISTRY: dict[str, type] = {}


def register(cls):
    """Class decorator: make ``cls`` available as ``type: <ClassName>``."""
    name = cls.__name__
    if name in REGISTRY and REGISTRY[name] is not cls:
        raise RuntimeError(f"block type {name!r} registered twice")
    cls.type_name = name
    REGISTRY[name] = cls
    return cls


def load_library() -> dict[str, type]:
    import blocks  # noqa: F401  (importing registers every library block)
    return REGISTRY


def lookup(type_name: str):
    reg = load_library()
    if type_name in reg:
        return reg[type_name]
    close = difflib.get_close_matches(str(type_name), list(reg), n=1, cutoff=0.5)
    if not close:
        lowered = {k.lower(): k for k in reg}
        if str(type_name).lower() in lowered:
            close = [lowered[str(type_name).lower()]]
    hint = f"; did you mean '{close[0]}'?" if close else "; run 'fwdstep blocks' for the list"
    raise UnknownBlockTypeError(f"unknown block type '{type_name}'{hint}")
