"""The explicit registry mapping YAML ``type:`` names to block classes.

Library modules register their classes with ``@register``; this module only holds the
mapping.  Filling it -- the shipped library (``blocks/``), installed entry points and plugin
files -- is ``fwdstep.structure.library``'s work, one layer up, so the blocks depend on the
registry and never the other way round.
"""
from __future__ import annotations

import sys

from fwdstep.core.errors import ConfigError

REGISTRY: dict[str, type] = {}


def origin(cls) -> str:
    """Where a block class comes from, for messages."""
    mod = sys.modules.get(cls.__module__)
    where = getattr(mod, "__fwdstep_plugin__", None) or cls.__module__
    return f"{cls.__name__} in {where}"


def register(cls):
    """Class decorator: make ``cls`` available as ``type: <ClassName>``."""
    name = cls.__name__
    if name in REGISTRY and REGISTRY[name] is not cls:
        old = REGISTRY[name]
        if (old.__module__, old.__qualname__) != (cls.__module__, cls.__qualname__):
            raise ConfigError(f"block type '{name}' is defined twice: {origin(old)} and "
                              f"{origin(cls)}; rename one of them")
    cls.type_name = name
    REGISTRY[name] = cls
    return cls
