"""The compiled-code cache cannot be used against its user (issue 16 item 1): a private
directory, refused when others can write to it; entries checked against their content hash
before import; every fault (a file where the directory should be, read-only, disk full, a
truncated or planted entry, a replaced numba index) ends in a fresh compile with one warning
line, never a traceback.  No numba compile is needed here: the modules are tiny."""
import errno
import os
import stat

import pytest

pytest.importorskip("numba")

from fwdstep.compiled import compiled_cache  # noqa: E402

SOURCE = "# fwdstep compiled program (test)\nCACHE = True\nVALUE = {}\n"


@pytest.fixture
def folder(tmp_path, monkeypatch):
    path = tmp_path / "cache"
    monkeypatch.setenv("FWDSTEP_CACHE_DIR", str(path))
    return path


def _name(source):
    import hashlib
    return compiled_cache.PREFIX + hashlib.sha256(source.encode()).hexdigest()[:32]


def _fresh(n):
    return SOURCE.format(f"{n!r} + {os.getpid()} * 0  # {os.urandom(4).hex()}")


def test_cache_directory_is_created_private(folder):
    mod = compiled_cache.load(_fresh(1))
    assert mod.VALUE == 1
    assert stat.S_IMODE(os.stat(folder).st_mode) == 0o700
    assert os.path.exists(folder / f"{mod.__name__}.py")


def test_directory_writable_by_others_is_refused(folder, capfd):
    folder.mkdir()
    os.chmod(folder, 0o777)
    mod = compiled_cache.load(_fresh(2))
    err = capfd.readouterr().err
    assert mod.VALUE == 2
    assert err.count("\n") == 1 and "compiled-code cache refused" in err
    assert "writable by other users (mode 777); compiling in memory" in err
    assert not any(p.name.endswith(".py") for p in folder.iterdir())


def test_a_file_where_the_directory_should_be(folder, capfd):
    folder.write_text("not a directory")
    mod = compiled_cache.load(_fresh(3))
    err = capfd.readouterr().err
    assert mod.VALUE == 3 and err.count("\n") == 1
    assert f"{folder} exists and is not a directory; compiling in memory" in err


@pytest.mark.parametrize("code", [errno.EROFS, errno.ENOSPC])
def test_read_only_or_full_disk_compiles_in_memory(folder, capfd, monkeypatch, code):
    def fail(*args, **kwargs):
        raise OSError(code, os.strerror(code), str(folder))
    monkeypatch.setattr(compiled_cache, "_atomic_write", fail)
    mod = compiled_cache.load(_fresh(4))
    err = capfd.readouterr().err
    assert mod.VALUE == 4 and err.count("\n") == 1
    assert f"compiled-code cache unusable ({os.strerror(code)}" in err


def test_truncated_entry_is_replaced(folder, capfd):
    source = _fresh(5)
    folder.mkdir(mode=0o700)
    (folder / f"{_name(source)}.py").write_text(source[:20])
    mod = compiled_cache.load(source)
    err = capfd.readouterr().err
    assert mod.VALUE == 5 and "does not match its hash" in err and err.count("\n") == 1
    assert (folder / f"{_name(source)}.py").read_text() == source


def test_planted_module_is_never_executed(folder, tmp_path, capfd):
    source = _fresh(6)
    marker = tmp_path / "pwned"
    folder.mkdir(mode=0o700)
    (folder / f"{_name(source)}.py").write_text(
        f"open({str(marker)!r}, 'w').write('x')\nVALUE = 666\n")
    mod = compiled_cache.load(source)
    assert mod.VALUE == 6 and not marker.exists()
    assert "does not match its hash" in capfd.readouterr().err


def test_replaced_numba_index_is_discarded_before_numba_can_load_it(folder, capfd):
    source = _fresh(7)
    name = _name(source)
    mod = compiled_cache.load(source)
    pyc = folder / "__pycache__"
    pyc.mkdir(exist_ok=True)      # (Python may have put the module's bytecode there)
    index = pyc / f"{name}.run_one-24.py311.nbi"
    index.write_bytes(b"written by numba in this process")
    compiled_cache.seal(mod)
    index.write_bytes(b"\x80\x04not what fwdstep recorded")
    import sys
    del sys.modules[name]
    again = compiled_cache.load(source)
    err = capfd.readouterr().err
    assert again.VALUE == 7 and not index.exists()
    assert "does not match its recorded hashes; compiling afresh" in err


