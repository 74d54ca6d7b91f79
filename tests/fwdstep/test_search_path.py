"""Where subsystem files come from (fwdstep/core/search.py) and what is never read.

A ``file: lib/NAME.yaml`` is found next to the including diagram, then in the library shipped
with fwdstep, then in ``FWDSTEP_PATH``; includes that leave those folders, absolute names and
anything but a regular file (a FIFO, a device, stdin) are refused with one line that never
quotes the content of the file it refused.  Every test writes its diagrams to a temporary
folder, so none of them depends on the checkout beyond the shipped library.
"""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fwdstep.cli import arguments as cli
import fwdstep
from fwdstep.core.errors import ConfigError
from fwdstep.core.search import shipped_library
from fwdstep.structure.spec import load_spec

REPO = Path(__file__).resolve().parents[2]

USES_PLANT = """
blocks:
  plant: {type: subsystem, file: lib/plant.yaml, parameters: {q0: [0.1, 0.2]}}
  tau: {type: Constant, value: [0, 0]}
  z: {type: Constant, value: [0, 0]}
connections:
  - tau.y -> plant.tau
  - z.y -> plant.z, plant.zdot
simulation: {t_final: 0.1, step: 0.01}
log: [plant.q]
"""

# a different "plant": one integrator, so which file was used shows in the block names
LOCAL_PLANT = """
parameters:
  q0: [0, 0]
blocks:
  x: {type: Integrator, shape: [2], initial: q0}
  sink: {type: Gain, gain: 1, shape: [2]}
ports:
  inputs: {tau: x.u, z: sink.u, zdot: sink.u}
  outputs: {q: x.y}
"""


@pytest.fixture(autouse=True)
def no_user_path(monkeypatch):
    monkeypatch.delenv("FWDSTEP_PATH", raising=False)


def _write(path: Path, text: str) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return str(path)


def test_a_diagram_anywhere_uses_the_shipped_library_without_copying(tmp_path):
    top = _write(tmp_path / "mine.yaml", USES_PLANT)
    spec = load_spec(top)
    lib = os.path.realpath(shipped_library())
    files = {b.name: os.path.realpath(b.file) for b in spec.blocks}
    assert files["plant/arm"] == os.path.join(lib, "plant.yaml")
    assert files["tau"] == os.path.realpath(top)
    r = fwdstep.simulate(fwdstep.load_diagram(top))
    assert r["plant.q"][0].tolist() == [0.1, 0.2]


def test_a_file_next_to_the_diagram_comes_before_the_library(tmp_path):
    _write(tmp_path / "lib" / "plant.yaml", LOCAL_PLANT)
    spec = load_spec(_write(tmp_path / "mine.yaml", USES_PLANT))
    assert sorted(b.name for b in spec.blocks) == ["plant/sink", "plant/x", "tau", "z"]


def test_fwdstep_path_is_searched_after_the_library(tmp_path, monkeypatch):
    shared = tmp_path / "shared"
    _write(shared / "lib" / "gain2.yaml", "blocks:\n  g: {type: Gain, gain: 2, shape: [1]}\n"
                                          "ports: {inputs: {u: g.u}, outputs: {y: g.y}}\n")
    top = _write(tmp_path / "project" / "top.yaml",
                 "blocks:\n  c: {type: Constant, value: [3]}\n"
                 "  k: {type: subsystem, file: lib/gain2.yaml}\n"
                 "connections: [c.y -> k.u]\nlog: [k.y]\n"
                 "simulation: {t_final: 0.1, step: 0.1}\n")
    with pytest.raises(ConfigError) as info:
        load_spec(top)
    here = os.path.join(os.path.dirname(top), "lib", "gain2.yaml")
    there = os.path.join(shipped_library(), "gain2.yaml")
    assert str(info.value) == (f"{top}:3: subsystem 'k': file 'lib/gain2.yaml' not found; "
                               f"looked in: {here}; {there}")
    monkeypatch.setenv("FWDSTEP_PATH", str(shared))
    r = fwdstep.simulate(fwdstep.load_diagram(top))
    assert r["k.y"][-1].tolist() == [6.0]


