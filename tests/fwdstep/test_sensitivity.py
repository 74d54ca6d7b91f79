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


# ---------------------------------------------------------------------- state events
# Located zero crossings (fwdstep/run/crossings.py): the crossing time moves with the
# parameters, the state may jump there (crossed()); references are analytic solutions of
# piecewise-smooth systems, and central differences of fwdstep runs on a robot diagram.

SWITCHED = """
parameters: {a: 2.1, b: 1.0}
blocks:
  x: {type: Integrator, initial: 0, shape: []}
  fa: {type: Constant, value: a}
  fb: {type: Constant, value: b}
  sw: {type: Switch, threshold: 1.0}
connections: [fb.y -> sw.u1, x.y -> sw.control, fa.y -> sw.u2, sw.y -> x.u]
simulation: {t_final: 2, step: 0.01, solver: rk4, log_every: 10}
log: [x.y]
"""

SATURATED = """
parameters: {x0: 3.37, L: 1.0}
blocks:
  x: {type: Integrator, initial: x0, shape: []}
  sat: {type: Saturation, lower: -L, upper: L}
  g: {type: Gain, gain: -1}
connections: [x.y -> sat.u, sat.y -> g.u, g.y -> x.u]
simulation: {t_final: 5, step: 0.01, solver: rk4, log_every: 1}
log: [x.y]
"""

# h' = v, v' = -g; at h = 0 falling (the reset input -h rises through 0) v <- -e v
BALL = """
parameters: {e: 0.8, h0: 2.0, g: 9.81}
blocks:
  grav: {type: Constant, value: -g}
  v: {type: LimitedIntegrator, initial: 0}
  hgt: {type: Integrator, initial: h0, shape: []}
  down: {type: Gain, gain: -1}
  bounce: {type: Gain, gain: -e}
connections: [grav.y -> v.u, v.y -> hgt.u, hgt.y -> down.u, down.y -> v.reset,
              v.y -> bounce.u, bounce.y -> v.value]
simulation: {t_final: 3, step: 0.01, solver: rk4, log_every: 1}
log: [hgt.y, v.y]
"""


def test_a_crossing_time_that_moves_with_the_parameters(tmp_path):
    """x' = a below x = 1, b above: x(t) = 1 + b (t - 1/a) after the crossing at 1/a, so
    dx/da = b/a^2 (a fixed crossing would give 1/a), dx/db = t - 1/a, d(1/a)/da = -1/a^2;
    RK4 is exact on these polynomials."""
    from fwdstep.analysis.sensitivity import event_time_sensitivity
    d = fwdstep.load_diagram(_write(tmp_path, SWITCHED))
    r = fwdstep.simulate(d, sensitivities=["a", "b"])
    a, b, t = 2.1, 1.0, r.t
    assert len(r.events) == 1 and not r.notes
    assert np.abs(r.sensitivity("x.y", "a") - np.where(t < 1 / a, t, b / a**2)).max() < 1e-12
    assert np.abs(r.sensitivity("x.y", "b") - np.where(t < 1 / a, 0, t - 1 / a)).max() < 1e-12
    assert abs(event_time_sensitivity(r, 0, "a") + 1 / a**2) < 1e-12
    assert abs(event_time_sensitivity(r, 0, "b")) < 1e-12
    for wrong in (1, -1, "0"):      # an IndexError without the count; -1 was the last one
        with pytest.raises(IndexError, match=r"located 1 event\(s\), numbered 0 to 0"):
            event_time_sensitivity(r, wrong, "a")


@pytest.mark.parametrize("x0, L", [(3.37, 1.0), (3.3712, 1.3)])
def test_leaving_a_saturation(tmp_path, x0, L):
    """x' = -sat_L(x) from x0 > L: x = x0 - L t until t1 = (x0 - L)/L, then L exp(-(t -
    t1)): dx/dx0 = 1, then exp(-(t - t1)); dx/dL = -t, then (1 - x0/L) exp(-(t - t1)).
    x0 = 3.37 puts the crossing on a grid time; L moves the kink itself (the guard's and
    the Saturation's parameter).  Tolerance: RK4's own error at h = 0.01 (up to 1.4e-9)."""
    from fwdstep.analysis.sensitivity import event_time_sensitivity
    path = _write(tmp_path, SATURATED)
    r = fwdstep.simulate(fwdstep.load_diagram(path, {"x0": x0, "L": L}),
                         sensitivities=["x0", "L"])
    t, t1 = r.t, (x0 - L) / L
    after = np.exp(-(t - t1))
    assert np.abs(r.sensitivity("x.y", "x0") - np.where(t < t1, 1.0, after)).max() < 1e-9
    assert np.abs(r.sensitivity("x.y", "L")
                  - np.where(t < t1, -t, (1 - x0 / L) * after)).max() < 2e-9
    assert abs(event_time_sensitivity(r, 0, "L") + x0 / L**2) < 1e-11
    assert abs(event_time_sensitivity(r, 0, "x0") - 1 / L) < 1e-11


