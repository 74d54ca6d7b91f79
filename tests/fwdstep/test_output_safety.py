"""Output safety: results go only into OUTDIR, are never silently overwritten, and are
written atomically (a failure mid-write leaves the old files intact and no temporary files)."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from fwdstep.cli import arguments as cli
import fwdstep
from fwdstep.core.errors import ConfigError, OutputError
from fwdstep.core.files import safe_path

DIAGRAM = """\
blocks:
  src: {type: Constant, value: [1, 2]}
  int: {type: Integrator, shape: [2]}
connections:
  - src.y -> int.u
simulation: {t_final: 0.1, step: 0.01}
plots:
  integral: [int.y]
"""


@pytest.fixture
def diagram(tmp_path) -> str:
    path = tmp_path / "d.yaml"
    path.write_text(DIAGRAM)
    return str(path)


def tree(root) -> set:
    return {os.path.relpath(os.path.join(d, f), root)
            for d, _, files in os.walk(root) for f in files}


def test_run_writes_only_inside_outdir(diagram, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    before = tree(tmp_path)
    assert cli.main(["run", diagram, "-o", "results/one", "-q"]) == 0
    new = tree(tmp_path) - before
    assert new == {"results/one/result.npz", "results/one/summary.json",
                   "results/one/integral.png", "results/one/manifest.json",
                   "results/one/diagram/d.yaml"}     # the copy of the diagram as run


@pytest.mark.parametrize("name", ["../escape.npz", "/etc/passwd", "sub/result.npz", "", ".",
                                  "..", "a\x00b"])
def test_safe_path_refuses_names_that_leave_outdir(tmp_path, name):
    with pytest.raises(OutputError) as info:
        safe_path(str(tmp_path), name)
    assert str(info.value) == (f"refusing to write '{name}': not a plain file name inside "
                               f"{tmp_path}")


@pytest.mark.parametrize("target", ["../elsewhere.npz", "inside.npz"])
def test_safe_path_never_writes_through_a_symlink(tmp_path, target):
    outdir = tmp_path / "out"
    outdir.mkdir()
    (outdir / "result.npz").symlink_to(target)
    with pytest.raises(OutputError) as info:
        safe_path(str(outdir), "result.npz")
    assert str(info.value) == f"refusing to write 'result.npz': it is a symbolic link in {outdir}"


@pytest.mark.parametrize("figure", ["../evil", "/tmp/evil", "a/b", ".hidden", "x" * 65])
def test_plot_names_cannot_become_paths(tmp_path, figure):
    path = tmp_path / "d.yaml"
    path.write_text(DIAGRAM.replace("integral:", json.dumps(figure) + ":"))
    with pytest.raises(ConfigError) as info:
        fwdstep.load_diagram(str(path))
    assert str(info.value) == (f"{path}:8: plot name '{figure}' must be letters, digits, '_' "
                               "or '-' (it becomes a file name)")


def test_existing_results_need_force(diagram, tmp_path, capsys):
    outdir = tmp_path / "out"
    assert cli.main(["run", diagram, "-o", str(outdir), "-q", "--no-plots"]) == 0
    old = {f: (outdir / f).read_bytes() for f in ("result.npz", "summary.json")}
    capsys.readouterr()
    assert cli.main(["run", diagram, "-o", str(outdir), "-q", "--no-plots"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err == (f"fwdstep: {outdir}/result.npz already exists; pass --force to "
                                 "overwrite it or -o to choose another directory\n")
    assert {f: (outdir / f).read_bytes() for f in old} == old
    assert cli.main(["run", diagram, "-o", str(outdir), "-q", "--no-plots", "--force"]) == 0
    assert json.loads((outdir / "summary.json").read_text())["wall_time_s"] != \
        json.loads(old["summary.json"])["wall_time_s"]


def test_a_summary_alone_also_counts_as_existing(diagram, tmp_path, capsys):
    outdir = tmp_path / "out"
    outdir.mkdir()
    (outdir / "summary.json").write_text("{}")
    assert cli.main(["run", diagram, "-o", str(outdir), "-q"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    assert (outdir / "summary.json").read_text() == "{}"


def test_outdir_that_is_a_file(diagram, tmp_path, capsys):
    target = tmp_path / "file"
    target.write_text("keep me")
    assert cli.main(["run", diagram, "-o", str(target), "-q"]) == 2
    assert capsys.readouterr().err == (f"fwdstep: output directory {target} exists and is not "
                                       "a directory\n")
    assert target.read_text() == "keep me"


class Boom(OSError):
    pass


def failing_savez(fh, **arrays):
    fh.write(b"PK\x03\x04 half a zip file")       # something is written, then the disk fails
    raise Boom(28, "No space left on device")


def test_failed_write_leaves_old_results_and_no_temporary_files(diagram, tmp_path, capsys,
                                                                monkeypatch):
    outdir = tmp_path / "out"
    assert cli.main(["run", diagram, "-o", str(outdir), "-q", "--no-plots"]) == 0
    old = {f: (outdir / f).read_bytes() for f in ("result.npz", "summary.json")}
    capsys.readouterr()
    monkeypatch.setattr(np, "savez", failing_savez)
    code = cli.main(["run", diagram, "-o", str(outdir), "-q", "--no-plots", "--force"])
    assert code == 2
    assert capsys.readouterr().err == (f"fwdstep: cannot write results to {outdir}: [Errno 28] "
                                       "No space left on device\n")
    assert sorted(os.listdir(outdir)) == ["diagram", "manifest.json", "result.npz", "summary.json"]
    assert {f: (outdir / f).read_bytes() for f in old} == old
    with np.load(outdir / "result.npz") as data:       # still the complete old file
        assert data["int.y"].shape == (11, 2)


def test_failed_summary_write_keeps_both_old_files(diagram, tmp_path, monkeypatch):
    outdir = tmp_path / "out"
    r = fwdstep.simulate(fwdstep.load_diagram(diagram))
    r.save(str(outdir))
    old = {f: (outdir / f).read_bytes() for f in ("result.npz", "summary.json")}
    real_fdopen = os.fdopen

    def fdopen_failing_text(fd, mode="r", *args, **kwargs):
        fh = real_fdopen(fd, mode, *args, **kwargs)
        if "b" not in mode:
            fh.write = lambda text: (_ for _ in ()).throw(Boom(5, "I/O error"))
        return fh

    monkeypatch.setattr(os, "fdopen", fdopen_failing_text)
    with pytest.raises(Boom):
        r.save(str(outdir))
    assert {f: (outdir / f).read_bytes() for f in old} == old    # npz not replaced either
    assert sorted(os.listdir(outdir)) == ["diagram", "manifest.json", "result.npz", "summary.json"]


def test_interrupt_while_writing_keeps_old_results(diagram, tmp_path, monkeypatch):
    outdir = tmp_path / "out"
    r = fwdstep.simulate(fwdstep.load_diagram(diagram))
    r.save(str(outdir))
    old = (outdir / "result.npz").read_bytes()

    def interrupted_savez(fh, **arrays):
        fh.write(b"PK partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", interrupted_savez)
    with pytest.raises(KeyboardInterrupt):
        r.save(str(outdir))
    assert (outdir / "result.npz").read_bytes() == old
    assert sorted(os.listdir(outdir)) == ["diagram", "manifest.json", "result.npz", "summary.json"]


def test_results_have_ordinary_permissions(diagram, tmp_path):
    outdir = tmp_path / "out"
    fwdstep.simulate(fwdstep.load_diagram(diagram)).save(str(outdir))
    mask = os.umask(0)
    os.umask(mask)
    for name in ("result.npz", "summary.json"):
        assert (outdir / name).stat().st_mode & 0o777 == 0o666 & ~mask


@pytest.mark.parametrize("force", [False, True])
def test_another_tools_manifest_is_never_replaced(diagram, tmp_path, capsys, force):
    outdir = tmp_path / "out"
    outdir.mkdir()
    (outdir / "manifest.json").write_text('{"mine": 1}\n')
    argv = ["run", diagram, "-o", str(outdir), "-q", "--no-plots"] + (["--force"] if force else [])
    assert cli.main(argv) == 2
    assert capsys.readouterr().err == (
        f"fwdstep: refusing to replace {outdir}/manifest.json: it is a file that fwdstep did "
        "not write (move it away or choose another directory with -o)\n")
    assert (outdir / "manifest.json").read_text() == '{"mine": 1}\n'
    assert sorted(os.listdir(outdir)) == ["manifest.json"]


def test_fwdsteps_own_manifest_is_replaced_with_force(diagram, tmp_path, capsys):
    outdir = tmp_path / "out"
    assert cli.main(["run", diagram, "-o", str(outdir), "-q", "--no-plots"]) == 0
    assert cli.main(["run", diagram, "-o", str(outdir), "-q", "--no-plots", "--force"]) == 0
    manifest = json.loads((outdir / "manifest.json").read_text())
    assert manifest["written_by"] == "fwdstep"
    assert sorted(manifest["files"]) == ["diagram/d.yaml", "result.npz", "summary.json"]
