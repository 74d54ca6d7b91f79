"""The block library as the loader sees it: the shipped blocks, installed plugins, plugin files.

``load_library`` imports ``fwdstep.blocks`` (whose modules register their classes in
``fwdstep.core.registry``).  More blocks come only from what the *user who runs fwdstep*
chose (docs/writing-blocks.md) -- never from a diagram file:

* installed packages advertising an entry point in the group ``fwdstep.blocks`` (a module
  whose import registers blocks, or a Block class), loaded with the library;
* Python files named with ``--plugin FILE.py`` or ``load_diagram(..., plugins=[...])``
  (``load_plugins``); they are also recorded in ``$FWDSTEP_PLUGINS`` so that the worker
  processes of a sweep load the same files.
"""
from __future__ import annotations

import difflib
import hashlib
import importlib.util
import os
import sys

import fwdstep.blocks  # noqa: F401  (importing registers every library block)
from fwdstep.core.block import Block
from fwdstep.core.errors import ConfigError, UnknownBlockTypeError
from fwdstep.core.registry import REGISTRY, register

#: entry-point group of installed block packages
ENTRY_POINT_GROUP = "fwdstep.blocks"
#: environment variable listing plugin files (os.pathsep-separated), inherited by workers
PLUGINS_ENV = "FWDSTEP_PLUGINS"

_plugin_files: dict = {}          # absolute path -> module
_library_loaded = False


def load_library() -> dict[str, type]:
    """The registry with the library, installed entry points and ``$FWDSTEP_PLUGINS``."""
    global _library_loaded
    if not _library_loaded:
        _library_loaded = True
        _load_entry_points()
        env = os.environ.get(PLUGINS_ENV, "")
        files = [f for f in env.split(os.pathsep) if f]
        if files:
            load_plugins(files)
    return REGISTRY


#: installed plugins that failed to load: name -> why (their block types are missing)
_broken_entry_points: dict = {}


def _load_entry_points() -> None:
    """Register the blocks of every installed ``fwdstep.blocks`` entry point.  One that fails
    to load is reported once, naming the plugin (a ``FwdstepWarning``: the CLI's line
    ``fwdstep: warning: ...``), and left out: it is the installation's fault, not the
    diagram's, and a diagram that does not use its blocks runs; one that does is told, with
    its unknown block type, which plugin failed."""
    import warnings
    from importlib.metadata import entry_points
    from fwdstep.core.errors import FwdstepWarning, one_line
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
            if isinstance(obj, type) and issubclass(obj, Block) and \
                    REGISTRY.get(obj.__name__) is not obj:
                register(obj)
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # noqa: BLE001 - a SystemExit on import too
            why = one_line(f"{type(exc).__name__}: {getattr(exc, 'message', exc)}")[:300]
            _broken_entry_points[ep.name] = why
            warnings.warn(FwdstepWarning(
                f"the installed block plugin '{ep.name}' ({ep.value}, entry point "
                f"{ENTRY_POINT_GROUP}) failed to load and is left out: {why}"), stacklevel=2)


def load_plugins(paths) -> list:
    """Import block plugin files (each once per process); the modules.  A file that is
    missing, not a regular ``.py`` file, or fails to import is refused in one line."""
    load_library()
    modules = []
    for path in paths:
        modules.append(_load_file(str(path)))
    known = [f for f in os.environ.get(PLUGINS_ENV, "").split(os.pathsep) if f]
    for path in _plugin_files:
        if path not in known:
            known.append(path)
    os.environ[PLUGINS_ENV] = os.pathsep.join(known)
    return modules