def _ball(t, e, h0, g):
    """The bouncing ball's height and its analytic derivatives in e and h0 at times t;
    the bounce times T_k = t1 (1 + 2e + ... + 2e^(k-1)) and their derivatives."""
    t1 = np.sqrt(2 * h0 / g)
    dt1 = t1 / (2 * h0)                              # d t1 / d h0
    h = h0 - g * t**2 / 2
    dh_de, dh_dh0 = np.zeros_like(t), np.ones_like(t)
    bounces = []
    tb, dtb_de, dtb_dh0 = t1, 0.0, dt1
    for k in range(1, 8):
        bounces.append((tb, dtb_de, dtb_dh0))
        v, dv_de, dv_dh0 = e**k * g * t1, k * e**(k - 1) * g * t1, e**k * g * dt1
        s = t - tb
        m = t >= tb
        h = np.where(m, v * s - g * s**2 / 2, h)
        dh_de = np.where(m, dv_de * s - (v - g * s) * dtb_de, dh_de)
        dh_dh0 = np.where(m, dv_dh0 * s - (v - g * s) * dtb_dh0, dh_dh0)
        tb, dtb_de, dtb_dh0 = (tb + 2 * v / g, dtb_de + 2 * dv_de / g,
                               dtb_dh0 + 2 * dv_dh0 / g)
    return h, dh_de, dh_dh0, bounces


def test_the_bouncing_ball(tmp_path):
    """Height at every recorded time (the apexes among them: e^(2k) h0 between bounces)
    and the time of the 3rd bounce, d/de and d/dh0, against the analytic solution (RK4 is
    exact on its parabolas); every bounce is a located reset v <- -e v."""
    from fwdstep.analysis.sensitivity import event_time_sensitivity
    d = fwdstep.load_diagram(_write(tmp_path, BALL))
    r = fwdstep.simulate(d, sensitivities=["e", "h0"])
    e, h0, g = 0.8, 2.0, 9.81
    h, dh_de, dh_dh0, bounces = _ball(r.t, e, h0, g)
    assert not r.notes
    assert np.abs(r["hgt.y"] - h).max() < 1e-11
    assert np.abs(r.sensitivity("hgt.y", "e") - dh_de).max() < 1e-9
    assert np.abs(r.sensitivity("hgt.y", "h0") - dh_dh0).max() < 1e-9
    impacts = [k for k, ev in enumerate(r.events) if ev.kind == "reset rising"]
    assert len(impacts) == 3
    T3, dT3_de, dT3_dh0 = bounces[2]
    assert abs(r.events[impacts[2]].time - T3) < 1e-12
    assert abs(event_time_sensitivity(r, impacts[2], "e") - dT3_de) < 1e-9
    assert abs(event_time_sensitivity(r, impacts[2], "h0") - dT3_dh0) < 1e-9
    # apex after the 2nd bounce: the recorded maximum's derivative is e^4 h0's to O(h^2)
    k = bounces[1][0] < r.t
    k &= r.t < bounces[2][0]
    top = np.flatnonzero(k)[np.argmax(r["hgt.y"][k])]
    assert abs(r.sensitivity("hgt.y", "e")[top] - 4 * e**3 * h0) < 0.02 * 4 * e**3 * h0


def _saturated_arm(tmp_path):
    """diagrams/pd_gravity.yaml with its torque through a Saturation at +-limit (both
    joints saturated at the start, leaving and reaching the limit later) for 1.5 s."""
    text = open(os.path.join(ROOT, "diagrams", "pd_gravity.yaml")).read()
    text = text.replace('  tau:  {type: Sum, signs: "--+"}',
                        '  tau:  {type: Sum, signs: "--+"}\n'
                        '  lim:  {type: Saturation, lower: -limit, upper: limit, shape: [2]}')
    text = text.replace("  - tau.y -> arm.tau\n", "  - tau.y -> lim.u\n  - lim.y -> arm.tau\n")
    text = text.replace("  kP: 400 ", "  limit: 40\n  kP: 400 ")
    text = text.replace("t_final: 20 ", "t_final: 1.5 ")
    assert "lim.y -> arm.tau" in text and "limit: 40" in text and "t_final: 1.5 " in text
    return _write(tmp_path, text, "saturated.yaml")


