"""The solve_ivp path (fwdstep.run.ivp): solver dop853 | radau | lsoda.

Checked against an analytic solution with a jump off the grid (the breakpoints make it
exact to the tolerance), against the fixed-step RK4 path at a tiny step on a nonlinear
closed loop, against scipy's exact discretisation for a sampled loop, and on the stiff
Theorem 4 at ell = 6.  The Result is the same object on the same output grid.
"""
import numpy as np
import pytest
from scipy.signal import cont2discrete

import fwdstep

ANALYTIC = """
blocks:
  u:   {type: Step, after: 1.0, time: 0.35}
  w:   {type: Sine, amplitude: 1.0, frequency: 0.5}
  s:   {type: Sum, signs: "++"}
  sys: {type: TransferFunction, num: [1], den: [1, 1], initial: 0.5}
connections:
  - u.y -> s.u1
  - w.y -> s.u2
  - s.y -> sys.u
simulation: {t_final: 2.0, step: 0.1, solver: rk4, log_every: 2}
"""


def _exact(t, T=0.35, w=0.5):
    forced = (np.sin(w * t) - w * np.cos(w * t) + w * np.exp(-t)) / (1 + w * w)
    return 0.5 * np.exp(-t) + forced + np.where(t >= T, 1 - np.exp(-(t - T)), 0.0)


def _load(tmp_path, text, **overrides):
    path = tmp_path / "d.yaml"
    path.write_text(text)
    return fwdstep.load_diagram(str(path), overrides=overrides or None)


@pytest.mark.parametrize("solver, tol", [("dop853", 1e-10), ("radau", 1e-8), ("lsoda", 1e-7)])
def test_matches_the_analytic_solution_across_a_jump(tmp_path, solver, tol):
    r = fwdstep.simulate(_load(tmp_path, ANALYTIC, **{
        "simulation.solver": solver, "simulation.rtol": 1e-12, "simulation.atol": 1e-12}))
    fixed = fwdstep.simulate(_load(tmp_path, ANALYTIC))
    np.testing.assert_array_equal(r.t, fixed.t)              # the same output grid
    assert r.names == fixed.names and r.status == "ok"
    assert np.abs(r["sys.y"] - _exact(r.t)).max() < tol
    np.testing.assert_array_equal(r["u.y"], fixed["u.y"])    # right limits at the records


LOOP = """
blocks:
  qd:  {type: Sine, amplitude: [0.5, 0.3], frequency: [1.0, 1.5], derivatives: 2}
  arm: {type: TwoLinkArm, q0: [0.3, -0.2]}
  e:   {type: Sum, signs: "+-", shape: [2]}
  ed:  {type: Sum, signs: "+-", shape: [2]}
  kp:  {type: Gain, gain: -40.0, shape: [2]}
  kd:  {type: Gain, gain: -12.0, shape: [2]}
  pd:  {type: Sum, signs: "++", shape: [2]}
connections:
  - arm.q -> e.u1
  - qd.y -> e.u2
  - arm.qdot -> ed.u1
  - qd.y_d1 -> ed.u2
  - e.y -> kp.u
  - ed.y -> kd.u
  - kp.y -> pd.u1
  - kd.y -> pd.u2
  - pd.y -> arm.tau
simulation: {t_final: 0.5, step: 0.0002, solver: rk4, log_every: 50}
"""


def test_dop853_agrees_with_rk4_at_a_tiny_step(tmp_path):
    fixed = fwdstep.simulate(_load(tmp_path, LOOP))
    r = fwdstep.simulate(_load(tmp_path, LOOP, **{"simulation.solver": "dop853",
                                                  "simulation.rtol": 1e-12,
                                                  "simulation.atol": 1e-12}))
    np.testing.assert_array_equal(r.t, fixed.t)
    assert np.abs(r["arm.q"] - fixed["arm.q"]).max() < 1e-10
    assert np.abs(r["pd.y"] - fixed["pd.y"]).max() < 1e-7