def test_unrecorded_numba_files_are_removed_quietly_and_recorded_ones_kept(folder, capfd):
    """A file nobody recorded (another process is still compiling, or a planted one) is
    never read: removed without alarming anyone, while the sealed entries stay usable."""
    source = _fresh(9)
    name = _name(source)
    mod = compiled_cache.load(source)
    pyc = folder / "__pycache__"
    pyc.mkdir(exist_ok=True)      # (Python may have put the module's bytecode there)
    sealed = pyc / f"{name}.run_one-24.py311.nbi"
    sealed.write_bytes(b"written by numba in this process")
    compiled_cache.seal(mod)
    other = pyc / f"{name}.run_all-40.py311.nbi"
    other.write_bytes(b"\x80\x04written by a process that has not sealed yet")
    import sys
    del sys.modules[name]
    again = compiled_cache.load(source)
    assert again.VALUE == 9 and sealed.exists() and not other.exists()
    assert capfd.readouterr().err == ""


def test_sealed_numba_files_are_kept(folder, capfd):
    source = _fresh(8)
    name = _name(source)
    mod = compiled_cache.load(source)
    pyc = folder / "__pycache__"
    pyc.mkdir(exist_ok=True)      # (Python may have put the module's bytecode there)
    index = pyc / f"{name}.run_one-24.py311.nbi"
    index.write_bytes(b"written by numba in this process")
    compiled_cache.seal(mod)
    import sys
    del sys.modules[name]
    again = compiled_cache.load(source)
    assert again.VALUE == 8 and index.exists() and capfd.readouterr().err == ""


def test_an_edited_block_changes_the_cache_key(tmp_path, monkeypatch):
    """The generated text (hence its hash, the cache key) names the digest of every kernel
    as it is in memory, i.e. of the code that is compiled: a plugin file edited after it was
    loaded keeps its key (the old code still runs), and the edited file, once loaded, gets
    another one.  Keying by the file on disk labelled machine code of the old text with the
    new text's key: the next process, loading the edited file, ran the old code."""
    import fwdstep
    from fwdstep.compiled import backend_numba
    plugin = tmp_path / "doubler.py"
    body = '''
from fwdstep.core.block import Block
from fwdstep.core.registry import register


def doubler_output(t, x, u):
    return (FACTOR * u,)


FACTOR = 2.0


@register
class Doubler(Block):
    """y = 2 u.

    Equation: y = 2 u.
    """
    params = {}

    def setup(self):
        self.declare_input("u", ())
        self.declare_output("y", ())
        self.set_kernels(output=doubler_output)
'''
    plugin.write_text(body)
    diagram = tmp_path / "d.yaml"
    diagram.write_text("blocks:\n  c: {type: Constant, value: 1}\n  g: {type: Doubler}\n"
                       "connections:\n  - c.y -> g.u\nsimulation: {t_final: 0.01}\n")
    seen = []
    monkeypatch.setattr(backend_numba.compiled_cache, "load",
                        lambda source: seen.append(source) or None)
    from fwdstep.compiled.llvm_stage import stage_ir
    stages = []
    real = backend_numba._scalar_stage

    def spy(*args):
        st = real(*args)
        stages.append(stage_ir(st))
        return None                                # then the array code (cached on disk)

    monkeypatch.setattr(backend_numba, "_scalar_stage", spy)
    d = fwdstep.load_diagram(str(diagram), plugins=[str(plugin)])
    backend_numba.build_program(d, 5)
    plugin.write_text(body.replace("FACTOR = 2.0", "FACTOR = 3.0"))
    backend_numba.build_program(d, 5)              # the loaded code is unchanged
    assert len(seen) == 2 and seen[0] == seen[1]
    fwdstep.structure.library._plugin_files.clear()         # as a new process would: load the new text
    d = fwdstep.load_diagram(str(diagram), plugins=[str(plugin)])
    backend_numba.build_program(d, 5)
    changed = [a for a, b in zip(seen[0].splitlines(), seen[2].splitlines()) if a != b]
    assert len(changed) == 1 and ".doubler_output " in changed[0], changed
    # the scalar stage (traced from the kernel in memory, never cached on disk) follows the
    # loaded code too: 2 u, 2 u, then 3 u
    two, three = "0x4000000000000000", "0x4008000000000000"
    assert [two in ir and three not in ir for ir in stages] == [True, True, False]
    assert three in stages[2]


def test_a_kernel_digest_follows_its_code_and_frozen_globals_not_its_comments(tmp_path,
                                                                              monkeypatch):
    """numba freezes a kernel's plain globals (numbers, arrays) into the machine code: they
    are part of the digest; comments and line numbers are not (no needless recompiles)."""
    import importlib
    import sys
    from fwdstep.compiled import backend_numba
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)   # same size, same second: no .pyc
    text = "import numpy as np\n\nC = 2.0\nW = np.array([1.0, 2.0])\n\n\n" \
           "def kern(x):\n    return C * x + W[0]\n"

    def digest(source):
        (tmp_path / "h27_kernel.py").write_text(source)
        sys.modules.pop("h27_kernel", None)
        importlib.invalidate_caches()
        fn = importlib.import_module("h27_kernel").kern
        return backend_numba._function_digest(fn)

    base = digest(text)
    assert digest("# a comment\n\n" + text) == base
    assert digest(text.replace("C = 2.0", "C = 3.0")) != base
    assert digest(text.replace("[1.0, 2.0]", "[1.5, 2.0]")) != base
    assert digest(text.replace("C * x", "x * C")) != base