def test_includes_may_not_leave_the_allowed_folders(tmp_path, monkeypatch):
    secret = _write(tmp_path / "private" / "secret.yaml", "SECRET_LINE: 1\n")
    top = _write(tmp_path / "project" / "top.yaml",
                 "blocks:\n  s: {type: subsystem, file: ../private/secret.yaml}\n")
    with pytest.raises(ConfigError) as info:
        load_spec(top)
    assert "leaves the diagram's folder" in str(info.value)
    assert "SECRET" not in str(info.value)
    # a symbolic link inside the tree that points out of it is refused the same way
    os.symlink(secret, tmp_path / "project" / "link.yaml")
    _write(tmp_path / "project" / "top.yaml", "blocks:\n  s: {type: subsystem, file: link.yaml}\n")
    with pytest.raises(ConfigError) as info:
        load_spec(top)
    assert "leaves the diagram's folder" in str(info.value) and "SECRET" not in str(info.value)
    # ... unless the user put that folder on FWDSTEP_PATH
    monkeypatch.setenv("FWDSTEP_PATH", str(tmp_path / "private"))
    with pytest.raises(ConfigError) as info:
        load_spec(top)
    link = os.path.join(os.path.dirname(top), "link.yaml")
    assert str(info.value) == (f"{link}:1: not a diagram: none of its 1 top-level keys is a "
                               "diagram section (description, parameters, blocks, connections, "
                               "ports, simulation, log, plots, metrics)")


def test_a_file_that_is_not_a_diagram_is_never_quoted(tmp_path):
    _write(tmp_path / "notes.yaml", "password: hunter2\ntoken: abc123\n")
    _write(tmp_path / "words.yaml", "root:x:0:0:root:/root:/bin/bash\n")
    for name in ("notes.yaml", "words.yaml"):
        top = _write(tmp_path / "top.yaml", f"blocks:\n  s: {{type: subsystem, file: {name}}}\n")
        with pytest.raises(ConfigError if name == "notes.yaml" else Exception) as info:
            load_spec(top)
        for word in ("hunter2", "password", "abc123", "root:x", "bash"):
            assert word not in str(info.value)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_fifo_is_never_opened(tmp_path):
    fifo = tmp_path / "plant.yaml"
    os.mkfifo(fifo)
    top = _write(tmp_path / "top.yaml", "blocks:\n  p: {type: subsystem, file: plant.yaml}\n")
    # in a child process with a timeout: a regression would hang, not fail
    code = ("import cli, sys; sys.exit(cli.main(['validate', sys.argv[1]]))")
    for target, expected in ((top, f"{top}:2: subsystem 'p': file 'plant.yaml' is a FIFO "
                                   f"(named pipe) ({fifo}), not a regular file"),
                             (str(fifo), f"{fifo}: the diagram is a FIFO (named pipe), not a "
                                         "regular file; fwdstep reads only regular files")):
        proc = subprocess.run([sys.executable, "-c", code, target], cwd=REPO,
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2
        assert proc.stderr == f"fwdstep: {expected}\n"


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/stdin", "/dev/null"])
def test_a_device_as_the_diagram_is_refused(device, capsys):
    if not os.path.exists(device):
        pytest.skip(f"no {device}")
    assert cli.main(["validate", device]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a regular file" in err


def test_the_library_ships_as_package_data():
    """pyproject.toml installs diagrams/lib as fwdstep.library; the files must match."""
    text = (REPO / "pyproject.toml").read_text()
    assert '"fwdstep.library" = "diagrams/lib"' in text
    assert '"fwdstep.library" = ["*.yaml"]' in text
    names = sorted(p.name for p in Path(shipped_library()).glob("*.yaml"))
    assert names == sorted(p.name for p in (REPO / "diagrams" / "lib").glob("*.yaml"))
    assert "plant.yaml" in names