PD = """
blocks:
  plant: {type: StateSpace, A: [[0, 1], [0, 0]], B: [[0], [1]], C: [[1, 0], [0, 1]],
          initial: [1.0, 0.5]}
  pd:    {type: Gain, gain: [[-40.0, -9.0]]}
  zoh:   {type: ZeroOrderHold, period: 0.01, shape: [1]}
connections:
  - plant.y -> pd.u
  - pd.y -> zoh.u
  - zoh.y -> plant.u
simulation: {t_final: 0.5, step: 0.01, solver: radau, rtol: 1e-10, atol: 1e-12}
"""


def test_sample_instants_are_breakpoints_with_the_same_updates(tmp_path):
    A, B, K = np.array([[0, 1], [0, 0.0]]), np.array([[0], [1.0]]), np.array([[-40, -9.0]])
    Ad, Bd, *_ = cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), 0.01, method="zoh")
    xs = [np.array([1.0, 0.5])]
    for _ in range(50):
        xs.append((Ad + Bd @ K) @ xs[-1])
    r = fwdstep.simulate(_load(tmp_path, PD))
    assert np.abs(r["plant.y"] - np.array(xs)).max() < 1e-8
    np.testing.assert_allclose(r["zoh.y"][:, 0], [(K @ x)[0] for x in xs], rtol=0, atol=1e-7)


def test_theorem4_at_ell_6_runs_with_radau():
    """The stiff case (rk4 needs h = 0.5 ms): radau agrees with rk4, and is the more
    accurate of the two: halving rk4's step moves it towards radau by the factor 2^4."""
    over = {"ell": 6, "simulation.t_final": 0.2, "log_every": 20}

    def rk4(h):
        return fwdstep.simulate(fwdstep.load_diagram("diagrams/theorem4.yaml", overrides={
            **over, "step": h, "log_every": int(round(0.02 / h))}))

    r = fwdstep.simulate(fwdstep.load_diagram("diagrams/theorem4.yaml", overrides={
        **over, "simulation.solver": "radau", "simulation.rtol": 1e-8,
        "simulation.atol": 1e-10}))
    half, quarter = rk4(0.0005), rk4(0.00025)
    assert r.status == "ok" and r.steps < half.steps
    np.testing.assert_array_equal(r.t, half.t)
    e_half = np.abs(half["e.y"] - r["e.y"]).max()
    e_quarter = np.abs(quarter["e.y"] - r["e.y"]).max()
    assert e_half < 3e-6 and 10 < e_half / e_quarter < 25, (e_half, e_quarter)


def test_bad_settings_are_refused(tmp_path):
    with pytest.raises(fwdstep.ConfigError) as err:
        _load(tmp_path, ANALYTIC.replace("solver: rk4", "solver: rk4, rtol: -1"))
    assert "simulation.rtol must be positive" in str(err.value)
    with pytest.raises(fwdstep.ConfigError) as err:
        _load(tmp_path, ANALYTIC.replace("solver: rk4", "solver: ode45"))
    assert "solvers are: euler, heun, rk4, dop853, radau, lsoda" in str(err.value)
    d = _load(tmp_path, ANALYTIC, **{"simulation.solver": "radau"})
    with pytest.raises(fwdstep.ConfigError) as err:
        fwdstep.simulate(d, backend="compiled")
    assert "no compiled backend" in str(err.value)


def test_divergence_keeps_the_records_before_it(tmp_path):
    text = """
blocks:
  c: {type: Constant, value: 1.0}
  i: {type: TransferFunction, num: [1], den: [1, -5], initial: 1.0}
connections:
  - c.y -> i.u
simulation: {t_final: 10.0, step: 0.1, solver: dop853, bound: 1000}
"""
    with pytest.raises(fwdstep.DivergenceError) as err:
        fwdstep.simulate(_load(tmp_path, text))
    res = err.value.result
    assert res.status == "diverged" and 0 < len(res.t) < 101
    exact = 1.2 * np.exp(5 * res.t) - 0.2
    assert np.abs(res["i.y"] - exact).max() < 1e-6 * exact.max()