def test_a_kernel_digest_is_the_same_in_another_process():
    """The key of the disk cache: a builtin (range) or attribute name a kernel reads once
    hashed a placeholder's repr, with its memory address, so no process ever found the
    cache another one wrote."""
    import subprocess
    import sys
    from fwdstep.compiled import backend_numba
    code = ("from fwdstep.compiled import backend_numba as b; "
            "print(b._function_digest(b._copy), b._function_digest(b._view1))")
    there = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           check=True, timeout=300).stdout.strip()
    here = f"{backend_numba._function_digest(backend_numba._copy)} " \
           f"{backend_numba._function_digest(backend_numba._view1)}"
    assert there == here


def test_an_edited_helper_module_never_reuses_a_cached_kernel(folder, tmp_path, monkeypatch):
    """Kernels are cached on disk (a new structure then compiles only its loop), in a folder
    keyed by every source file they depend on.  numba's own key is the kernel's file and
    bytecode only: a kernel whose helper lives in another, edited file would load stale
    machine code (2 x + 1 below) without that folder key."""
    import importlib
    import sys
    from fwdstep.compiled import backend_numba
    # no bytecode beside the helper: edited within the same second to the same size,
    # Python's own import would run the old helper from __pycache__ (its check is the
    # source's mtime and size), whatever fwdstep's cache does
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    (tmp_path / "h24_helper.py").write_text("def helper(x):\n    return 2.0 * x\n")
    (tmp_path / "h24_kernel.py").write_text(
        "from h24_helper import helper\n\n\ndef kern(x):\n    return helper(x) + 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))

    def fresh_kernel():
        for name in ("h24_helper", "h24_kernel"):
            sys.modules.pop(name, None)
        importlib.invalidate_caches()
        fn = importlib.import_module("h24_kernel").kern
        return backend_numba.jit_kernel(fn)[0]

    first = fresh_kernel()
    assert first(1.0) == 3.0
    backend_numba.seal_kernels()
    kernel_files = [p for p in (folder / compiled_cache.KERNELS).rglob("*.nb[ic]")]
    assert kernel_files, "the kernel was not cached on disk"
    again = fresh_kernel()                       # same sources: loaded from the disk cache
    assert again is not first and again(1.0) == 3.0 and again.stats.cache_hits
    (tmp_path / "h24_helper.py").write_text("def helper(x):\n    return 5.0 * x\n")
    edited = fresh_kernel()
    assert edited(1.0) == 6.0 and not edited.stats.cache_hits


def test_tampered_kernel_cache_file_is_removed_before_numba_reads_it(folder, capfd):
    where = compiled_cache.kernel_folder("k" * 24)
    sub = os.path.join(where, "blocks_x")
    os.makedirs(sub)
    index = os.path.join(sub, "m.kern-1.py311.nbi")
    with open(index, "wb") as fh:
        fh.write(b"written by numba")
    compiled_cache.seal_folder(where)
    assert compiled_cache.kernel_folder("k" * 24) == where and os.path.exists(index)
    assert capfd.readouterr().err == ""
    with open(index, "wb") as fh:
        fh.write(b"replaced by someone else")
    compiled_cache.kernel_folder("k" * 24)
    assert not os.path.exists(index)
    assert "does not match its recorded hashes" in capfd.readouterr().err


def test_a_kernel_folder_keeps_its_sealed_files_beside_another_process_unsealed_ones(
        folder, capfd):
    """Two processes compiling at once: the second finds files the first has not sealed
    yet.  It removes only those (quietly); it used to warn and empty the whole folder."""
    where = compiled_cache.kernel_folder("j" * 24)
    sub = os.path.join(where, "blocks_x")
    os.makedirs(sub)
    sealed = os.path.join(sub, "m.kern-1.py311.nbi")
    with open(sealed, "wb") as fh:
        fh.write(b"written by numba, sealed")
    compiled_cache.seal_folder(where)
    fresh = os.path.join(sub, "m.other-9.py311.nbi")
    with open(fresh, "wb") as fh:
        fh.write(b"written by a process still compiling")
    assert compiled_cache.kernel_folder("j" * 24) == where
    assert os.path.exists(sealed) and not os.path.exists(fresh)
    assert capfd.readouterr().err == ""
