"""What made a run, kept with its results so that it can be read, redone and built on.

Every run written by ``Result.write_files`` (``fwdstep run``, ``Result.save``) and every
sweep records, in ``summary.json`` / ``sweep.json`` under ``"provenance"``:

* ``fwdstep_version`` (and ``source_commit`` of a git checkout), Python and NumPy versions,
  and those of scipy, numba, llvmlite and pinocchio when the process loaded them;
* ``command``: the command line, ``sets``: every ``--set`` as typed (block paths included),
  ``overrides``: the same as values (from the Python API too);
* ``backend`` used and ``simulation``: every solver setting as run;
* ``plugins``: each plugin file that defines a block type of the diagram, with the
  SHA-256 of what was imported;
* ``files``: a COPY of the diagram and of every file it read (subsystems, URDFs), in the
  output directory under ``diagram/`` (listed in its manifest), each with its original
  path and SHA-256; ``includes``: which name in which file stands for which copy.

``load_recorded`` turns that record back into a load of the copy (``fwdstep rerun``,
``fwdstep report``): the copy's ``file:`` names are redirected to the other copies, so the
working tree is never read.  Paths in the record are relative to the output directory, so
the directory can be moved or read from any folder.
"""
from __future__ import annotations

import datetime
import hashlib
import os
import platform
import sys

from fwdstep.core.errors import ConfigError, OutputError, printable
from fwdstep.core.files import atomic_write

#: the folder of an output directory that holds the copy of the diagram as run
COPY_DIR = "diagram"


def environment() -> dict:
    """Versions of what computed the numbers."""
    import numpy as np
    from fwdstep.core.version import __version__, source_commit
    out = {"fwdstep_version": __version__}
    commit = source_commit()
    if commit:
        out["source_commit"] = commit
    out.update(python=platform.python_version(), numpy=np.__version__,
               platform=platform.platform(terse=True))
    for name in OPTIONAL_NUMERICS:       # those this process loaded (none is imported here)
        module = sys.modules.get(name)
        if module is not None and getattr(module, "__version__", None):
            out[name] = str(module.__version__)
    return out


#: optional packages that compute numbers of a run when loaded: scipy (solve_ivp, the
#: analyses), numba and llvmlite (the compiled backend; llvmlite also the native kernels of
#: the NumPy path's robot blocks), pinocchio (URDF robots)
OPTIONAL_NUMERICS = ("scipy", "numba", "llvmlite", "pinocchio")


def plugins_used(spec) -> list:
    """The plugin files that define a block type of ``spec``, with the SHA-256 of what was
    imported (other plugins loaded in the process took no part in the run)."""
    from fwdstep.structure.library import plugin_files
    modules = {entry.cls.__module__ for entry in spec.blocks}
    return [{"file": path, "sha256": digest} for path, digest in plugin_files(modules)]


def _layout(spec) -> dict:
    """Original absolute path -> its copy's name under ``diagram/``: the top-level diagram
    by its own name, files in its folder tree where they are relative to it, files of
    fwdstep's library under ``library/``, anything else under ``external/``."""
    from fwdstep.core.search import shipped_library
    top = os.path.abspath(spec.sources[0].path) if spec.sources else os.path.abspath(spec.file)
    here = os.path.dirname(top)
    library = shipped_library()
    out: dict = {}
    taken: set = set()
    for source in spec.sources:
        path = os.path.abspath(source.path)
        if path in out:
            continue
        if _inside(path, here):
            name = os.path.relpath(path, here)
        elif library and _inside(path, library):
            name = os.path.join("library", os.path.relpath(path, library))
        else:
            name = os.path.join("external", os.path.basename(path))
        name = name.replace(os.sep, "/")
        stem, ext = os.path.splitext(name)
        k = 2
        while name in taken:                   # two files of one name from different folders
            name, k = f"{stem}-{k}{ext}", k + 1
        taken.add(name)
        out[path] = f"{COPY_DIR}/{name}"
    return out


def _inside(path: str, root: str) -> bool:
    try:
        return os.path.commonpath([path, root]) == root
    except ValueError:
        return False


