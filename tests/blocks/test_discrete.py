"""Discrete-time blocks against scipy's exact discretisations and discrete simulations.

A double-integrator plant under a sampled PD law is exactly the discrete system
(Ad + Bd K) given by scipy.signal.cont2discrete (zoh): RK4 integrates a constant input on a
double integrator without error, and the sample instants end steps exactly, whether the
step divides the period, does not, or is longer than it.  DiscreteStateSpace and
DiscreteTransferFunction are compared with scipy.signal.dlsim at the sample instants.
"""
import numpy as np
import pytest
from scipy.linalg import expm
from scipy.signal import cont2discrete, dlsim

import fwdstep
from fwdstep.cli import arguments as cli

PD = """
parameters: {{T: 0.01}}
blocks:
  plant: {{type: StateSpace, A: [[0, 1], [0, 0]], B: [[0], [1]], C: [[1, 0], [0, 1]],
          initial: [1.0, 0.5]}}
  pd:    {{type: Gain, gain: [[-40.0, -9.0]]}}
  zoh:   {{type: ZeroOrderHold, period: T, shape: [1], offset: {offset}}}
connections:
  - plant.y -> pd.u
  - pd.y -> zoh.u
  - zoh.y -> plant.u
simulation: {{t_final: {t_final}, step: {h}, solver: rk4}}
"""
A = np.array([[0.0, 1.0], [0.0, 0.0]])
B = np.array([[0.0], [1.0]])
K = np.array([[-40.0, -9.0]])


def _load(tmp_path, text, **overrides):
    path = tmp_path / "d.yaml"
    path.write_text(text)
    return fwdstep.load_diagram(str(path), overrides=overrides or None)


def _flow(tau):
    """exp([[A, B], [0, 0]] tau), the plant's exact flow with a constant input (closed form
    of the double integrator's; equal to scipy.linalg.expm, checked below)."""
    return np.array([[1.0, tau, tau * tau / 2], [0.0, 1.0, tau], [0.0, 0.0, 1.0]])


def test_the_closed_form_flow_is_expm():
    M = np.zeros((3, 3))
    M[:2, :2], M[:2, 2:] = A, B
    np.testing.assert_allclose(_flow(0.0137), expm(M * 0.0137), rtol=0, atol=1e-15)


def _between_samples(t, xs, T, offset=0.0, u_before=0.0, x0=None):
    """The exact continuous state at t: from the last sample, a constant input K x_k."""
    k = int(np.floor((t - offset) / T + 1e-9))
    if k < 0:
        E = _flow(t)
        return E[:2, :2] @ x0 + E[:2, 2] * u_before
    E = _flow(t - offset - k * T)
    return E[:2, :2] @ xs[k] + E[:2, 2:] @ (K @ xs[k])


@pytest.mark.parametrize("h, t_final", [(0.0025, 1.0), (0.003, 0.999), (0.02, 1.0),
                                        (0.0007, 0.35)])
def test_sampled_pd_loop_is_its_exact_discretisation(tmp_path, h, t_final):
    T = 0.01
    Ad, Bd, *_ = cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), T, method="zoh")
    xs = [np.array([1.0, 0.5])]
    for _ in range(int(t_final / T) + 2):
        xs.append((Ad + Bd @ K) @ xs[-1])
    r = fwdstep.simulate(_load(tmp_path, PD.format(offset=0.0, t_final=t_final, h=h)))
    exact = np.array([_between_samples(t, xs, T) for t in r.t])
    assert np.abs(r["plant.y"] - exact).max() < 1e-12


