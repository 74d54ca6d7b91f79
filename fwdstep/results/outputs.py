"""An output directory as a transaction: the one way fwdstep writes results to disk.

Every writer (``fwdstep run``, sweeps, figures, reports) goes through ``OutputDir``::

    with OutputDir(outdir, force=force, expected=["result.npz", "run.png"]) as out:
        ...                              # simulate
        result.write_files(out.dir)      # any writer: plain files into out.dir
        plot_result(result, out.dir)
        written = out.commit()           # one rename puts everything in place

What it promises:

* **One run per directory.**  ``OutputDir`` takes an exclusive lock (``fcntl.flock`` on
  ``<parent>/.<name>.fwdstep-lock``) when it is entered; a second run into the same directory
  is refused at once with the holder's pid, host, command and start time.  A lock left by a
  killed process is released by the kernel, so it never needs cleaning up by hand.
* **All or nothing.**  Writers write into ``out.dir``, a private staging directory (mode
  0700, beside the target, same file system).  ``commit()`` writes ``manifest.json`` (the
  files of this run with their sizes and SHA-256) and moves the staging directory into place
  with one ``rename``.  When the target already exists it is first renamed aside, and what
  this run did not supersede (the user's files, earlier figures) is moved into the new
  directory (earlier fwdstep files stay in the manifest): at every instant the
  target holds either the complete old results or the complete new ones, never a new
  ``summary.json`` beside an old ``result.npz``.  (The one exception: an existing directory
  that is, or contains, the current directory is not renamed away under the user's shell,
  and one whose parent the user cannot write holds its own lock and staging directory;
  there the files are moved in one by one, the manifest last.)  Leaving the ``with`` block
  without ``commit()`` removes the staging directory.
* **Never replaces what fwdstep did not write.**  An existing entry is fwdstep's when
  ``manifest.json`` lists it (or, for directories written before manifests existed, when it
  is a regular ``result.npz``/``summary.json``/``sweep.csv``).  ``force`` allows replacing
  fwdstep's own results; nothing, not even ``force``, replaces another file, a directory or a
  symbolic link with the same name as a new file.  ``expected`` names the files a run will
  write, so these refusals happen before any work is done.
* **A killed writer leaves nothing half done.**  The next run into the directory (holding
  the lock, so nobody else is writing) puts back a directory a killed commit had renamed
  aside and removes abandoned staging directories.
* **Symbolic links are not followed.**  New files are created in the fresh staging
  directory, where nobody else can plant a link; links in the old directory are moved like
  any other foreign entry, never written through.

A writer that must put files in place while it is still running (a sweep keeping finished
variants for ``--resume``) holds ``OutputDir.lock_only(outdir)`` and writes each file with
``out.put(name, write)`` (``name`` may be ``SUBDIR/NAME``): staged in a private directory,
listed in the manifest, renamed into place, never over an entry the manifest does not list,
never through a link; ``out.discard(names)`` removes only listed files (``--force``), and a
failure (a full disk) is one ``OutputError``.
"""
from __future__ import annotations

import contextlib
import datetime
import fcntl
import hashlib
import json
import os
import shutil
import socket
import stat
import sys
import time
import tempfile

from fwdstep.core.errors import OutputError, printable

MANIFEST_FILE = "manifest.json"
#: private staging directories of ``OutputDir.put`` inside the output directory
PUT_PREFIX = ".fwdstep-put-"
#: files fwdstep wrote before manifests existed (regular files with these names are ours)
LEGACY_FILES = ("result.npz", "summary.json", "sweep.csv")