def copy_sources(spec, outdir: str, write=None) -> dict:
    """Copy every file ``spec`` was read from into ``outdir/diagram/``; the record's
    ``files``, ``includes`` and ``diagram`` (the copy of the top-level file).  ``write(name,
    data)``: how a copy is written (a sweep's ``OutputDir.put``: listed, no link followed);
    default: an atomic write into ``outdir`` (a fresh staging directory)."""
    layout = _layout(spec)
    files = []
    given = {os.path.abspath(s.path): s.text for s in spec.sources if s.text is not None}
    for path, copy in layout.items():
        try:
            if path in given:                  # built in Python: the text that was loaded
                data = given[path].encode("utf-8")
            else:
                with open(path, "rb") as fh:
                    data = fh.read()
        except OSError as exc:
            raise OutputError(f"cannot copy {printable(path)} into the output directory: "
                              f"{exc.strerror}") from None
        if write is not None:
            write(copy, data)
        else:
            target = os.path.join(outdir, *copy.split("/"))
            os.makedirs(os.path.dirname(target), exist_ok=True)
            atomic_write(target, lambda fh, data=data: fh.write(data), binary=True)
        kind = next(s.kind for s in spec.sources if os.path.abspath(s.path) == path)
        files.append({"copy": copy, "source": path, "kind": kind, "bytes": len(data),
                      "sha256": hashlib.sha256(data).hexdigest()})
    includes = []
    for source in spec.sources:
        if source.by is None:
            continue
        by = "" if source.by == "" else layout.get(os.path.abspath(source.by))
        entry = {"by": by, "named": source.named, "copy": layout[os.path.abspath(source.path)]}
        if by is not None and entry not in includes:
            includes.append(entry)
    top = files[0]["copy"] if files else None
    return {"diagram": top, "files": files, "includes": includes}


def record(result, copies: dict | None, extra: dict | None = None) -> dict:
    """The provenance of ``result`` (its diagram, settings and environment); ``copies`` from
    ``copy_sources``; ``extra``: what only the caller knows (``command``, ``sets``)."""
    return record_spec(result.diagram.spec, copies, extra,
                       backend=getattr(result, "backend", None))


def record_spec(spec, copies: dict | None, extra: dict | None = None,
                backend: str | None = None) -> dict:
    """``record`` for a loaded spec (a sweep's base diagram)."""
    import dataclasses
    from fwdstep.core.jsonable import jsonable as _jsonable
    out = {**environment(),
           "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds")}
    out["diagram"] = (copies or {}).get("diagram")
    out["diagram_source"] = os.path.abspath(spec.sources[0].path if spec.sources else spec.file)
    out["overrides"] = _jsonable(dict(spec.overrides))
    out["backend"] = backend or spec.simulation.backend
    out["simulation"] = _jsonable({k: v for k, v in dataclasses.asdict(spec.simulation).items()
                                   if k not in ("defaulted", "given")})
    out["plugins"] = plugins_used(spec)
    if copies:
        out["files"] = copies["files"]
        out["includes"] = copies["includes"]
    out.update(extra or {})          # the caller's word wins (a rerun keeps the original's)
    return out


# ---------------------------------------------------------------------------- reading back
def read_record(run_dir: str) -> dict:
    """The provenance stored in ``run_dir`` (summary.json of a run, sweep.json of a sweep);
    OutputError in one line when there is none."""
    import json
    for name in ("summary.json", "sweep.json"):
        path = os.path.join(run_dir, name)
        if os.path.isfile(path):
            try:
                with open(path, encoding="utf-8") as fh:
                    prov = json.load(fh).get("provenance")
            except (OSError, ValueError, AttributeError) as exc:
                raise OutputError(f"cannot read {printable(path)}: {exc}") from None
            if not isinstance(prov, dict) or not prov.get("diagram"):
                raise OutputError(f"{printable(path)} records no copy of the diagram (written "
                                  "by an older fwdstep); run the diagram again")
            return prov
    raise OutputError(f"{printable(run_dir)} holds no saved run or sweep (no summary.json or "
                      "sweep.json)")