def _load_file(path: str):
    full = os.path.realpath(path)
    if full in _plugin_files:
        return _plugin_files[full]
    if not os.path.isfile(full):
        raise ConfigError(f"plugin '{path}' is not a file")
    if not full.endswith(".py"):
        raise ConfigError(f"plugin '{path}' must be a Python file ending in .py")
    name = _module_name(full)
    spec = importlib.util.spec_from_file_location(name, full)
    module = importlib.util.module_from_spec(spec)
    module.__fwdstep_plugin__ = path
    with open(full, "rb") as fh:             # what is imported, for the record of each run
        data = fh.read()
    module.__fwdstep_sha256__ = hashlib.sha256(data).hexdigest()
    module.__fwdstep_source__ = data           # what workers and a sweep's identity get
    sys.modules[name] = module
    _plugin_files[full] = module
    try:
        # exactly the bytes hashed: the import system would take __pycache__'s bytecode when
        # the file was edited within the same second to the same size (its check is mtime
        # and size), running the old code under the new file's SHA-256
        exec(compile(data, full, "exec"), module.__dict__)  # noqa: S102 - the user's plugin
    except ConfigError as exc:
        del sys.modules[name], _plugin_files[full]
        raise ConfigError(f"plugin '{path}': {exc.message}") from None
    except BaseException as exc:  # noqa: BLE001 - one line naming the file
        del sys.modules[name], _plugin_files[full]
        if isinstance(exc, KeyboardInterrupt):
            raise
        line = ""
        tb = exc.__traceback__
        while tb is not None:
            if tb.tb_frame.f_code.co_filename == full:
                line = f":{tb.tb_lineno}"
            tb = tb.tb_next
        raise ConfigError(f"plugin '{path}{line}' failed to load: "
                          f"{type(exc).__name__}: {exc}") from None
    return module


def plugin_files(modules=None) -> list:
    """(absolute path, SHA-256 of the file as imported) of the plugin files loaded in this
    process whose module is one of ``modules`` (all when None), in load order (recorded by
    every run: ``fwdstep.results.provenance``)."""
    return [(path, module.__fwdstep_sha256__) for path, module in _plugin_files.items()
            if modules is None or module.__name__ in modules]


def file_sha256(path: str) -> str:
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def _module_name(full: str) -> str:
    """The module name of the plugin file at real path ``full`` (the same in every process,
    so a pickled spec naming a plugin class finds it in a worker)."""
    stem = os.path.splitext(os.path.basename(full))[0]
    tag = hashlib.sha256(full.encode()).hexdigest()[:10]
    return f"fwdstep_plugin_{''.join(c if c.isalnum() else '_' for c in stem)}_{tag}"


def plugin_sources(classes=None) -> dict:
    """The plugin files loaded in this process: real path -> the bytes imported (hashed in
    the record of each run; what a worker on another machine needs to load the same blocks,
    ``load_plugin_sources``, and what a sweep's identity hashes), never the file read again
    (edited since, or in an encoding its coding line declares, it would differ or fail);
    with ``classes``, only the files that define one of them (the blocks a diagram uses)."""
    modules = None if classes is None else {c.__module__ for c in classes}
    return {full: module.__fwdstep_source__ for full, module in _plugin_files.items()
            if modules is None or module.__name__ in modules}


def load_plugin_sources(sources: dict) -> None:
    """In a worker process: load plugin files from their bytes (``plugin_sources`` of the
    process that sent the jobs; text is taken as UTF-8), each once, under the module name
    it had there."""
    load_library()
    for full, data in sources.items():
        if full in _plugin_files or _module_name(full) in sys.modules:
            continue
        if isinstance(data, str):
            data = data.encode("utf-8")
        name = _module_name(full)
        module = importlib.util.module_from_spec(
            importlib.util.spec_from_loader(name, loader=None, origin=full))
        module.__file__ = full
        module.__fwdstep_plugin__ = full
        module.__fwdstep_sha256__ = hashlib.sha256(data).hexdigest()
        module.__fwdstep_source__ = data
        sys.modules[name] = module
        _plugin_files[full] = module
        try:
            exec(compile(data, full, "exec"), module.__dict__)  # noqa: S102 - the user's plugin
        except BaseException as exc:
            del sys.modules[name], _plugin_files[full]
            raise ConfigError(f"plugin '{full}' failed to load in a worker: "
                              f"{type(exc).__name__}: {exc}") from None


def lookup(type_name: str):
    reg = load_library()
    if type_name in reg:
        return reg[type_name]
    close = difflib.get_close_matches(str(type_name), list(reg), n=1, cutoff=0.5)
    if not close:
        lowered = {k.lower(): k for k in reg}
        if str(type_name).lower() in lowered:
            close = [lowered[str(type_name).lower()]]
    hint = (f"; did you mean '{close[0]}'?" if close else
            "; run 'fwdstep blocks' for the list; block types of your own are added with "
            "--plugin FILE.py (docs/writing-blocks.md)")
    if _broken_entry_points:
        hint += "; the installed block plugin " + ", ".join(
            f"'{name}' ({why})" for name, why in _broken_entry_points.items()) + \
            " failed to load"
    raise UnknownBlockTypeError(f"unknown block type '{type_name}'{hint}")