def test_a_saturation_in_the_loop_of_a_robot_equals_differences_of_fwdstep(tmp_path):
    """Central differences of fwdstep runs (h = 1e-5 of the value, small enough that no
    crossing moves past a recorded time) of the tracking error and of the crossing times,
    w.r.t. a gain and the torque limit."""
    from fwdstep.analysis.sensitivity import event_time_sensitivity
    path = _saturated_arm(tmp_path)
    r = fwdstep.simulate(fwdstep.load_diagram(path), sensitivities=["kP", "limit"])
    assert len(r.events) == 4 and not r.notes
    for name, value in (("kP", 400.0), ("limit", 40.0)):
        diff, runs = _differences(path, {}, name, value, h=1e-5 * value)
        s = r.sensitivity("e.y", name)
        assert np.abs(s - diff["e.y"]).max() < 1e-8 * np.abs(s).max()
        times = [np.array([ev.time for ev in q.events]) for q in runs]
        h = 1e-5 * value
        dt = (4 * (times[2] - times[3]) / h - (times[0] - times[1]) / (2 * h)) / 3
        got = np.array([event_time_sensitivity(r, k, name) for k in range(4)])
        assert np.abs(got - dt).max() < 1e-6 * np.abs(dt).max()


def test_a_stop_leaves_nan_with_a_note(tmp_path):
    """A Stop block ends the run at a crossing (the last row's time moves): not
    differentiated, NaN from there with a note; before it, dx/da = t exactly."""
    text = SWITCHED.replace("  sw: {type: Switch, threshold: 1.0}",
                            "  sw: {type: Switch, threshold: 1.0}\n"
                            "  lvl: {type: Constant, value: 1.5}\n"
                            "  d: {type: Sum, signs: '+-'}\n"
                            "  stop: {type: Stop}")
    text = text.replace("sw.y -> x.u]",
                        "sw.y -> x.u, x.y -> d.u1, lvl.y -> d.u2, d.y -> stop.u]")
    r = fwdstep.simulate(fwdstep.load_diagram(_write(tmp_path, text)), sensitivities=["a"])
    stop = r.events[-1].time
    s = r.sensitivity("x.y", "a")
    assert r.status == "stopped"
    assert np.isnan(s[r.t >= stop]).all()
    before = r.t < 1 / 2.1
    assert np.abs(s[before] - r.t[before]).max() < 1e-12
    assert any("block 'stop' (Stop) stops the run there" in n for n in r.notes)


def test_a_chattering_block_leaves_nan_with_a_note(tmp_path):
    """x' = -a sign(x) (a Switch) slides on x = 0 from t = x0/a: the crossings recur,
    are no longer located (chattering), and are not differentiated: NaN from there with
    a note; before, dx/dx0 = 1 and dx/da = -t."""
    text = SWITCHED.replace("{a: 2.1, b: 1.0}", "{a: 1.0, x0: 0.5}")
    text = text.replace("initial: 0,", "initial: x0,").replace("value: b}", "value: -a}")
    text = text.replace("threshold: 1.0", "threshold: 0.0").replace("t_final: 2", "t_final: 1")
    r = fwdstep.simulate(fwdstep.load_diagram(_write(tmp_path, text)), sensitivities=["x0", "a"])
    chatter = next(e.time for e in r.events if e.kind == "chattering")
    assert np.isnan(r.sensitivity("x.y", "x0")[r.t >= chatter]).all()
    before = r.t < 0.5
    assert np.abs(r.sensitivity("x.y", "x0")[before] - 1).max() < 1e-12
    assert np.abs(r.sensitivity("x.y", "a")[before] + r.t[before]).max() < 1e-12
    assert any("block 'sw' chatters there" in n for n in r.notes)


# ---------------------------------------------------------------------- the loader's light path
# How a parameter reaches the blocks is found by moving it 4x per column: the light path
# (fwdstep.structure.spec.Reevaluation) evaluates only what reads it, with the loader's own
# code; the reference is the whole reload of the file (compile_spec of load_spec).

def _loaded(d, params, light: bool, monkeypatch):
    from fwdstep.analysis import sensitivity as sens
    from fwdstep.structure import spec as spec_module
    resolved, P = [], 0
    for text in params:
        par = sens.resolve_parameter(d, text)
        par.columns = slice(P, P + len(par.elements))
        P += len(par.elements)
        resolved.append(par)
    with monkeypatch.context() as m:
        if not light:
            m.setattr(spec_module.Reevaluation, "__init__",
                      lambda self, *a, **k: setattr(self, "applies", False))
        return sens.loader_derivative(d, resolved, P)