def _in_copy(run_dir: str, name) -> str:
    """The absolute path of the copy ``name`` (relative to ``run_dir``), refused when it
    would leave the run's ``diagram/`` folder (a record is data, never trusted)."""
    root = os.path.realpath(os.path.join(run_dir, COPY_DIR))
    if not isinstance(name, str):
        raise OutputError(f"{printable(run_dir)}: the record names no file")
    path = os.path.realpath(os.path.join(run_dir, *name.split("/")))
    if not _inside(path, root):
        raise OutputError(f"{printable(run_dir)}: the record names {printable(name)}, outside "
                          f"its {COPY_DIR}/ folder")
    if not os.path.isfile(path):
        raise OutputError(f"{printable(run_dir)}: the copy {printable(name)} of the diagram as "
                          "run is missing")
    return path


def load_recorded(run_dir: str, prov: dict | None = None) -> tuple:
    """(path of the copy of the diagram, overrides, redirects) to load the diagram exactly
    as it was run: ``load_diagram(path, overrides, redirects=redirects)``."""
    prov = read_record(run_dir) if prov is None else prov
    top = _in_copy(run_dir, prov.get("diagram"))
    redirects = {}
    for entry in prov.get("includes") or []:
        by = entry.get("by")
        key = "" if by == "" else _in_copy(run_dir, by)
        redirects[(key, entry.get("named"))] = _in_copy(run_dir, entry.get("copy"))
    sets = prov.get("sets")
    if sets is not None:
        from fwdstep.structure.spec import parse_override
        overrides = dict(parse_override(text) for text in sets)
    else:
        overrides = dict(prov.get("overrides") or {})
    return top, overrides, redirects


def check_plugins(prov: dict) -> list:
    """The plugin files of the record, each still the file that was imported; ConfigError in
    one line naming the first that is missing or changed."""
    from fwdstep.structure.library import file_sha256
    files = []
    for entry in prov.get("plugins") or []:
        path = entry.get("file")
        try:
            now = file_sha256(path)
        except (OSError, TypeError):
            raise ConfigError(f"plugin {printable(str(path))} of the recorded run is missing; "
                              "cannot re-run exactly") from None
        if now != entry.get("sha256"):
            raise ConfigError(f"plugin {printable(path)} has changed since the run (SHA-256 "
                              f"{now[:12]}... , recorded {str(entry.get('sha256'))[:12]}...); "
                              "refusing to re-run with other code")
        files.append(path)
    return files


def recorded_diagram(summary: dict, run_dir: str | None):
    """The compiled diagram of a saved run as it was run: the copy kept in ``run_dir``,
    loaded with the recorded ``--set`` values and plugin files (report, animate), never
    the working tree.  A run written before fwdstep kept copies: its stored path (relative
    to the working directory or absolute) and parameters; FileNotFoundError when that file
    is not there."""
    from fwdstep.core.errors import FwdstepError
    from fwdstep.structure.compiler import load_diagram
    prov = summary.get("provenance")
    if isinstance(prov, dict) and prov.get("diagram") and run_dir is not None:
        top, overrides, redirects = load_recorded(run_dir, prov)
        _load_recorded_plugins(prov)
        return load_diagram(top, overrides, redirects=redirects)
    path = summary.get("diagram")
    if not path or not os.path.isfile(path):
        raise FileNotFoundError(f"the diagram file {path} is not here; no picture")
    params = summary.get("parameters")
    try:
        return load_diagram(path, params if isinstance(params, dict) else None)
    except FwdstepError:
        return load_diagram(path)


def _load_recorded_plugins(prov: dict) -> None:
    """Load the run's plugin files that are still there (drawing and replaying run none of
    their numbers, so a changed file is used, not refused; rerun refuses it)."""
    from fwdstep.structure.library import load_plugins
    files = [e.get("file") for e in prov.get("plugins") or []
             if isinstance(e.get("file"), str) and os.path.isfile(e["file"])]
    if files:
        load_plugins(files)


__all__ = ["recorded_diagram", "COPY_DIR", "copy_sources", "record", "read_record", "load_recorded",
           "check_plugins", "environment"]
