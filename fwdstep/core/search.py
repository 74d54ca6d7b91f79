"""Where diagram files are found: the search path for subsystems, and what may be read at all.

A subsystem's ``file: NAME`` (a relative path, ``/`` as separator) is looked up in order:

1. next to the file that names it (the including diagram's own folder);
2. in the library shipped with fwdstep (``diagrams/lib`` of the source tree, installed as the
   package data ``fwdstep.library``): ``lib/plant.yaml`` names its ``plant.yaml``;
3. in each folder of the environment variable ``FWDSTEP_PATH`` (separated like ``PATH``).

The first candidate that exists wins.  Includes are confined: a candidate is used only when it
lies (after resolving ``..`` and symbolic links) inside the top-level diagram's folder tree,
the shipped library or a ``FWDSTEP_PATH`` folder (an absolute name too).  Only regular
files are read (never a FIFO, a device such as ``/dev/zero``, a socket or a directory), for
the top-level diagram as well, so nothing can hang or stream without end.
"""
from __future__ import annotations

import os
import stat

from fwdstep.core.errors import ConfigError

PATH_VARIABLE = "FWDSTEP_PATH"
LIBRARY_PREFIX = "lib/"


def shipped_library() -> str | None:
    """The folder of the shipped subsystem library (``lib/...`` names), or None: the installed
    package data ``fwdstep/library`` or, in a source checkout, ``diagrams/lib``."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))     # the fwdstep package
    for folder in (os.path.join(here, "library"),
                   os.path.join(os.path.dirname(here), "diagrams", "lib")):
        if os.path.isdir(folder):
            return folder
    return None


def user_path() -> list:
    """The folders of ``FWDSTEP_PATH`` (empty entries ignored), as absolute paths."""
    raw = os.environ.get(PATH_VARIABLE, "")
    return [os.path.abspath(p) for p in raw.split(os.pathsep) if p.strip()]


def _inside(path: str, root: str) -> bool:
    try:
        return os.path.commonpath([path, root]) == root
    except ValueError:          # different drives
        return False


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def check_regular_file(path: str, what: str = "the diagram") -> None:
    """Refuse anything but an existing regular file, without opening it (a FIFO would block,
    ``/dev/zero`` would never end)."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise ConfigError(f"{what} cannot be read: {exc.strerror or 'not found'}",
                          file=path) from None
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError(f"{what} is {_kind(st.st_mode)}, not a regular file; fwdstep reads "
                          "only regular files", file=path)


class SearchPath:
    """The roots includes may come from, fixed once per top-level diagram."""

    def __init__(self, top_file: str, redirects: dict | None = None):
        self.library = shipped_library()
        #: (including file, name as written) -> the file to read instead: a run's recorded
        #: copy (``fwdstep.results.provenance``), so a rerun reads exactly what was run
        self.redirects = {(os.path.normpath(os.path.abspath(by)) if by else by, name): target
                          for (by, name), target in (redirects or {}).items()}
        self.user = user_path()
        given = [os.path.dirname(os.path.abspath(top_file))]
        given += ([self.library] if self.library else []) + self.user
        self.roots_real = [os.path.realpath(r) for r in given]
        self.roots_text = [os.path.normpath(os.path.abspath(r)) for r in given] + self.roots_real
        self.documents: dict = {}     # realpath -> parsed document, filled by the loader
        self.read: list = []          # every file the loader read (structure.model.SourceFile)

    def allowed(self, path: str) -> bool:
        """``path`` lies inside one of the roots, both as written (no ``..`` out of it) and
        after resolving symbolic links."""
        norm = os.path.normpath(os.path.abspath(path))
        if not any(_inside(norm, r) for r in self.roots_text):
            return False
        real = os.path.realpath(norm)
        return any(_inside(real, r) for r in self.roots_real)

    def _redirected(self, name: str, including_file: str | None):
        if not self.redirects:
            return None
        key = os.path.normpath(os.path.abspath(including_file)) if including_file else \
            including_file
        return self.redirects.get((key, name))

    def data_file(self, name: str, including_file: str | None) -> str:
        """The absolute path of a block's data file (``Param("file")``, e.g. a URDF) named
        ``name`` by ``including_file`` (None: typed on the command line, relative to the
        working directory).  Relative names are relative to the file that names them, as
        subsystem files are; data files are not confined (they are read by the block, which
        says when one is missing)."""
        target = self._redirected(name, including_file or "")
        if target is not None:
            return target
        if not name:
            return name
        expanded = os.path.expanduser(name)
        if os.path.isabs(expanded) or not including_file:
            return os.path.normpath(os.path.abspath(expanded))
        return os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(including_file)),
                                             expanded))

    def candidates(self, name: str, including_file: str) -> list:
        """(label, path) in search order for ``file: name``."""
        here = os.path.dirname(including_file)
        out = [("next to the diagram", os.path.normpath(os.path.join(here, name)))]
        if os.path.isabs(name):       # allowed only inside the roots (checked by the caller)
            return out
        if self.library and name.startswith(LIBRARY_PREFIX):
            out.append(("in fwdstep's library", os.path.normpath(
                os.path.join(self.library, name[len(LIBRARY_PREFIX):]))))
        for folder in self.user:
            out.append((f"in {PATH_VARIABLE}", os.path.normpath(os.path.join(folder, name))))
        return out

    def resolve(self, name: str, including_file: str, what: str, line) -> str:
        """The file ``file: name`` of ``including_file`` stands for; ConfigError otherwise.
        Messages name the places looked in, never the content of any file."""
        target = self._redirected(name, including_file)
        if target is not None:
            return target
        if name.startswith("~") or "\\" in name:
            raise ConfigError(f"{what}: file '{name}' must be a path with '/' relative to the "
                              f"diagram, the library (lib/NAME) or {PATH_VARIABLE}",
                              file=including_file, line=line)
        tried, refused = [], False
        for label, path in self.candidates(name, including_file):
            if not self.allowed(path):
                refused = True
                continue
            try:
                st = os.stat(path)
            except OSError:
                tried.append(path)
                continue
            if not stat.S_ISREG(st.st_mode):
                raise ConfigError(f"{what}: file '{name}' is {_kind(st.st_mode)} ({path}), not "
                                  "a regular file", file=including_file, line=line)
            return path
        if refused and not tried:
            raise ConfigError(f"{what}: file '{name}' leaves the diagram's folder; subsystems "
                              f"come from the diagram's folder tree, fwdstep's library (lib/NAME) "
                              f"or a folder in {PATH_VARIABLE}", file=including_file, line=line)
        raise ConfigError(f"{what}: file '{name}' not found; looked in: {'; '.join(tried)}",
                          file=including_file, line=line)