def test_sample_offset_holds_the_initial_output_until_the_first_sample(tmp_path):
    T, off = 0.01, 0.0042
    Ad, Bd, *_ = cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), T, method="zoh")
    x_first = _flow(off)[:2, :2] @ np.array([1.0, 0.5])          # u = 0 before the sample
    xs = [x_first]
    for _ in range(60):
        xs.append((Ad + Bd @ K) @ xs[-1])
    r = fwdstep.simulate(_load(tmp_path, PD.format(offset=off, t_final=0.5, h=0.0025)))
    exact = np.array([_between_samples(t, xs, T, off, 0.0, np.array([1.0, 0.5]))
                      for t in r.t])
    assert np.abs(r["plant.y"] - exact).max() < 1e-12
    assert np.all(r["zoh.y"][r.t < off] == 0.0)


HOLD = """
blocks:
  w:   {{type: Sine, amplitude: [1.0, 2.0], frequency: [3.0, 7.0]}}
  zoh: {{type: ZeroOrderHold, period: {T}, shape: [2]}}
  d:   {{type: UnitDelay, period: {T}, shape: [2], initial: [5.0, 6.0]}}
connections:
  - w.y -> zoh.u, d.u
simulation: {{t_final: 1.0, step: 0.001, solver: rk4}}
"""


def test_zero_order_hold_is_exactly_piecewise_constant(tmp_path):
    T = 0.013                                       # not a multiple of the step
    r = fwdstep.simulate(_load(tmp_path, HOLD.format(T=T)))
    k = np.floor(r.t / T + 1e-9)
    tk = k * T
    expected = np.stack([np.sin(3.0 * tk), 2.0 * np.sin(7.0 * tk)], axis=1)
    np.testing.assert_allclose(r["zoh.y"], expected, rtol=0, atol=1e-14)   # Sine's rounding
    # constant between samples: it changes only on rows that cross a sample instant
    changed = np.any(np.diff(r["zoh.y"], axis=0) != 0, axis=1)
    np.testing.assert_array_equal(changed, np.diff(k) != 0)


def test_unit_delay_outputs_the_previous_sample(tmp_path):
    T = 0.02
    r = fwdstep.simulate(_load(tmp_path, HOLD.format(T=T)))
    k = np.floor(r.t / T + 1e-9)
    prev = (k - 1) * T
    expected = np.stack([np.sin(3.0 * prev), 2.0 * np.sin(7.0 * prev)], axis=1)
    expected[k == 0] = [5.0, 6.0]
    np.testing.assert_allclose(r["d.y"], expected, rtol=0, atol=1e-14)


DSS = """
blocks:
  w:   {type: Sine, amplitude: [1.0, 0.5], frequency: [2.0, 5.0]}
  dss: {type: DiscreteStateSpace, A: [[0.9, 0.2], [-0.1, 0.7]], B: [[1.0, 0.0], [0.5, 1.0]],
        C: [[1.0, -1.0]], D: [[0.3, 0.1]], period: 0.05, x0: [0.2, -0.4]}
  dtf: {type: DiscreteTransferFunction, num: [0.5, -0.2, 0.1], den: [1.0, -1.1, 0.3],
        period: 0.05, shape: [2]}
connections:
  - w.y -> dss.u, dtf.u
simulation: {t_final: 2.0, step: 0.01, solver: rk4}
"""


def test_discrete_state_space_and_transfer_function_match_dlsim(tmp_path):
    r = fwdstep.simulate(_load(tmp_path, DSS))
    T = 0.05
    tk = np.arange(41) * T
    u = np.stack([np.sin(2.0 * tk), 0.5 * np.sin(5.0 * tk)], axis=1)
    rows = np.searchsorted(r.t, tk - 1e-12)           # the records at the sample instants
    _, y, _ = dlsim((np.array([[0.9, 0.2], [-0.1, 0.7]]), np.array([[1.0, 0.0], [0.5, 1.0]]),
                     np.array([[1.0, -1.0]]), np.array([[0.3, 0.1]]), T), u,
                    x0=np.array([0.2, -0.4]))
    assert np.abs(r["dss.y"][rows] - y).max() < 1e-12
    for j in range(2):
        _, yj = dlsim(([0.5, -0.2, 0.1], [1.0, -1.1, 0.3], T), u[:, j])
        assert np.abs(r["dtf.y"][rows, j] - yj[:, 0]).max() < 1e-12
    # held between the sample instants
    k = np.floor(r.t / T + 1e-9).astype(int)
    np.testing.assert_array_equal(r["dss.y"][:, 0], y[k, 0])


