"""Forward sensitivities (issue 28): the derivative of fwdstep's discrete solution.

References are independent of the code under test: the analytic solution of x' = -k x, and
Richardson-extrapolated central differences of ordinary fwdstep runs with the parameter
moved through ``load_diagram(..., overrides)``."""
import os
import re

import numpy as np
import pytest

import fwdstep
from fwdstep.core.errors import ConfigError

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
THEOREM1 = os.path.join(ROOT, "diagrams", "theorem1.yaml")

DECAY = """
parameters: {k: 0.7, x0: 1.5}
blocks:
  x: {type: Integrator, initial: x0, shape: []}
  g: {type: Gain, gain: -k}
connections: [x.y -> g.u, g.y -> x.u]
simulation: {t_final: 2, step: 0.001, solver: rk4, log_every: 10}
log: [x.y]
"""

SAMPLED = """
parameters: {k: 3.0, a: 2.0, x0: 1.0}
blocks:
  plant: {type: Integrator, initial: x0, shape: []}
  hold: {type: ZeroOrderHold, period: 0.05, shape: []}
  g: {type: Gain, gain: -k}
  step: {type: Step, after: a, time: 0.333}
  u: {type: Sum, signs: "++"}
connections: [plant.y -> hold.u, hold.y -> g.u, g.y -> u.u1, step.y -> u.u2, u.y -> plant.u]
simulation: {t_final: 1, step: 0.01, solver: rk4, log_every: 1}
log: [plant.y, hold.y]
"""


def _write(tmp_path, text, name="d.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def _differences(path, overrides, name, value, element=None, signals=("e.y",), h=None):
    """Richardson central differences of fwdstep runs: d signal / d (value[element])."""
    value = np.asarray(value, dtype=float)
    flat = value.reshape(-1)
    i = 0 if element is None else element
    h = h or 1e-3 * max(1.0, abs(flat[i]))
    runs = []
    for off in (1.0, -1.0, 0.5, -0.5):
        moved = flat.copy()
        moved[i] += off * h
        o = dict(overrides)
        o[name] = moved.reshape(value.shape).tolist()
        runs.append(fwdstep.simulate(fwdstep.load_diagram(path, o)))
    out = {}
    for s in signals:
        v = [r[s] for r in runs]
        out[s] = (4 * (v[2] - v[3]) / h - (v[0] - v[1]) / (2 * h)) / 3
    return out, runs


def test_decay_matches_the_analytic_sensitivity(tmp_path):
    d = fwdstep.load_diagram(_write(tmp_path, DECAY))
    r = fwdstep.sensitivities(d, ["k", "x0", "g.gain"])
    t, k, x0 = r.t, 0.7, 1.5
    assert r.sensitivity("x.y", "k").shape == r["x.y"].shape
    assert np.abs(r.sensitivity("x.y", "k") - (-t * x0 * np.exp(-k * t))).max() < 1e-9
    assert np.abs(r.sensitivity("x.y", "x0") - np.exp(-k * t)).max() < 1e-9
    # the block's own gain is -k: the opposite sign
    assert np.abs(r.sensitivity("x.y", "g.gain") - t * x0 * np.exp(-k * t)).max() < 1e-9


@pytest.fixture(scope="module")
def theorem1():
    overrides = {"t_final": 1}
    d = fwdstep.load_diagram(THEOREM1, overrides)
    r = fwdstep.sensitivities(d, ["alpha", "a1", "Ks.gain[1,0]", "K[0,1]", "theta0", "q0[1]"])
    return d, r, overrides


@pytest.mark.parametrize("name, value, element, asked", [
    ("alpha", 4.0, None, "alpha"),                      # top level -> ReferenceDynamics
    ("a1", 0.5, None, "a1"),                            # through qd_coefficients' expression
    ("Ks.gain", [[50.0, 0.0], [0.0, 50.0]], 2, "Ks.gain[1,0]"),   # block path, one entry
    ("K", [[50.0, 0.0], [0.0, 50.0]], 1, "K[0,1]"),     # top-level matrix entry
    ("theta0", [1.0, 0.5, 0.5, 0.0], 2, "theta0"),      # an initial state (whole array)
    ("q0", [0.0, 0.0], 1, "q0[1]"),                     # the arm's and z(0)'s initial state
])
def test_theorem1_equals_central_differences_of_fwdstep(theorem1, name, value, element,
                                                        asked):
    d, r, overrides = theorem1
    ref, _ = _differences(THEOREM1, overrides, name, value, element, ("e.y", "tau.y"))
    for signal in ("e.y", "tau.y"):
        got = r.sensitivity(signal, asked)
        if asked == "theta0":
            assert got.shape == r[signal].shape + (4,)
            got = got[..., element]
        else:
            assert got.shape == r[signal].shape
        scale = np.abs(ref[signal]).max()
        assert scale > 1e-8, (name, signal)
        assert np.abs(got - ref[signal]).max() <= 1e-5 * scale, (name, signal)


def test_metric_gradients_equal_differences_of_the_metrics(theorem1):
    d, r, overrides = theorem1
    _, runs = _differences(THEOREM1, overrides, "alpha", 4.0)
    h = 4e-3
    from fwdstep.results.objectives import objective
    for metric in ("rms_error_norm", "final_error_norm", "max_abs(tau.y)", "ise(e.y)"):
        v = [objective(run, metric) for run in runs]
        ref = (4 * (v[2] - v[3]) / h - (v[0] - v[1]) / (2 * h)) / 3
        got = r.metric_gradient(metric, "alpha")
        assert abs(got - ref) <= 1e-6 * max(abs(ref), 1e-12) + 1e-12, metric
    grads = r.metric_gradient("rms_error_norm")
    assert grads["theta0"].shape == (4,) and np.shape(grads["alpha"]) == ()


def test_sample_instants_and_a_step_are_differentiated(tmp_path):
    path = _write(tmp_path, SAMPLED)
    d = fwdstep.load_diagram(path)
    r = fwdstep.sensitivities(d, ["k", "a", "x0"])
    for name, value in (("k", 3.0), ("a", 2.0), ("x0", 1.0)):
        ref, _ = _differences(path, {}, name, value, signals=("plant.y", "hold.y"))
        for signal in ("plant.y", "hold.y"):
            scale = np.abs(ref[signal]).max()
            assert np.abs(r.sensitivity(signal, name) - ref[signal]).max() <= 1e-8 * scale


@pytest.mark.parametrize("asked, message", [
    ("kappa", "has no parameter 'kappa'; parameters are: k, a, x0"),
    ("g.gainn", "block 'g' (Gain) has no parameter 'gainn'"),
    ("nope.gain", "there is no block 'nope'"),
    ("step.time", "changes block 'step' beyond its run-time parameters"),
    ("x0[3]", "index [3] is outside the parameter's shape []"),
])
def test_parameters_that_cannot_be_differentiated_are_refused(tmp_path, asked, message):
    d = fwdstep.load_diagram(_write(tmp_path, SAMPLED))
    with pytest.raises(ConfigError, match=re.escape(message)):
        fwdstep.sensitivities(d, [asked])