class OutputDir:
    """See the module docstring.  ``expected``: names of the files this run will write (the
    first one that already exists decides the "pass --force" message)."""

    def __init__(self, outdir: str, force: bool = False, expected=()):
        self.requested = outdir
        self.force = force
        self.expected = list(expected)
        self.target = os.path.join(os.path.realpath(os.path.dirname(os.path.abspath(outdir))
                                                    or "/"),
                                   os.path.basename(os.path.abspath(outdir)))
        if os.path.islink(self.target):          # -o pointing at a link: the user's choice
            self.target = os.path.realpath(self.target)
        self.parent = os.path.dirname(self.target)
        self.name = os.path.basename(self.target)
        # where the lock and the staging directory live: beside the target, or inside it
        # when only the target (not its parent) is writable (see ``_place``)
        self.home, self.prefix, self.inside = self.parent, f".{self.name}.fwdstep-", False
        self.dir: str | None = None
        self._lock_fd: int | None = None
        self._committed = False
        self._keep = False                         # staging kept when commit was refused

    # ------------------------------------------------------------------ enter / leave
    def __enter__(self) -> "OutputDir":
        self._open()
        try:
            self.dir = tempfile.mkdtemp(prefix=f"{self.prefix}new-", dir=self.home)
        except BaseException:
            self._unlock()
            raise
        return self

    def _open(self) -> None:
        """The target checked, its folder made, the lock taken, a killed writer's leftovers
        recovered and the existing files checked (the lock released if that fails)."""
        self._check_target()
        try:
            os.makedirs(self.parent, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create {printable(self.parent)}: "
                              f"{exc.strerror or exc}") from None
        self._place()
        self._lock()
        try:
            self._recover()
            self._check_existing()
        except BaseException:
            self._unlock()
            raise

    def __exit__(self, *exc) -> bool:
        try:
            if not self._committed and not self._keep and self.dir is not None:
                shutil.rmtree(self.dir, ignore_errors=True)
        finally:
            self._unlock()
        return False

    @classmethod
    @contextlib.contextmanager
    def lock_only(cls, outdir: str, force: bool = False, expected=()):
        """Hold the directory's lock (and check ``expected`` as ``OutputDir`` does) without
        staging: for writers that must put files in place while they run."""
        out = cls(outdir, force, expected)
        out._open()
        try:
            yield out
        finally:
            out._unlock()

    # ------------------------------------------------------------------ checks
    def _check_target(self) -> None:
        if os.path.lexists(self.target) and not os.path.isdir(self.target):
            raise OutputError(f"output directory {printable(self.requested)} exists and is not "
                              "a directory")

    def _place(self) -> None:
        """An existing, writable target in a directory the user cannot write to (a results
        folder in a shared project): lock and stage inside it, commit file by file."""
        if (os.path.isdir(self.target) and not os.access(self.parent, os.W_OK | os.X_OK)
                and os.access(self.target, os.W_OK | os.X_OK)):
            self.home, self.prefix, self.inside = self.target, ".fwdstep-", True

    def _recover(self) -> None:
        """Under the lock, leftovers of a writer that was killed (SIGKILL, power loss) are
        its own: a directory renamed aside with no new one in place is put back (the
        complete old results), and abandoned staging directories are removed."""
        prefix = self.prefix
        try:
            entries = sorted(os.listdir(self.home))
        except OSError:
            return
        for entry in entries:
            path = os.path.join(self.home, entry)
            if not entry.startswith(prefix) or os.path.islink(path) or not os.path.isdir(path):
                continue
            kind = entry[len(prefix):].split("-", 1)[0]
            if kind == "old" and not self.inside and not os.path.lexists(self.target):
                os.rename(path, self.target)
            elif kind in ("old", "new") and os.stat(path).st_uid == os.getuid():
                shutil.rmtree(path, ignore_errors=True)
        with contextlib.suppress(OSError):      # private directories of ``put``
            for entry in os.listdir(self.target):
                path = os.path.join(self.target, entry)
                if (entry.startswith(PUT_PREFIX) and not os.path.islink(path)
                        and os.path.isdir(path) and os.stat(path).st_uid == os.getuid()):
                    shutil.rmtree(path, ignore_errors=True)

    def _check_existing(self) -> None:
        if not os.path.isdir(self.target):
            return
        if foreign_manifest(self.target):
            raise OutputError(_not_ours(os.path.join(self.requested, MANIFEST_FILE),
                                        os.path.join(self.target, MANIFEST_FILE)))
        ours = owned_entries(self.target)
        existing = [n for n in self.expected if os.path.lexists(os.path.join(self.target, n))]
        for n in existing:
            if n not in ours:
                raise OutputError(_not_ours(os.path.join(self.requested, n),
                                            os.path.join(self.target, n)))
        if existing and not self.force:
            raise OutputError(f"{printable(os.path.join(self.requested, existing[0]))} already "
                              "exists; pass --force to overwrite it or -o to choose another "
                              "directory")

    # ------------------------------------------------------------------ lock
    def _lock_path(self) -> str:
        return os.path.join(self.home, f"{self.prefix}lock")

    def _lock(self) -> None:
        path = self._lock_path()
        while True:
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
            except OSError as exc:
                raise OutputError(f"cannot lock the output directory {printable(self.requested)}"
                                  f": {exc.strerror}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read_small(fd)
                for _ in range(40):       # the holder writes who it is just after its lock
                    if holder != "holder unknown":
                        break
                    time.sleep(0.005)
                    holder = _read_small(fd)
                os.close(fd)
                raise OutputError(f"output directory {printable(self.requested)} is being "
                                  f"written by another fwdstep run ({printable(holder)}); wait "
                                  "for it to finish or choose another directory with -o") from None
            # the previous holder may have removed the file between our open and flock
            try:
                same = os.fstat(fd).st_ino == os.stat(path, follow_symlinks=False).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        self._lock_fd = fd
        started = datetime.datetime.now().isoformat(timespec="seconds")
        command = " ".join(os.path.basename(a) if i == 0 else a
                           for i, a in enumerate(sys.argv))[:200]
        try:                       # who holds it, for the message of a second run
            os.ftruncate(fd, 0)
            os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}, started {started}: "
                         f"{command}".encode("utf-8", "replace"))
        except OSError as exc:     # a full disk: nothing was written yet, say so in one line
            self._unlock()
            raise OutputError(f"cannot lock the output directory {printable(self.requested)}: "
                              f"{exc.strerror or exc}") from None

    def _unlock(self) -> None:
        if self._lock_fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self._lock_path())          # removed while still held: no race
        os.close(self._lock_fd)
        self._lock_fd = None

    # ------------------------------------------------------------------ live writes
    # Under ``lock_only`` (a writer that puts files in place while it runs, e.g. a sweep's
    # finished batches): every file goes through ``put``, every removal through ``discard``,
    # both keeping the directory's manifest.json up to date.
    def put(self, name: str, write, binary: bool = False) -> str:
        """Write ``name`` (a file name, or ``SUB/.../NAME``) into the directory now, as one
        transaction: ``write(fh)`` writes into a private staging directory (mode 0700, where
        nobody can plant a link), the file is listed in manifest.json, then renamed into
        place.  Refuses to replace an entry that the manifest does not list (the user's own
        file, a directory, a symbolic link) and never writes through a symbolic link; a
        failure (a full disk) is one ``OutputError`` and leaves the old file as it was.
        Returns the path as the user named it."""
        def produce(tmp):
            with open(tmp, "xb" if binary else "x") as fh:
                write(fh)
        return self._put(name, produce)

    def put_path(self, name: str, write_to) -> str:
        """``put`` for writers that want a file name: ``write_to(path)`` creates ``path``
        (inside the private staging directory)."""
        return self._put(name, write_to)

    def owned(self, prefix: str = "") -> list:
        """The files of this directory that fwdstep's manifest lists (sorted), those whose
        name starts with ``prefix`` (e.g. ``'parts/'``)."""
        return sorted(n for n in owned_files(self.target) if n.startswith(prefix))

    def discard(self, names) -> None:
        """Remove fwdstep's own files ``names`` (and unlist them); anything else of the same
        name -- the user's file, a link, a directory -- is left alone.  Subdirectories left
        empty are removed."""
        names = list(names)
        if not names:
            return
        ours = owned_files(self.target)
        files = self._manifest_files()
        subdirs = set()
        try:
            for n in names:
                if n in ours:
                    os.unlink(os.path.join(self.target, n))
                    if "/" in n:
                        subdirs.add(n.split("/", 1)[0])
                files.pop(n, None)
            self._write_manifest(files)
        except OSError as exc:
            raise OutputError(f"cannot remove earlier results in {printable(self.requested)}: "
                              f"{exc.strerror or exc}") from None
        for sub in subdirs:
            with contextlib.suppress(OSError):
                os.rmdir(os.path.join(self.target, sub))

    def check_subdir(self, sub: str) -> None:
        """Refuse (one ``OutputError``) a ``sub`` entry of the directory that is not a real
        directory: a symbolic link (never written through) or a file."""
        path = os.path.join(self.target, sub)
        if os.path.islink(path) or (os.path.lexists(path) and not os.path.isdir(path)):
            raise OutputError(_not_ours(os.path.join(self.requested, sub), path) +
                              f"; fwdstep keeps files in {sub}/ there")

    def _put(self, name: str, produce) -> str:
        parts = name.split("/")
        if len(parts) > 8 or not all(_plain_name(p) for p in parts) or name == MANIFEST_FILE:
            raise OutputError(f"refusing to write '{printable(name)}': not a plain file name")
        shown = os.path.join(self.requested, name)
        final = os.path.join(self.target, name)
        try:
            os.makedirs(self.target, exist_ok=True)
            for k in range(1, len(parts)):         # each folder on the way: a real one
                sub = "/".join(parts[:k])
                self.check_subdir(sub)
                with contextlib.suppress(FileExistsError):
                    os.mkdir(os.path.join(self.target, sub))
            if os.path.lexists(final) and name not in owned_files(self.target):
                raise OutputError(_not_ours(shown, final))
            staging = tempfile.mkdtemp(prefix=PUT_PREFIX, dir=self.target)
            try:
                tmp = os.path.join(staging, parts[-1])
                produce(tmp)
                if not stat.S_ISREG(os.lstat(tmp).st_mode):
                    raise OutputError(f"cannot write {printable(shown)}: the writer made no "
                                      "regular file")
                files = self._manifest_files()
                files[name] = _describe(tmp)
                self._write_manifest(files, staging)   # listed first: a kill leaves no orphan
                # the directory that receives it, opened without following a link
                where = os.open(os.path.join(self.target, *parts[:-1]),
                                os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
                try:
                    os.replace(tmp, parts[-1], dst_dir_fd=where)
                finally:
                    os.close(where)
            finally:
                shutil.rmtree(staging, ignore_errors=True)
        except OSError as exc:
            raise OutputError(f"cannot write {printable(shown)}: {exc.strerror or exc}; "
                              "nothing there was changed") from None
        return shown

    def _manifest_files(self) -> dict:
        """The manifest's ``files`` (read once, then kept: the lock is held)."""
        if getattr(self, "_live", None) is not None:
            return self._live
        if foreign_manifest(self.target):
            raise OutputError(_not_ours(os.path.join(self.requested, MANIFEST_FILE),
                                        os.path.join(self.target, MANIFEST_FILE)))
        try:
            with open(os.path.join(self.target, MANIFEST_FILE), "rb") as fh:
                files = json.loads(fh.read(1 << 24)).get("files")
        except FileNotFoundError:
            files = {n: _describe(os.path.join(self.target, n))
                     for n in owned_files(self.target)}        # legacy result files
        except (OSError, ValueError, AttributeError):
            files = None
        self._live = dict(files) if isinstance(files, dict) else {}
        return self._live

    def _write_manifest(self, files: dict, staging: str | None = None) -> None:
        text = json.dumps({"written_by": "fwdstep", "files": files}, indent=0)
        own = staging is None
        if own:
            staging = tempfile.mkdtemp(prefix=PUT_PREFIX, dir=self.target)
        try:
            tmp = os.path.join(staging, MANIFEST_FILE)
            with open(tmp, "x", encoding="utf-8") as fh:
                fh.write(text)
            os.chmod(tmp, 0o666 & ~_umask())
            os.replace(tmp, os.path.join(self.target, MANIFEST_FILE))
            self._live = files
        finally:
            if own:
                shutil.rmtree(staging, ignore_errors=True)

    # ------------------------------------------------------------------ commit
    def commit(self) -> list:
        """Write the manifest and move everything into place; returns the final paths (as
        the user named the directory) of the files written, manifest last."""
        from fwdstep.core.signals import deferred
        if self.dir is None or self._committed:
            raise OutputError("commit() outside the with block or twice")
        with deferred():
            names = sorted(os.listdir(self.dir))
            files = {}
            for n in names:                        # a folder (the diagram as run): its files
                for rel in _files_below(self.dir, n):
                    files[rel] = _describe(os.path.join(self.dir, rel))
            exists = os.path.isdir(self.target)
            if exists:                             # earlier results stay fwdstep's
                if foreign_manifest(self.target):
                    self._keep = True
                    raise OutputError(
                        _not_ours(os.path.join(self.requested, MANIFEST_FILE),
                                  os.path.join(self.target, MANIFEST_FILE)) +
                        f"; this run's files are kept in {printable(self.dir)}")
                ours = owned_entries(self.target)
                for n in names:                    # re-checked: the user may have acted since
                    old = os.path.join(self.target, n)
                    if os.path.lexists(old) and n not in ours:
                        self._keep = True
                        raise OutputError(_not_ours(os.path.join(self.requested, n), old) +
                                          f"; this run's files are kept in {printable(self.dir)}")
                for n in sorted(owned_files(self.target) - {MANIFEST_FILE}):
                    if n.split("/", 1)[0] not in names:      # not superseded by this run
                        files[n] = _describe(os.path.join(self.target, n))
            with open(os.path.join(self.dir, MANIFEST_FILE), "w") as fh:
                json.dump({"written_by": "fwdstep", "files": files}, fh, indent=2)
            os.chmod(self.dir, 0o777 & ~_umask())
            try:
                if exists and (self.inside or _holds_cwd(self.target)):
                    self._in_place(names)
                elif exists:
                    self._swap(set(names))
                else:
                    os.rename(self.dir, self.target)
            except OSError as exc:                 # nothing computed is lost
                if os.path.isdir(self.dir):
                    self._keep = True
                    raise OutputError(f"cannot move the results into "
                                      f"{printable(self.requested)}: {exc.strerror or exc}; "
                                      f"they are kept in {printable(self.dir)}") from None
                raise
            self._committed = True
        return [os.path.join(self.requested, n) for n in names + [MANIFEST_FILE]]

    def _in_place(self, names: list) -> None:
        """The target is (or contains) the current directory, which must not be renamed
        away under the user's shell, or its parent is not writable: the new files are moved
        in one by one (each replacing only fwdstep's own file, or nothing), the manifest
        last."""
        for n in names + [MANIFEST_FILE]:
            new, old = os.path.join(self.dir, n), os.path.join(self.target, n)
            if os.path.isdir(new) and os.path.isdir(old) and not os.path.islink(old):
                shutil.rmtree(old)                 # fwdstep's own folder (owned_entries)
            os.replace(new, old)
        os.rmdir(self.dir)

    def _swap(self, new: set) -> None:
        """Old directory aside, new one in place, then everything of the old directory
        that this run did not supersede (the user's files, earlier figures) moved back."""
        aside = tempfile.mkdtemp(prefix=f".{self.name}.fwdstep-old-", dir=self.parent)
        os.rmdir(aside)                            # a fresh unused name
        os.rename(self.target, aside)              # target: absent for an instant ...
        os.rename(self.dir, self.target)           # ... then complete with the new results
        for entry in os.listdir(aside):
            if entry not in new and entry != MANIFEST_FILE:
                with contextlib.suppress(OSError):
                    os.rename(os.path.join(aside, entry), os.path.join(self.target, entry))
        shutil.rmtree(aside, ignore_errors=True)   # only superseded fwdstep files remain


def _holds_cwd(path: str) -> bool:
    try:
        cwd = os.path.realpath(os.getcwd())
    except OSError:
        return False
    return cwd == path or cwd.startswith(path.rstrip(os.sep) + os.sep)


def foreign_manifest(directory: str) -> bool:
    """Whether ``directory`` holds a ``manifest.json`` that fwdstep did not write (another
    tool's file, a link, a directory): fwdstep must not replace it."""
    path = os.path.join(directory, MANIFEST_FILE)
    try:
        if not stat.S_ISREG(os.lstat(path).st_mode):
            return True
        with open(path, "rb") as fh:
            return json.loads(fh.read(1 << 24)).get("written_by") != "fwdstep"
    except FileNotFoundError:
        return False
    except (OSError, ValueError, AttributeError):
        return True


def _files_below(root: str, name: str) -> list:
    """``name`` (an entry of ``root``) if it is a file, else the files inside the folder
    ``name`` as manifest names ('diagram/lib/plant.yaml'); symbolic links are not followed."""
    top = os.path.join(root, name)
    if os.path.islink(top) or not os.path.isdir(top):
        return [name]
    out = []
    for here, dirs, files in os.walk(top):
        dirs.sort()
        rel = os.path.relpath(here, root).replace(os.sep, "/")
        out += [f"{rel}/{f}" for f in sorted(files)]
    return out


def owned_entries(directory: str) -> set:
    """Top-level entries of ``directory`` that fwdstep wrote: its files (``owned_files``) and
    its folders -- real folders (no symbolic link) every file of which the manifest lists,
    so that replacing one never removes a file of the user's."""
    ours = owned_files(directory)
    out = {n for n in ours if "/" not in n}
    for top in {n.split("/", 1)[0] for n in ours if "/" in n}:
        path = os.path.join(directory, top)
        if os.path.islink(path) or not os.path.isdir(path):
            continue
        inside = []
        for here, dirs, files in os.walk(path):
            rel = os.path.relpath(here, directory).replace(os.sep, "/")
            if any(os.path.islink(os.path.join(here, d)) for d in dirs):
                inside.append(None)            # a link inside: not ours to remove
            inside += [f"{rel}/{f}" for f in files]
        if all(n in ours for n in inside):
            out.add(top)
    return out


def owned_files(directory: str) -> set:
    """Files of ``directory`` that fwdstep wrote: listed in its manifest (and still regular
    files, reached without a symbolic link), or legacy result files when there is no
    manifest.  Names inside a folder fwdstep wrote read 'diagram/theorem1.yaml'."""
    try:
        with open(os.path.join(directory, MANIFEST_FILE), "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                raise OSError
            listed = set(json.loads(fh.read(1 << 24)).get("files", {}))
    except (OSError, ValueError, AttributeError):
        listed = set(LEGACY_FILES)
    out = set()
    for n in listed:
        parts = n.split("/") if isinstance(n, str) else [""]
        if any(p in ("", ".", "..") or os.sep in p for p in parts) or os.path.isabs(n):
            continue
        try:
            for k in range(1, len(parts)):      # no symbolic link on the way
                if not stat.S_ISDIR(os.lstat(os.path.join(directory, *parts[:k])).st_mode):
                    raise OSError
            if stat.S_ISREG(os.lstat(os.path.join(directory, *parts)).st_mode):
                out.add(n)
        except OSError:
            pass
    return out


def _plain_name(name: str) -> bool:
    return (bool(name) and name not in (".", "..") and os.path.basename(name) == name
            and "\x00" not in name)


def _not_ours(shown: str, real: str) -> str:
    kind = ("a symbolic link" if os.path.islink(real) else
            "a directory" if os.path.isdir(real) else "a file")
    return (f"refusing to replace {printable(shown)}: it is {kind} that fwdstep did not write "
            "(move it away or choose another directory with -o)")


def _describe(path: str) -> dict:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return {"bytes": os.path.getsize(path), "sha256": h.hexdigest()}


def _read_small(fd: int) -> str:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        return os.read(fd, 300).decode("utf-8", "replace") or "holder unknown"
    except OSError:
        return "holder unknown"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