CHAIN = """
blocks:
  w:    {type: Sine, amplitude: 1.0, frequency: 4.0}
  zoh:  {type: ZeroOrderHold, period: 0.1}
  g:    {type: Gain, gain: 2.0}
  zoh2: {type: ZeroOrderHold, period: 0.1}
connections:
  - w.y -> zoh.u
  - zoh.y -> g.u
  - g.y -> zoh2.u
simulation: {t_final: 1.0, step: 0.01, solver: rk4}
"""


def test_a_chain_of_holds_passes_this_instants_sample(tmp_path):
    """zoh2 samples 2 zoh.y at t_k *after* zoh took u(t_k): no extra delay per block."""
    r = fwdstep.simulate(_load(tmp_path, CHAIN))
    np.testing.assert_array_equal(r["zoh2.y"], 2.0 * r["zoh.y"])


def test_a_discrete_algebraic_loop_is_refused_in_one_line(tmp_path):
    text = """
blocks:
  a: {type: ZeroOrderHold, period: 0.1, initial: 1.0}
  g: {type: Gain, gain: 0.5}
  b: {type: ZeroOrderHold, period: 0.1}
connections:
  - a.y -> g.u
  - g.y -> b.u
  - b.y -> a.u
simulation: {t_final: 1.0, step: 0.01, solver: rk4}
"""
    with pytest.raises(fwdstep.ConfigError) as err:      # before the run: a diagram error
        fwdstep.simulate(_load(tmp_path, text))
    msg = str(err.value)
    assert "discrete algebraic loop" in msg and "'a'" in msg and "'b'" in msg
    assert "\n" not in msg


@pytest.mark.parametrize("params, text", [
    ("period: 0", "parameter 'period' must be positive, got 0"),
    ("period: 0.1, offset: -1", "parameter 'offset' must be >= 0, got -1"),
])
def test_bad_sampling_parameters(tmp_path, params, text):
    body = ("blocks:\n  z: {type: ZeroOrderHold, " + params + "}\n  w: {type: Constant, value: 1}"
            "\nconnections:\n  - w.y -> z.u\nsimulation: {t_final: 1, step: 0.01}\n")
    with pytest.raises(fwdstep.ParameterError) as err:
        _load(tmp_path, body)
    assert text in str(err.value)


def test_dss_refuses_mismatched_matrices(tmp_path):
    body = ("blocks:\n  z: {type: DiscreteStateSpace, A: [[1, 0], [0, 1]], B: [[1], [0]], "
            "C: [[1, 0, 0]], period: 0.1}\n  w: {type: Constant, value: [1]}\n"
            "connections:\n  - w.y -> z.u\nsimulation: {t_final: 1, step: 0.01}\n")
    with pytest.raises(fwdstep.ParameterError) as err:
        _load(tmp_path, body)
    assert "parameter 'C' has shape (1, 3)" in str(err.value)


# ---------------------------------------------------------------- sampled subsystems
PD_SUB = """
blocks:
  pd: {type: Gain, gain: [[-40.0, -9.0]]}
ports:
  inputs: {x: pd.u}
  outputs: {u: pd.y}
"""
LEAD_SUB = """
parameters: {k: 30.0}
blocks:
  e:    {type: Gain, gain: [[-1.0, 0.0]]}
  lead: {type: TransferFunction, num: [k, 2 * k], den: [1, 20], shape: [1]}
connections:
  - e.y -> lead.u
ports:
  inputs: {x: e.u}
  outputs: {u: lead.y}
"""
LOOP_SUB = """
blocks:
  plant: {{type: StateSpace, A: [[0, 1], [0, 0]], B: [[0], [1]], C: [[1, 0], [0, 1]],
          initial: [1.0, 0.5]}}
  ctrl:  {{type: subsystem, file: ctrl.yaml, sample_period: 0.01}}
connections:
  - plant.y -> ctrl.x
  - ctrl.u -> plant.u
simulation: {{t_final: {t_final}, step: {h}, solver: rk4}}
"""


