"""A sweep's identity: what it is, recorded when it starts and compared by ``--resume``.

``--resume`` fills in the variants a sweep has not finished.  Comparing only the swept
values would let a resumed run mix two studies in one sweep.csv (another ``--set``,
another ``t_final``, an edited diagram file).  So a sweep records, in its output folder
(``sweep-identity.json``, listed in the manifest), everything that decides its numbers:

* ``files``: the SHA-256 of the diagram file, of every subsystem file it includes and of
  every file a block's ``Param("file")`` names (a URDF), by path relative to the diagram's
  folder;
* ``plugins``: the SHA-256 of every plugin file (``--plugin``, ``$FWDSTEP_PLUGINS``) that
  defines a block the diagram uses;
* ``overrides``: every ``--set`` (and ``--backend``) value;
* ``settings``: the simulation settings as loaded (``t_final``, step, solver, backend, ...);
* ``sweep``: the grid, the random parameters and their design, samples and seed, the seed
  parameter, whether signals are kept; ``variants``: the SHA-256 of every variant's values;
* ``fwdstep``: the version that ran it.

``check_identity`` refuses a resume whose identity differs, in one line naming what differs.
How the sweep runs (``--workers``, ``--scheduler``, ``--max-memory``, ``--batch-size``,
``--sequential``) does not change the numbers and is not part of it.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os

import numpy as np

from fwdstep.core.errors import ConfigError, OutputError, printable
from fwdstep.core.version import __version__
from fwdstep.results.sweep_format import IDENTITY_FILE

#: the fields compared, in the order a difference is reported
FIELDS = ("files", "plugins", "overrides", "settings", "sweep", "variants", "fwdstep")


def _sha256(path: str) -> str:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    except OSError as exc:
        return f"unreadable: {exc.strerror}"
    return h.hexdigest()


def canonical(value):
    """``value`` as plain JSON data (arrays as lists, dataclasses and named tuples as
    mappings), so that equal settings give equal text."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: canonical(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if hasattr(value, "_asdict"):
        return {k: canonical(v) for k, v in value._asdict().items()}
    if isinstance(value, dict):
        return {str(k): canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [canonical(v) for v in value]
    if isinstance(value, (np.ndarray, np.generic)):
        return canonical(np.asarray(value).tolist())
    if isinstance(value, float) and not np.isfinite(value):
        return repr(value)
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)


def _files(path: str, loader) -> dict:
    """Every file that decides the variants' numbers: the files the loader read (the
    diagram, its subsystems, the files its blocks' ``Param("file")`` name, e.g. a URDF:
    ``DiagramSpec.sources``) and, as a fallback, the loader's document cache."""
    home = os.path.dirname(os.path.realpath(path))
    found = {os.path.realpath(path)}
    for source in getattr(loader.base, "sources", None) or []:
        if getattr(source, "text", None) is None and isinstance(source.path, str):
            found.add(os.path.realpath(source.path))
    for key in getattr(loader, "cache", {}):
        if isinstance(key, tuple) and key and isinstance(key[0], str):
            found.add(key[0])
    return {_shown(f, home): _sha256(f) for f in sorted(found)}


def _shown(path: str, home: str) -> str:
    rel = os.path.relpath(path, home)
    return path if rel.startswith("..") else rel


def sweep_identity(path: str, loader, overrides: dict, all_values: list,
                   options: dict) -> dict:
    """The identity of a sweep (see the module docstring)."""
    from fwdstep.structure.library import plugin_sources
    values = json.dumps(canonical(all_values), sort_keys=True)
    return {"written_by": "fwdstep sweep",
            "fwdstep": __version__,
            "files": _files(path, loader),
            "plugins": {p: hashlib.sha256(data).hexdigest() for p, data in sorted(
                plugin_sources({e.cls for e in loader.base.blocks}).items())},
            "overrides": canonical(dict(overrides)),
            "settings": canonical(loader.base.simulation),
            "sweep": canonical(options),
            "variants": {"count": len(all_values),
                         "sha256": hashlib.sha256(values.encode()).hexdigest()}}


def check_identity(out, identity: dict) -> None:
    """Refuse (one ``ConfigError``) to resume into ``out`` (an ``OutputDir``) a sweep whose
    identity differs from the one recorded there, naming what differs."""
    shown = os.path.join(out.requested, IDENTITY_FILE)
    if IDENTITY_FILE not in out.owned():
        if out.owned("parts/"):
            raise ConfigError(f"cannot resume: {printable(shown)} is missing, so nothing says "
                              "the finished batches are this sweep's; pass --force to start "
                              "again")
        return                                  # nothing finished: nothing to mix
    try:
        with open(os.path.join(out.target, IDENTITY_FILE), encoding="utf-8") as fh:
            recorded = json.loads(fh.read(1 << 24))
        if not isinstance(recorded, dict):
            raise ValueError("not a mapping")
    except (OSError, ValueError) as exc:
        raise OutputError(f"{printable(shown)} cannot be read ({exc}); pass --force to start "
                          "again") from None
    differences = []
    for name in FIELDS:
        differences += _differences(name, recorded.get(name), canonical(identity[name]))
    if differences:
        more = f" (and {len(differences) - 4} more)" if len(differences) > 4 else ""
        raise ConfigError(f"--resume refused: {out.requested} holds a different sweep: "
                          f"{'; '.join(differences[:4])}{more}; run the same command as "
                          "before, or --force to start again, or another -o")


_WHAT = {"files": "file", "plugins": "plugin", "overrides": "--set", "settings": "simulation",
         "sweep": "sweep option", "variants": "variants", "fwdstep": "fwdstep version"}


def _differences(field: str, before, now) -> list:
    if before == now:
        return []
    what = _WHAT[field]
    if isinstance(before, dict) and isinstance(now, dict) and field != "variants":
        out = []
        for key in list(before) + [k for k in now if k not in before]:
            a, b = before.get(key, _ABSENT), now.get(key, _ABSENT)
            if a == b:
                continue
            if field in ("files", "plugins"):
                state = ("not used before" if a is _ABSENT else "not used now" if b is _ABSENT
                         else "content changed")
                out.append(f"{what} {printable(key)}: {state}")
            else:
                out.append(f"{what} {printable(key)}: {_brief(a)} before, {_brief(b)} now")
        return out
    if field == "variants" and isinstance(before, dict) and isinstance(now, dict) and \
            before.get("count") != now.get("count"):
        return [f"{before.get('count')} variants before, {now.get('count')} now"]
    if field == "variants":
        return ["the swept values differ"]
    return [f"{what}: {_brief(before)} before, {_brief(now)} now"]


class _Absent:
    def __repr__(self) -> str:
        return "absent"


_ABSENT = _Absent()


def _brief(value) -> str:
    if value is _ABSENT or value is None:
        return "absent" if value is _ABSENT else "none"
    text = json.dumps(value) if not isinstance(value, str) else value
    text = printable(text)
    return text if len(text) <= 60 else text[:57] + "..."


__all__ = ["sweep_identity", "check_identity", "canonical", "FIELDS"]
