"""Smoke test of every shipped diagram: diagrams/*.yaml is discovered, so a new diagram is
covered as soon as it is added.

Each diagram must validate (``fwdstep validate`` exits 0 and prints one line) and run a
shortened simulation: the spec is loaded once, its ``t_final`` cut to ``SMOKE_STEPS`` solver
steps before compiling (no parameter naming convention is assumed), and every recorded
signal must be finite.  Subsystem files under diagrams/lib/ are not top-level diagrams; they
are exercised through the diagrams that include them.
"""
from __future__ import annotations

import glob
import os

import numpy as np
import pytest

from fwdstep.cli import arguments as cli
import fwdstep
from fwdstep.structure.compiler import compile_spec
from fwdstep.structure.spec import load_spec

DIAGRAMS = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", "..", "diagrams"))
SHIPPED = sorted(glob.glob(os.path.join(DIAGRAMS, "*.yaml")))
SMOKE_STEPS = 100


def test_the_issue_diagrams_are_shipped():
    names = {os.path.basename(p) for p in SHIPPED}
    assert {"theorem1.yaml", "theorem1_sine.yaml", "slotine_li.yaml"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=os.path.basename)
def test_shipped_diagram_validates(path, capsys):
    assert cli.main(["validate", path]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert out.count("\n") == 1 and ": ok" in out


@pytest.mark.parametrize("path", SHIPPED, ids=os.path.basename)
def test_shipped_diagram_runs_briefly(path):
    spec = load_spec(path)
    assert spec.description.strip(), "a shipped diagram says what it is"
    step = spec.simulation.step
    spec.simulation.t_final = min(spec.simulation.t_final, SMOKE_STEPS * step)
    d = compile_spec(spec)
    r = fwdstep.simulate(d)
    assert r.status == "ok"
    assert r.t[-1] == pytest.approx(spec.simulation.t_final)
    assert r.names, "something is recorded"
    for name in r.names:
        assert np.all(np.isfinite(r[name])), f"{name} is not finite"
    if "error" in spec.metrics:
        m = r.metrics()
        assert np.isfinite(m["final_error_norm"])