def _sampled_loop(tmp_path, controller, h, t_final):
    (tmp_path / "ctrl.yaml").write_text(controller)
    return fwdstep.simulate(_load(tmp_path, LOOP_SUB.format(h=h, t_final=t_final)))


def test_a_sampled_subsystem_is_the_exact_discretisation_of_the_loop(tmp_path):
    r = _sampled_loop(tmp_path, PD_SUB, 0.003, 0.498)
    assert "ctrl/sample_x" in r.names[1] and r.status == "ok"
    T = 0.01
    Ad, Bd, *_ = cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), T, method="zoh")
    xs = [np.array([1.0, 0.5])]
    for _ in range(60):
        xs.append((Ad + Bd @ K) @ xs[-1])
    exact = np.array([_between_samples(t, xs, T) for t in r.t])
    assert np.abs(r["plant.y"] - exact).max() < 1e-12
    k = np.floor(r.t / T + 1e-9).astype(int)
    np.testing.assert_allclose(r["ctrl.u"][:, 0], [(K @ xs[i])[0] for i in k], atol=1e-12)


def test_a_sampled_controller_with_state_is_its_zoh_discretisation(tmp_path):
    """Between samples the controller's own filter runs on the held input: for a linear
    controller that is cont2discrete(controller, 'zoh'), with its output held."""
    from scipy.signal import tf2ss
    r = _sampled_loop(tmp_path, LEAD_SUB, 0.0005, 0.5)
    T = 0.01
    Ac, Bc, Cc, Dc = tf2ss([30.0, 60.0], [1.0, 20.0])
    Acd, Bcd, *_ = cont2discrete((Ac, Bc, Cc, Dc), T, method="zoh")
    Ad, Bd, *_ = cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), T, method="zoh")
    x, xc, xs = np.array([1.0, 0.5]), np.zeros(1), []
    for _ in range(51):
        xs.append(x)
        e = np.array([-x[0]])
        u = Cc @ xc + Dc @ e
        x, xc = Ad @ x + Bd @ u, Acd @ xc + Bcd @ e
    rows = np.arange(0, len(r.t), 20)                      # the sample instants
    # what remains is RK4's own error on the filter's exp(-20 t) (1.4e-9 at h = 1 ms)
    assert np.abs(r["plant.y"][rows] - np.array(xs)).max() < 2e-10


def test_sampled_subsystem_settings_are_checked(tmp_path):
    (tmp_path / "ctrl.yaml").write_text(PD_SUB)
    bad = LOOP_SUB.format(h=0.001, t_final=0.1).replace("sample_period: 0.01",
                                                         "sample_period: -1")
    with pytest.raises(fwdstep.ConfigError) as err:
        _load(tmp_path, bad)
    assert "subsystem 'ctrl' sample_period must be positive, or 0" in str(err.value)
    bad = LOOP_SUB.format(h=0.001, t_final=0.1).replace("sample_period", "sample_perod")
    with pytest.raises(fwdstep.DiagramError) as err:
        _load(tmp_path, bad)
    assert "keys are: type, file, parameters, sample_period, sample_offset" in str(err.value)


