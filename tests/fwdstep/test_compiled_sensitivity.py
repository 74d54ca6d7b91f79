"""Forward sensitivities on the compiled backend (issue 28; fwdstep/analysis/compiled_sensitivity.py).

References independent of the code under test: the analytic solution of x' = -k x,
Richardson central differences of ordinary compiled fwdstep runs with the parameter moved
through ``load_diagram(..., overrides)``, and the NumPy path's sensitivities (block by
block, ``fwdstep/analysis/sensitivity.py``: another implementation of the chain rule).
Skipped without numba."""
import os

import numpy as np
import pytest

import fwdstep
from fwdstep.core.errors import ConfigError
from tests.fwdstep.test_sensitivity import DECAY   # x' = -k x: the same diagram on both paths

numba = pytest.importorskip("numba")

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
THEOREM1 = os.path.join(ROOT, "diagrams", "theorem1.yaml")
SLOTINE_LI = os.path.join(ROOT, "diagrams", "slotine_li.yaml")

SAMPLED = """
parameters: {k: 3.0, x0: 1.0}
blocks:
  plant: {type: Integrator, initial: x0, shape: []}
  hold: {type: ZeroOrderHold, period: 0.05, shape: []}
  g: {type: Gain, gain: -k}
connections: [plant.y -> hold.u, hold.y -> g.u, g.y -> plant.u]
simulation: {t_final: 1, step: 0.01, solver: rk4, log_every: 1}
log: [plant.y, hold.y]
"""

# most kinds of kernels and fused linear blocks (the compiled backend's own test diagram):
# a parameter reaches traced kernels (Sine, ReferenceDynamics' alpha through its fused
# matrices, AdaptationLaw), fused gains, a transfer function and a state-space filter
MIXED = """
parameters: {alpha: 4, a: 0.3, kg: 30, w: -5}
blocks:
  qd:    {type: Sine, amplitude: [a, 0.2], frequency: [[1.0, 2.0], [1.5, 0.5]],
          phase: 0.2, offset: [0.1, 0], derivatives: 2}
  arm:   {type: TwoLinkArm, q0: [0.1, -0.1], gravity: 9.81}
  ref:   {type: ReferenceDynamics, variant: eq16, ell: 2, n: 2, alpha: alpha}
  e:     {type: Sum, signs: "+-", shape: [2]}
  s:     {type: Sum, signs: "+-", shape: [2]}
  Y:     {type: Regressor, gravity: 9.81}
  W:     {type: StateSpace, A: [[w, 0], [0, -5]], B: [[5, 0], [0, 5]], C: [[1, 0], [0, 1]],
          columns: 7}
  Ks:    {type: Gain, gain: [[kg, 5], [5, 20]]}
  lag:   {type: TransferFunction, num: [1, 10], den: [1, 10], shape: [2]}
  Yth:   {type: Product, a_shape: [2, 7], b_shape: [7]}
  tau:   {type: Sum, signs: "+-", shape: [2]}
  adapt: {type: AdaptationLaw, regressor_shape: [2, 7], gamma: 1, theta0: 0.5}
connections:
  - arm.q -> ref.q, Y.q, e.u1
  - arm.qdot -> ref.qdot, Y.qdot, s.u1
  - qd.y -> ref.q_d, e.u2
  - qd.y_d1 -> ref.qdot_d
  - qd.y_d2 -> ref.qddot_d
  - ref.z -> s.u2, Y.zeta
  - ref.zdot -> Y.zetad
  - Y.Y -> Yth.a, W.u
  - W.y -> adapt.W
  - adapt.theta_hat -> Yth.b
  - s.y -> Ks.u, adapt.e
  - Ks.y -> lag.u
  - Yth.y -> tau.u1
  - lag.y -> tau.u2
  - tau.y -> arm.tau
simulation: {t_final: 0.5, step: 0.001, solver: rk4, log_every: 3}
log: [e.y, tau.y, adapt.theta_hat]
"""


@pytest.fixture(autouse=True)
def cache(numba_cache):
    return numba_cache


