"""Writing files safely: never outside the output folder, never through a symbolic link, never
a truncated file (write to a temporary file, then rename)."""
from __future__ import annotations

import os
import shutil
import tempfile

from fwdstep.core.errors import OutputError, printable


def safe_path(outdir: str, name: str) -> str:
    """``outdir/name``, refusing any name that would leave ``outdir``."""
    if os.path.basename(name) != name or name in ("", ".", "..") or "\x00" in name:
        raise OutputError(f"refusing to write '{name}': not a plain file name inside {outdir}")
    if not name.isprintable():
        raise OutputError(f"refusing to write '{printable(name)}': control characters in a file "
                          "name")
    base = os.path.realpath(outdir)
    path = os.path.join(base, name)
    if os.path.islink(path):           # never written through: atomic_write would follow it
        raise OutputError(f"refusing to write '{name}': it is a symbolic link in {outdir}")
    return path


def atomic_write(path: str, write, binary: bool = False, commit: bool = True):
    """Write to a temporary file in the same directory, then rename it over ``path``.

    ``path`` is always either the old file or the complete new one, never a truncated file,
    and no temporary file is left behind.  With ``commit=False`` the rename is deferred:
    the return value is a context manager yielding a function that performs it (the
    temporary file is removed if the block is left without calling it)."""
    directory = os.path.dirname(path)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=directory)
    try:
        os.fchmod(fd, 0o666 & ~_umask())          # as open() would create it, not 0600
        with os.fdopen(fd, "wb" if binary else "w") as fh:
            write(fh)
        if commit:
            os.replace(tmp, path)
            return None
    except BaseException:
        _unlink(tmp)
        raise
    return _Deferred(tmp, path)


def atomic_write_path(path: str, write_to) -> str:
    """``atomic_write`` for writers that want a file name (NetCDF): ``write_to(tmp)``
    creates ``tmp`` inside a private directory (mode 0700, beside ``path``: nobody can plant
    a link at that name), which is then renamed over ``path``.  ``path`` itself must not be a
    symbolic link (a rename would replace the link, never write through it)."""
    if os.path.islink(path):
        raise OutputError(f"refusing to write '{printable(path)}': it is a symbolic link")
    staging = tempfile.mkdtemp(prefix=".tmp-", dir=os.path.dirname(path) or ".")
    try:
        tmp = os.path.join(staging, os.path.basename(path))
        write_to(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return path


class _Deferred:
    def __init__(self, tmp: str, path: str):
        self.tmp, self.path, self.done = tmp, path, False

    def __enter__(self):
        return self.commit

    def commit(self) -> None:
        os.replace(self.tmp, self.path)
        self.done = True

    def __exit__(self, *exc) -> bool:
        if not self.done:
            _unlink(self.tmp)
        return False


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
