"""The Python API promised by issue 2, section 6, on the shipped Theorem 1 diagram:

    d = fwdstep.load_diagram(path, overrides={...})
    r = fwdstep.simulate(d)          # -> fwdstep.Result
    r.t, r["block.port"]

and the design rule that a compiled diagram is a description: simulating it twice needs no
reset and gives identical results (all per-run data lives in the run, not in the blocks).
"""
from __future__ import annotations

import os

import numpy as np
import pytest

import fwdstep
from fwdstep.structure.spec import load_spec

ROOT = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", ".."))
THEOREM1 = os.path.join(ROOT, "diagrams", "theorem1.yaml")
SLOTINE_LI = os.path.join(ROOT, "diagrams", "slotine_li.yaml")
SHORT = {"t_final": 1.0}


def test_load_simulate_result_as_in_the_issue():
    d = fwdstep.load_diagram(THEOREM1, overrides={"ell": 3, **SHORT})
    assert isinstance(d, fwdstep.CompiledDiagram)
    r = fwdstep.simulate(d)
    assert isinstance(r, fwdstep.Result)
    assert r.status == "ok"
    # r.t: the recorded times, 0 .. t_final every log_every * step = 0.01 s
    np.testing.assert_allclose(r.t, np.linspace(0.0, 1.0, 101), atol=1e-12)
    # r["block.port"]: (T, *shape) for a single run
    assert r["e.y"].shape == (101, 2)
    assert r["adapt.theta_hat"].shape == (101, 4)
    assert "e.y" in r and "nosuch.port" not in r
    with pytest.raises(KeyError, match="was not recorded"):
        r["nosuch.port"]
    # the override reached the blocks: ell = 3 gives ReferenceDynamics 3 states per joint
    ref = next(b for b in d.blocks if b.name == "ref")
    assert ref.n_states == 3 * 2
    assert d.variant_parameters[0]["ell"] == 3


def test_overrides_accept_expressions_and_lists():
    d = fwdstep.load_diagram(THEOREM1, overrides={"K": "80*eye(2)", "q0": [0.1, 0.2], **SHORT})
    np.testing.assert_array_equal(d.variant_parameters[0]["K"], 80 * np.eye(2))
    r = fwdstep.simulate(d)
    np.testing.assert_allclose(r["arm.q"][0], [0.1, 0.2])


def test_unknown_override_is_a_diagram_error_naming_the_parameter():
    with pytest.raises(fwdstep.DiagramError, match="no parameter 'Kp'"):
        fwdstep.load_diagram(THEOREM1, overrides={"Kp": 1})


def test_metrics_are_computed_from_the_declared_error_signal():
    r = fwdstep.simulate(fwdstep.load_diagram(THEOREM1, overrides=SHORT))
    m = r.metrics()
    norm = np.linalg.norm(r["e.y"], axis=1)
    assert m["final_error_norm"] == pytest.approx(norm[-1], rel=1e-12)
    assert m["tail_error_norm_max"] == pytest.approx(norm[r.t >= 0.8].max(), rel=1e-12)
    assert m["rms_error_norm"] == pytest.approx(np.sqrt(np.mean(norm ** 2)), rel=1e-12)


@pytest.mark.parametrize("path", [THEOREM1, SLOTINE_LI], ids=os.path.basename)
def test_simulating_the_same_compiled_diagram_twice_is_identical(path):
    """No reset: a second run starts from the same initial state (the adaptation law, the
    reference dynamics and the arm keep nothing from the first run)."""
    d = fwdstep.load_diagram(path, overrides=SHORT)
    first = fwdstep.simulate(d)
    second = fwdstep.simulate(d)
    assert first.names == second.names
    np.testing.assert_array_equal(first.t, second.t)
    for name in first.names:
        np.testing.assert_array_equal(first[name], second[name], err_msg=name)
    # and a freshly loaded diagram agrees too
    third = fwdstep.simulate(fwdstep.load_diagram(path, overrides=SHORT))
    for name in first.names:
        np.testing.assert_array_equal(first[name], third[name], err_msg=name)


def test_batch_of_variants_matches_single_runs():
    """compile_batch stacks structurally identical variants (here two gains K); each variant
    of the batch equals its own single run."""
    gains = ["50*eye(2)", "120*eye(2)"]
    specs = [load_spec(THEOREM1, {"K": k, **SHORT}) for k in gains]
    rb = fwdstep.simulate(fwdstep.compile_batch(specs))
    assert rb["e.y"].shape == (101, 2, 2)
    for b, k in enumerate(gains):
        r1 = fwdstep.simulate(fwdstep.load_diagram(THEOREM1, {"K": k, **SHORT}))
        np.testing.assert_allclose(rb["e.y"][:, b], r1["e.y"], rtol=0, atol=1e-12)