def _write(tmp_path, text, name="d.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def _compiled_differences(path, overrides, name, value, element=None, signals=("e.y",)):
    """Richardson central differences of compiled fwdstep runs: d signal / d value[element]."""
    value = np.asarray(value, dtype=float)
    flat = value.reshape(-1)
    i = 0 if element is None else element
    h = 1e-3 * max(1.0, abs(flat[i]))
    runs = []
    for off in (1.0, -1.0, 0.5, -0.5):
        moved = flat.copy()
        moved[i] += off * h
        o = dict(overrides)
        o[name] = moved.reshape(value.shape).tolist()
        runs.append(fwdstep.simulate(fwdstep.load_diagram(path, o), backend="compiled"))
    assert all(r.backend == "compiled" for r in runs)
    return {s: (4 * (runs[2][s] - runs[3][s]) / h - (runs[0][s] - runs[1][s]) / (2 * h)) / 3
            for s in signals}


def _relative(a, b):
    return np.abs(a - b).max() / max(np.abs(b).max(), 1e-300)


def test_decay_on_the_compiled_backend_matches_the_analytic_sensitivity(tmp_path):
    d = fwdstep.load_diagram(_write(tmp_path, DECAY))
    r = fwdstep.simulate(d, backend="compiled", sensitivities=["k", "x0", "g.gain"])
    assert r.backend == "compiled" and not r.notes
    t, k, x0 = r.t, 0.7, 1.5
    assert r.sensitivity("x.y", "k").shape == r["x.y"].shape
    assert np.abs(r.sensitivity("x.y", "k") - (-t * x0 * np.exp(-k * t))).max() < 1e-9
    assert np.abs(r.sensitivity("x.y", "x0") - np.exp(-k * t)).max() < 1e-9
    assert np.abs(r.sensitivity("x.y", "g.gain") - t * x0 * np.exp(-k * t)).max() < 1e-9
    # the run itself is the compiled run's
    plain = fwdstep.simulate(d, backend="compiled")
    assert np.array_equal(r["x.y"], plain["x.y"]) and np.array_equal(r.t, plain.t)


def test_theorem1_alpha_equals_central_differences_of_compiled_runs():
    overrides = {"t_final": 1}
    d = fwdstep.load_diagram(THEOREM1, overrides)
    r = fwdstep.simulate(d, backend="compiled", sensitivities=["alpha"])
    assert r.backend == "compiled" and not r.notes
    ref = _compiled_differences(THEOREM1, overrides, "alpha", 4.0, signals=("e.y", "tau.y"))
    for signal in ("e.y", "tau.y"):
        got = r.sensitivity(signal, "alpha")
        assert got.shape == r[signal].shape
        assert np.abs(ref[signal]).max() > 1e-8
        assert _relative(got, ref[signal]) <= 1e-5, signal


@pytest.mark.parametrize("path, overrides, params", [
    (THEOREM1, {"t_final": 1}, ["alpha", "a1", "Ks.gain[1,0]", "K[0,1]", "theta0", "q0[1]"]),
    (SLOTINE_LI, {"t_final": 1}, ["Lambda", "Gamma", "K", "A[0]", "w[1]", "theta0[1]"]),
])
def test_compiled_and_numpy_sensitivities_are_equal(path, overrides, params):
    d = fwdstep.load_diagram(path, overrides)
    numpy = fwdstep.simulate(d, backend="numpy", sensitivities=params)
    compiled = fwdstep.simulate(d, backend="compiled", sensitivities=params)
    assert compiled.backend == "compiled" and not compiled.notes
    for name in d.logged:
        a, b = compiled.sensitivity_matrix(name), numpy.sensitivity_matrix(name)
        assert a.shape == b.shape
        assert np.abs(a - b).max() <= 1e-10 * max(np.abs(b).max(), 1e-300), name
    assert compiled.metric_gradient("rms_error_norm", params[0]) == pytest.approx(
        numpy.metric_gradient("rms_error_norm", params[0]), rel=1e-10)


def test_fused_groups_and_traced_kernels_on_the_compiled_backend(tmp_path):
    """alpha moves ReferenceDynamics' fused matrices, kg a fused gain's entry, w a
    state-space filter's A, a a Sine's traced amplitude; also a block path's entry."""
    d = fwdstep.load_diagram(_write(tmp_path, MIXED))
    params = ["alpha", "kg", "w", "a", "Ks.gain[1,1]", "adapt.gamma"]
    numpy = fwdstep.simulate(d, backend="numpy", sensitivities=params)
    compiled = fwdstep.simulate(d, backend="compiled", sensitivities=params)
    assert compiled.backend == "compiled" and not compiled.notes
    for name in d.logged:
        a, b = compiled.sensitivity_matrix(name), numpy.sensitivity_matrix(name)
        for c in range(b.shape[2]):
            assert np.abs(b[..., c]).max() > 0, (name, c)
            assert _relative(a[..., c], b[..., c]) <= 1e-10, (name, params[c])


def test_a_sampled_diagram_takes_the_numpy_path_with_a_note(tmp_path):
    d = fwdstep.load_diagram(_write(tmp_path, SAMPLED))
    r = fwdstep.simulate(d, backend="compiled", sensitivities=["k", "x0"])
    assert r.notes == ["sensitivities computed on the numpy path: discrete blocks update "
                       "at sample instants"]
    ref = fwdstep.sensitivities(d, ["k", "x0"], backend="numpy")
    assert not ref.notes
    for name in ("plant.y", "hold.y"):
        assert np.array_equal(r.sensitivity_matrix(name), ref.sensitivity_matrix(name))


def test_simulate_with_sensitivities_is_fwdstep_sensitivities(tmp_path):
    d = fwdstep.load_diagram(_write(tmp_path, DECAY))
    a = fwdstep.simulate(d, sensitivities="k")
    b = fwdstep.sensitivities(d, ["k"])
    assert a.backend == "numpy" and np.array_equal(a.sensitivity("x.y", "k"),
                                                   b.sensitivity("x.y", "k"))
    with pytest.raises(ConfigError, match="they take no x0"):
        fwdstep.simulate(d, x0=np.ones(1), sensitivities=["k"])
    with pytest.raises(ConfigError, match="unknown backend 'fast'"):
        fwdstep.simulate(d, backend="fast", sensitivities=["k"])


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


@pytest.mark.parametrize("backend", ["numpy", "compiled"])
def test_a_state_event_is_differentiated_on_either_backend(tmp_path, backend):
    """x' = a below x = 1, b above: the crossing time 1/a moves with a, dx(T)/da = b/a^2
    after it (not the 1/a of a fixed crossing), x/a = t before; the compiled backend
    takes the NumPy path's sensitivities for a diagram with zero crossings, with a note
    (never NaN silently)."""
    d = fwdstep.load_diagram(_write(tmp_path, SWITCHED))
    r = fwdstep.simulate(d, backend=backend, sensitivities=["a"])
    crossing = r.events[0].time
    assert abs(crossing - 1 / 2.1) < 1e-12
    s = r.sensitivity("x.y", "a")
    assert np.abs(s - np.where(r.t < crossing, r.t, 1.0 / 2.1**2)).max() < 1e-12
    if backend == "compiled":
        assert "sensitivities computed on the numpy path: block 'sw' (Switch) has zero " \
               "crossings" in r.notes


def test_a_stage_that_does_not_trace_takes_the_numpy_path_with_a_note(tmp_path, monkeypatch):
    from fwdstep.analysis import compiled_sensitivity
    from fwdstep.compiled.scalarize import Untraceable

    def refuse(*args):
        raise Untraceable("np.linalg is not traced")

    monkeypatch.setattr(compiled_sensitivity, "variational_stage", refuse)
    d = fwdstep.load_diagram(_write(tmp_path, DECAY))
    r = fwdstep.simulate(d, backend="compiled", sensitivities=["k"])
    assert r.backend == "numpy"
    assert r.notes == ["sensitivities computed on the numpy path: its variational stage is "
                       "not compiled (np.linalg is not traced)"]
    assert np.abs(r.sensitivity("x.y", "k") - (-r.t * 1.5 * np.exp(-0.7 * r.t))).max() < 1e-9


def test_sensitivities_that_grow_past_floats_are_said_not_finite(tmp_path):
    """x' = 360 x from x0 = 1e-305 stays under the bound (1e8) for 2 s, while dx/dx0 =
    e^(360 t) = x / x0 passes the largest float near t = 1.97: not finite from there on,
    said in a note (x alone is checked against the bound)."""
    text = DECAY.replace("{k: 0.7, x0: 1.5}", "{k: -360.0, x0: 1.0e-305}")
    d = fwdstep.load_diagram(_write(tmp_path, text))
    for backend in ("numpy", "compiled"):
        r = fwdstep.simulate(d, backend=backend, sensitivities=["x0"])
        assert r.status == "ok" and np.abs(r["x.y"]).max() < 1e8
        s = r.sensitivity("x.y", "x0")
        first = int(np.flatnonzero(~np.isfinite(s))[0])
        assert 1.9 < r.t[first] < 2.0 and np.isfinite(s[:first]).all()
        assert np.allclose(s[:first], r["x.y"][:first] / 1e-305, rtol=1e-12)
        assert f"sensitivities are not finite from t = {r.t[first]:.6g} s on" in r.notes


# ---------------------------------------------------------------------- the memoised stage
# A tuning calls with a new value each time: the traced variational stage is reused with
# the moving entries' and seeds' columns of W rebound (compiled_sensitivity.variational_stage).

def _counting_stages(monkeypatch):
    """The number of variational stages traced from now on."""
    from fwdstep.analysis import compiled_sensitivity as cs
    made = []
    real = cs.VariationalStage

    class Counting(real):
        def __init__(self, *args, **kwargs):
            made.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(cs, "VariationalStage", Counting)
    return made


def _run(path, overrides, params):
    r = fwdstep.simulate(fwdstep.load_diagram(path, overrides), backend="compiled",
                         sensitivities=params)
    assert r.backend == "compiled" and not r.notes, r.notes
    return r


def test_a_new_value_reuses_the_traced_stage_and_gives_a_fresh_trace_s_numbers(
        tmp_path, monkeypatch):
    """MIXED: alpha moves ReferenceDynamics' fused matrices, kg a fused gain's entry, a a
    traced Sine's amplitude, adapt.gamma a traced kernel's argument.  Another value of each
    runs the first call's machine code; the numbers are those of a fresh trace, exactly."""
    from fwdstep.analysis import compiled_sensitivity as cs
    path = _write(tmp_path, MIXED)
    params = ["alpha", "kg", "a", "Ks.gain[1,1]", "adapt.gamma"]
    cs._STAGES.clear()
    first = _run(path, {}, params)
    made = _counting_stages(monkeypatch)
    moved = {"alpha": 5.5, "kg": 42.0, "a": 0.35}
    again = _run(path, moved, params)
    assert made == []                                   # the memo's stage, rebound
    cs._STAGES.clear()
    fresh = _run(path, moved, params)
    assert made == [1]
    for name in again.sensitivity_data["signals"]:
        assert np.array_equal(again.sensitivity_matrix(name), fresh.sensitivity_matrix(name))
        assert np.array_equal(again[name], fresh[name])
    assert not np.allclose(first.sensitivity_matrix("e.y"), again.sensitivity_matrix("e.y"))


def test_a_rebound_stage_matches_the_analytic_sensitivity(tmp_path, monkeypatch):
    """x' = -k x (a fused integrator and gain: k is an entry of the fused matrix, seeded
    with dM): dx/dk = -t x0 exp(-k t) at every k the memoised stage is rebound to."""
    from fwdstep.analysis import compiled_sensitivity as cs
    path = _write(tmp_path, DECAY)
    cs._STAGES.clear()
    _run(path, {}, ["k", "x0"])
    made = _counting_stages(monkeypatch)
    for k in (0.3, 1.9):
        r = _run(path, {"k": k}, ["k", "x0"])
        assert np.abs(r.sensitivity("x.y", "k") - (-r.t * 1.5 * np.exp(-k * r.t))).max() < 1e-9
        assert np.abs(r.sensitivity("x.y", "x0") - np.exp(-k * r.t)).max() < 1e-9
    assert made == []


def test_a_rebound_theorem1_stage_equals_central_differences_at_the_new_value(monkeypatch):
    from fwdstep.analysis import compiled_sensitivity as cs
    cs._STAGES.clear()
    _run(THEOREM1, {"t_final": 1}, ["alpha", "Gamma"])
    made = _counting_stages(monkeypatch)
    overrides = {"t_final": 1, "alpha": 5.0, "Gamma": 3.0}
    r = _run(THEOREM1, overrides, ["alpha", "Gamma"])
    assert made == []
    # the run itself is the plain compiled run's, bit for bit (only the tangents' products
    # and sums may be fused multiply-adds: fwdstep.compiled.llvm_stage)
    plain = fwdstep.simulate(fwdstep.load_diagram(THEOREM1, overrides), backend="compiled")
    for name in ("e.y", "tau.y", "adapt.theta_hat"):
        assert np.array_equal(r[name], plain[name]), name
    for name, value in (("alpha", 5.0), ("Gamma", 3.0)):
        ref = _compiled_differences(THEOREM1, overrides, name, value)["e.y"]
        assert np.abs(ref).max() > 1e-8
        assert _relative(r.sensitivity("e.y", name), ref) <= 1e-5, name