def test_sample_period_0_runs_the_subsystem_continuously(tmp_path):
    """issue 24: ``--set ctrl.sample_period=0`` (or ``sample_period: 0``) compares the
    digital controller with its analog design: no holds, the continuous closed loop."""
    from scipy.linalg import expm
    (tmp_path / "ctrl.yaml").write_text(PD_SUB)
    text = LOOP_SUB.format(h=0.001, t_final=0.5)
    d = _load(tmp_path, text, **{"ctrl.sample_period": 0})
    assert not any(b.type_name == "ZeroOrderHold" for b in d.blocks)
    r = fwdstep.simulate(d)
    exact = np.array([expm((A + B @ K) * t) @ [1.0, 0.5] for t in r.t])
    assert np.abs(r["plant.y"] - exact).max() < 1e-9                  # RK4 at h = 1 ms
    unsampled = fwdstep.simulate(_load(tmp_path, text.replace(", sample_period: 0.01", "")))
    assert np.array_equal(r["plant.y"], unsampled["plant.y"])
    assert cli.main(["validate", str(tmp_path / "d.yaml"), "--set",
                     "ctrl.sample_period=0"]) == 0


REF_INIT = """
blocks:
  q:   {{type: Constant, value: [0.3, -0.2]}}
  qd:  {{type: Sine, amplitude: [0.5, 0.4], frequency: [1.0, 2.0], phase: [0.4, 1.0], derivatives: 2}}
  zoh: {{type: ZeroOrderHold, period: 0.01, shape: [2]}}
  ref: {{type: ReferenceDynamics, variant: eq16, ell: 2, n: 2, alpha: 3}}
connections:
  - q.y -> {via}
  - {src}.y -> ref.q, ref.qdot
  - qd.y -> ref.q_d
  - qd.y_d1 -> ref.qdot_d
  - qd.y_d2 -> ref.qddot_d
simulation: {{t_final: 0.02, step: 0.001, solver: rk4}}
"""


def test_states_initialised_from_inputs_see_the_samples_of_t0(tmp_path):
    """Reference dynamics behind a hold start from the hold's sample of t = 0, as they do
    without the hold (not from the hold's initial value 0)."""
    from fwdstep.run.events import plan_events
    from fwdstep.run.simulate import initial_state
    held = _load(tmp_path, REF_INIT.format(via="zoh.u", src="zoh"))
    plain = _load(tmp_path, REF_INIT.format(via="zoh.u", src="q"))
    x_held = initial_state(held, event=plan_events(held, 0.001, 20).start)
    x_plain = initial_state(plain, event=plan_events(plain, 0.001, 20).start)
    ref = held.schedule[[st.block.name for st in held.schedule].index("ref")].state
    assert np.any(x_plain[:, ref] != 0)
    np.testing.assert_array_equal(x_held[:, ref], x_plain[:, ref])
    zoh = held.schedule[[st.block.name for st in held.schedule].index("zoh")].state
    np.testing.assert_array_equal(x_held[:, zoh], 0.0)      # updated by the run, once
    r = fwdstep.simulate(held)
    np.testing.assert_array_equal(r["zoh.y"][0], [0.3, -0.2])


def test_a_shipped_controller_subsystem_samples_signals_of_every_shape(tmp_path):
    """The holds take their shapes from the wiring (vectors and the (2, 4) regressor)."""
    import pathlib
    text = pathlib.Path("diagrams/slotine_li_disturbed.yaml").read_text().replace(
        "file: lib/torque_passive.yaml,", "file: lib/torque_passive.yaml, sample_period: 0.01,")
    path = tmp_path / "sampled.yaml"
    path.write_text(text)            # lib/ is found in the shipped library
    d = fwdstep.load_diagram(str(path), overrides={"simulation.t_final": 0.05})
    shapes = {b.name: b.inputs["u"].shape for b in d.blocks if b.type_name == "ZeroOrderHold"}
    assert shapes["tq/sample_Y"] == (2, 4) and shapes["tq/hold_tau"] == (2,)
    r = fwdstep.simulate(d)
    k = np.floor(r.t / 0.01 + 1e-9)
    changed = np.any(np.diff(r["tq.tau"], axis=0) != 0, axis=1)
    np.testing.assert_array_equal(changed, np.diff(k) != 0)     # held between samples