@pytest.mark.parametrize("params", [
    ["alpha"],                       # ReferenceDynamics' p arrays and its initial state
    ["a1", "T"],                     # through the qd_coefficients expression
    ["K[0,1]", "Ks.gain[1,1]"],      # a matrix entry, a block parameter path
    ["theta0", "q0"],                # whole arrays reaching initial states
])
def test_the_light_path_equals_reloading_the_file(monkeypatch, params):
    from fwdstep.analysis.sensitivity import _PARSED
    from fwdstep.structure.spec import Reevaluation
    d = fwdstep.load_diagram(THEOREM1, {"t_final": 1, "Gamma": 3})
    for text in params:
        assert Reevaluation(d.spec, [text.split("[")[0]], _PARSED).applies, text
    light = _loaded(d, params, True, monkeypatch)
    whole = _loaded(d, params, False, monkeypatch)
    assert light.p.keys() == whole.p.keys()
    assert light.p or light.x0.any()
    for key in whole.p:
        assert np.abs(light.p[key] - whole.p[key]).max() <= 1e-12 * max(
            np.abs(whole.p[key]).max(), 1e-300), key
    assert np.abs(light.x0 - whole.x0).max() <= 1e-12 * max(np.abs(whole.x0).max(), 1e-300)


INNER = """
parameters: {g: 1.0}
blocks:
  gain: {type: Gain, gain: -g, shape: []}
ports:
  inputs: {u: gain.u}
  outputs: {y: gain.y}
"""

OUTER = """
parameters: {k: 0.7, x0: 1.5}
blocks:
  x: {type: Integrator, initial: x0, shape: []}
  g: {type: subsystem, file: inner.yaml, parameters: {g: k}}
connections: [x.y -> g.u, g.y -> x.u]
simulation: {t_final: 2, step: 0.001, solver: rk4, log_every: 10}
log: [x.y]
"""


def test_a_parameter_passed_into_a_subsystem_reloads_the_file(tmp_path):
    """The light path does not follow subsystems: the whole file is loaded again (and the
    derivative is still right: x' = -k x, dx/dk = -t x0 exp(-k t))."""
    from fwdstep.analysis.sensitivity import _PARSED
    from fwdstep.structure.spec import Reevaluation
    (tmp_path / "inner.yaml").write_text(INNER)
    d = fwdstep.load_diagram(_write(tmp_path, OUTER))
    assert not Reevaluation(d.spec, ["k"], _PARSED).applies
    assert Reevaluation(d.spec, ["x0"], _PARSED).applies
    r = fwdstep.sensitivities(d, ["k", "x0"])
    assert np.abs(r.sensitivity("x.y", "k") - (-r.t * 1.5 * np.exp(-0.7 * r.t))).max() < 1e-9
    assert np.abs(r.sensitivity("x.y", "x0") - np.exp(-0.7 * r.t)).max() < 1e-9


@pytest.mark.parametrize("asked, message", [
    # the light path rebuilds qd's entry, whose expression fails: the --set is named
    ("ell", "--set ell=2.002: parameter 'qd_coefficients', which uses ell, cannot be "
            "evaluated"),
    ("step", "simulation.t_final (1) is not a whole number of steps of 0.003"),
    ("t_final", "simulation.t_final (1.001) is not a whole number of steps of 0.002"),
    ("log_every", "simulation.log_every must be a whole number of steps >= 1, got 5.005"),
])
def test_a_parameter_beyond_the_run_time_arrays_is_refused_as_a_reload_says(asked, message):
    d = fwdstep.load_diagram(THEOREM1, {"t_final": 1})
    with pytest.raises(ConfigError, match=re.escape(message)):
        fwdstep.sensitivities(d, [asked])


def test_a_result_loaded_from_disk_says_its_sensitivities_were_not_saved(tmp_path):
    """Saving keeps the run's signals, not its sensitivities: asking the loaded Result for
    one says so (it said only 'this result has no sensitivities')."""
    from fwdstep.analysis.sensitivity import event_time_sensitivity
    d = fwdstep.load_diagram(_write(tmp_path, DECAY))
    r = fwdstep.simulate(d, sensitivities=["k"])
    assert r.sensitivity("x.y", "k").shape == r["x.y"].shape
    r.save(str(tmp_path / "out"))
    loaded = fwdstep.load_result(str(tmp_path / "out"))
    np.testing.assert_array_equal(loaded["x.y"], r["x.y"])
    for ask in (lambda: loaded.sensitivity("x.y", "k"),
                lambda: loaded.sensitivity_matrix("x.y"),
                lambda: event_time_sensitivity(loaded, 0, "k")):
        with pytest.raises(KeyError, match="not saved with a result: one loaded from disk "
                                           "has none"):
            ask()
