"""The compiled-code cache: generated modules and numba's machine code, kept so that only the
first process running a structure pays the compile — and never usable against its user.

* The directory (``$FWDSTEP_CACHE_DIR``, default ``$XDG_CACHE_HOME/fwdstep`` or
  ``~/.cache/fwdstep``) is created private (0700).  One that is not a directory, not owned
  by the user, or writable by group or others is refused with a one-line reason and the
  program is compiled in memory (nothing read from or written to disk).
* A generated module is stored under the SHA-256 of its text and its content is checked
  against that hash before it is imported; numba's index and data files of a module are
  checked against the hashes recorded (``seal``) right after numba wrote them, before
  numba can load (unpickle) them.  A file changed since its record is discarded (one
  warning line) and compiled afresh; a file with no record (another process still
  compiling, or planted) is discarded quietly; recorded, intact files are kept, so
  processes compiling at the same time do not empty each other's cache.
* Any fault — a file where the directory should be, a read-only directory, a full disk, a
  truncated or foreign entry — gives one warning line on stderr and a fresh compile; the
  run goes on.
"""
from __future__ import annotations

import glob
import hashlib
import importlib.util
import json
import os
import stat
import sys
import tempfile
import types

PREFIX = "fwdstep_compiled_"


def cache_dir() -> str:
    env = os.environ.get("FWDSTEP_CACHE_DIR")
    if env:
        return env
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "fwdstep")


def warn(message: str) -> None:
    """One line on stderr (control characters shown escaped)."""
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in message)
    sys.stderr.write(f"fwdstep: warning: {text}\n")


def private_dir(path: str) -> str | None:
    """Create ``path`` private if missing; None when it is safe to use, else the reason."""
    try:
        os.makedirs(path, mode=0o700, exist_ok=True)
    except FileExistsError:
        return f"{path} exists and is not a directory"
    except OSError as exc:
        return f"cannot create {path}: {exc.strerror or exc}"
    try:
        st = os.stat(path)
    except OSError as exc:
        return f"cannot inspect {path}: {exc.strerror or exc}"
    if not stat.S_ISDIR(st.st_mode):
        return f"{path} is not a directory"
    if hasattr(os, "getuid") and st.st_uid != os.getuid():
        return f"{path} belongs to another user (uid {st.st_uid})"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"{path} is writable by other users (mode {stat.S_IMODE(st.st_mode):o})"
    if not os.access(path, os.W_OK | os.X_OK):
        return f"{path} is not writable"
    return None


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _numba_files(folder: str, name: str) -> list:
    pattern = os.path.join(folder, "__pycache__", f"{name}.*")
    return sorted(p for p in glob.glob(pattern) if p.endswith((".nbi", ".nbc")))


def compiled_before(module) -> bool:
    """Whether the run functions of a generated module (``load``) are compiled already: in
    this process, or in numba's cache beside it (their first call then loads machine code
    instead of compiling it)."""
    fn = getattr(module, "run_one", None)
    if fn is not None and getattr(fn, "signatures", None):
        return True
    path = getattr(module, "__file__", None)
    return bool(path) and bool(_numba_files(os.path.dirname(path), module.__name__))


def _manifest(folder: str, name: str) -> str:
    return os.path.join(folder, f"{name}.sums")


def _atomic_write(folder: str, path: str, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _prune(files: list, sums_path: str, relative) -> bool:
    """Remove the files numba must not read: those not recorded in ``sums_path`` (written by
    another process that has not recorded them yet, or by nobody we know: removed quietly,
    as they are no sign of harm) and those whose contents differ from the record (changed
    after it was written: True, the caller warns).  Recorded, intact files are kept, so a
    process starting while another compiles keeps the cache the others sealed."""
    try:
        with open(sums_path, encoding="utf-8") as fh:
            sums = json.load(fh)
    except (OSError, ValueError):
        sums = {}
    if not isinstance(sums, dict):
        sums = {}
    changed = False
    for f in files:
        recorded = sums.get(relative(f))
        if recorded is not None and _sha(_read(f)) == recorded:
            continue
        changed = changed or recorded is not None
        try:
            os.unlink(f)
        except OSError:
            pass
    return changed


def _check_numba_files(folder: str, name: str) -> None:
    """Remove numba's files of ``name`` that do not match the recorded hashes (``_prune``)."""
    files = _numba_files(folder, name)
    if files and _prune(files, _manifest(folder, name), os.path.basename):
        warn(f"compiled-code cache entry {name} does not match its recorded hashes; "
             "compiling afresh")


def _read(path: str) -> bytes:
    with open(path, "rb") as fh:
        return fh.read()


def load(source: str) -> types.ModuleType:
    """The module of generated ``source``: from the cache when it is safe and intact,
    else compiled in memory (with one warning line saying why)."""
    data = source.encode()
    digest = _sha(data)
    name = PREFIX + digest[:32]
    if name in sys.modules:
        return sys.modules[name]
    folder = cache_dir()
    reason = private_dir(folder)
    if reason is not None:
        _REFUSALS_TOLD.add(reason)
        warn(f"compiled-code cache refused: {reason}; compiling in memory")
        return _in_memory(source, name)
    path = os.path.join(folder, f"{name}.py")
    try:
        if os.path.exists(path) and _sha(_read(path)) != digest:
            warn(f"compiled-code cache entry {name}.py does not match its hash (truncated or "
                 "replaced); compiling afresh")
            for f in _numba_files(folder, name) + [_manifest(folder, name)]:
                if os.path.exists(f):
                    os.unlink(f)
            _atomic_write(folder, path, data)
        elif not os.path.exists(path):
            for f in _numba_files(folder, name):   # orphans of an unknown writer
                os.unlink(f)
            _atomic_write(folder, path, data)
        _check_numba_files(folder, name)
        if _sha(_read(path)) != digest:             # re-read: what is imported is checked
            raise OSError("entry changed while loading")
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except (OSError, ImportError, SyntaxError, ValueError) as exc:
        warn(f"compiled-code cache unusable ({_describe(exc)}); compiling in memory")
        return _in_memory(source, name)
    module.__fwdstep_cache__ = (folder, name)
    sys.modules[name] = module
    return module


def seal(module) -> None:
    """Record the hashes of numba's files of ``module`` (after a compile wrote them), so a
    later process loads only what this one wrote.  Faults only warn."""
    where = getattr(module, "__fwdstep_cache__", None)
    if where is None:
        return
    folder, name = where
    try:
        files = _numba_files(folder, name)
        sums = {os.path.basename(f): _sha(_read(f)) for f in files}
        target = _manifest(folder, name)
        _record(folder, target, sums)
    except OSError as exc:
        warn(f"compiled-code cache: could not record hashes ({_describe(exc)})")


# ---------------------------------------------------------------------------- kernel caches
#: numba's cache files of jitted block kernels live in ``<cache>/kernels/<key>``, where the key
#: hashes the source files the kernel depends on (its module and every helper's module) and
#: the numba and Python versions: an edited block gets a new folder, never stale code.
KERNELS = "kernels"
_SUMS = "sums.json"


def _tree_files(folder: str) -> list:
    return sorted(p for p in glob.glob(os.path.join(folder, "**", "*"), recursive=True)
                  if p.endswith((".nbi", ".nbc")))


def kernel_folder(key: str) -> str | None:
    """The private folder for numba's cache of the kernels with this key, its files checked
    against the sums recorded by ``seal_folder`` (mismatching files removed); None when no
    safe folder can be had (the kernels are then compiled in memory)."""
    base = cache_dir()
    root = os.path.join(base, KERNELS)
    folder = os.path.join(root, key)
    for path in (base, root, folder):
        if private_dir(path) is not None:
            return None            # load() says why, once, for the generated module
    files = _tree_files(folder)
    if files and _prune(files, os.path.join(folder, _SUMS),
                        lambda f: os.path.relpath(f, folder)):
        warn(f"compiled kernel cache {key} does not match its recorded hashes; compiling "
             "the changed kernels afresh")
    return folder


def seal_folder(folder: str) -> None:
    """Record the hashes of numba's files in a kernel folder (faults only warn)."""
    try:
        sums = {os.path.relpath(f, folder): _sha(_read(f)) for f in _tree_files(folder)}
        target = os.path.join(folder, _SUMS)
        _record(folder, target, sums)
    except OSError as exc:
        warn(f"compiled-code cache: could not record hashes ({_describe(exc)})")


# ---------------------------------------------------------------- native block kernels
#: machine code of the NumPy path's native block kernels (``fwdstep.compiled.native_block``):
#: ``<cache>/native/<key>.o`` and its SHA-256 in ``<key>.sha256``, the key hashing the LLVM IR
#: and the target (so the IR, not the block, names the code)
NATIVE = "native"


#: the reasons a cache folder was refused that this process has printed (the NumPy path's
#: native kernels ask for the folder at each kernel: the user is told once, not never)
_REFUSALS_TOLD: set = set()


def _native_paths(key: str):
    base = cache_dir()
    folder = os.path.join(base, NATIVE)
    for path in (base, folder):
        reason = private_dir(path)
        if reason is not None:
            if reason not in _REFUSALS_TOLD:
                _REFUSALS_TOLD.add(reason)
                warn(f"compiled-code cache refused: {reason}; native kernels compiled in "
                     "memory")
            return None
    return folder, os.path.join(folder, f"{key}.o"), os.path.join(folder, f"{key}.sha256")


def native_object(key: str) -> bytes | None:
    """The object code stored under ``key``, if the cache is safe to use and the file
    matches the hash recorded when it was written; else None (a mismatching entry is
    removed with one warning line)."""
    paths = _native_paths(key)
    if paths is None:
        return None
    _, obj, digest = paths
    try:
        data, recorded = _read(obj), _read(digest).decode("ascii").strip()
    except (OSError, UnicodeDecodeError):
        return None
    if _sha(data) == recorded:
        return data
    warn(f"native kernel cache entry {key[:16]} does not match its recorded hash; "
         "compiling afresh")
    for path in (obj, digest):
        try:
            os.unlink(path)
        except OSError:
            pass
    return None


def store_native_object(key: str, data: bytes) -> None:
    """Keep object code under ``key`` (the file, then its hash); faults only warn."""
    paths = _native_paths(key)
    if paths is None:
        return
    folder, obj, digest = paths
    try:
        _atomic_write(folder, obj, data)
        _atomic_write(folder, digest, _sha(data).encode("ascii"))
    except OSError as exc:
        warn(f"native kernel cache: could not store ({_describe(exc)})")


def _record(folder: str, target: str, sums: dict) -> None:
    """Write the hashes ``sums`` to ``target`` atomically, unless it already holds them."""
    try:
        with open(target, encoding="utf-8") as fh:
            if json.load(fh) == sums:
                return
    except (OSError, ValueError):
        pass
    _atomic_write(folder, target, json.dumps(sums, sort_keys=True).encode())


def _describe(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    return f"{type(exc).__name__}: {exc}"[:200]


def _in_memory(source: str, name: str) -> types.ModuleType:
    """Compile ``source`` without any file (numba's disk cache off)."""
    module = types.ModuleType(name)
    module.__file__ = f"<{name}>"
    code = compile(source.replace("CACHE = True", "CACHE = False", 1), f"<{name}>", "exec")
    exec(code, module.__dict__)  # noqa: S102 - text generated by fwdstep, never user text
    sys.modules[name] = module
    return module
