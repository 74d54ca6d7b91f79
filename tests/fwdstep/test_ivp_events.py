"""State events on the solve_ivp path (fwdstep.run.ivp, issue 26): each guard a terminal
event, the crossing found again on the solver's own map, the blocks act, solve_ivp restarts.

Every reference is analytic: the kink of x' = -sat(x) at t = 2.37, a bouncing ball's apex
heights 0.64^k h0, a relay's triangle wave, a Stop at ln(1 / 0.3), an anti-windup
integrator of sin t.
"""
import math

import numpy as np
import pytest

import fwdstep
from tests.fwdstep import crossing_diagrams
from tests.fwdstep.crossing_diagrams import CHATTER, RELAY

TOL = {"simulation.rtol": 1e-10, "simulation.atol": 1e-10}


def _run(tmp_path, text, solver="dop853", name="d.yaml", **overrides):
    path = tmp_path / name
    path.write_text(text)
    over = {"simulation.solver": solver, **TOL, **overrides}
    return fwdstep.simulate(fwdstep.load_diagram(str(path), overrides=over))


SAT = """
blocks:
  sat: {type: Saturation, lower: -1.0, upper: 1.0}
  neg: {type: Gain, gain: -1.0}
  i:   {type: Integrator, initial: 3.37}
connections:
  - i.y -> sat.u
  - sat.y -> neg.u
  - neg.y -> i.u
simulation: {t_final: 5.0, step: 0.1, solver: rk4}
"""


@pytest.mark.parametrize("solver, tol, bound", [("dop853", 1e-10, 1e-10),
                                                ("dop853", 1e-12, 5e-13),
                                                ("radau", 1e-10, 2e-11)])
def test_saturated_decay_to_the_tolerance(tmp_path, solver, tol, bound):
    """x' = -sat(x; -1, 1), x(0) = 3.37: x = 3.37 - t up to t = 2.37, then e^-(t - 2.37).
    The kink is an event found to 1e-12 s, the state at t = 4 right to the tolerance
    (measured: dop853 5.0e-11 at 1e-10, 8.1e-14 at 1e-12, radau 6.3e-12; integrated
    through the kink dop853 gave 2.7e-10 and 3.3e-12)."""
    r = _run(tmp_path, SAT, solver, **{"simulation.rtol": tol, "simulation.atol": tol})
    assert r.status == "ok"
    assert [(e.block, e.kind) for e in r.events] == [("sat", "upper falling")]
    assert abs(r.events[0].time - 2.37) < 1e-12
    exact = np.where(r.t < 2.37, 3.37 - r.t, np.exp(-(r.t - 2.37)))
    err = np.abs(r["i.y"] - exact)
    assert err[r.t < 2.37].max() < 1e-14
    assert err[np.argmin(np.abs(r.t - 4.0))] < bound


BALL = crossing_diagrams.BALL.replace("t_final: 13.0", "t_final: 12.0")


@pytest.mark.parametrize("solver", ["dop853", "radau"])
def test_bouncing_ball_apex_heights(tmp_path, solver):
    """Restitution 0.8 from 10 m: the apex after bounce k is 0.64^k * 10 m (p + v^2 / 2g
    between bounces), the first impact at sqrt(2 h0 / g)."""
    r = _run(tmp_path, BALL, solver)
    bounces = [e.time for e in r.events if e.kind == "reset rising"]
    assert abs(bounces[0] - math.sqrt(2 * 10 / 9.81)) < 1e-12
    apex = r["p.y"] + r["v.y"] ** 2 / (2 * 9.81)
    for k in range(10):
        flight = (r.t > bounces[k]) & (r.t < bounces[k + 1])
        assert flight.any()
        np.testing.assert_allclose(apex[flight], 10 * 0.64 ** (k + 1), rtol=0, atol=1e-8)


def test_stop_block_ends_the_run_at_the_analytic_time(tmp_path):
    """x' = -x from 1, Stop on x - 0.3: it stops at t = ln(1 / 0.3)."""
    r = _run(tmp_path, """
blocks:
  x:    {type: TransferFunction, num: [1], den: [1, 1], initial: 1.0}
  zero: {type: Constant, value: 0.0}
  lvl:  {type: Constant, value: 0.3}
  d:    {type: Sum, signs: "+-"}
  stop: {type: Stop}
connections:
  - zero.y -> x.u
  - x.y -> d.u1
  - lvl.y -> d.u2
  - d.y -> stop.u
simulation: {t_final: 5.0, step: 0.1, solver: rk4}
""")
    t_stop = math.log(1 / 0.3)
    assert r.status == "stopped"
    assert abs(r.t[-1] - t_stop) < 1e-10 and abs(r["x.y"][-1] - 0.3) < 1e-10
    said = r.message.split("stopped by block 'stop' (Stop) at t = ")[1]
    assert abs(float(said) - t_stop) < 1e-10
    assert [(e.block, round(e.time, 9)) for e in r.events] == [("stop", round(t_stop, 9))]


@pytest.mark.parametrize("solver", ["dop853", "radau", "lsoda"])
def test_relay_switching_times(tmp_path, solver):
    """Off (+1) until x reaches 1, on (-1) until x falls to -1: switches at 1, 3, 5, 7 and
    x is the triangle wave of period 4."""
    r = _run(tmp_path, RELAY, solver)
    assert [e.kind for e in r.events] == ["switch rising", "switch falling"] * 2
    np.testing.assert_allclose([e.time for e in r.events], [1.0, 3.0, 5.0, 7.0], rtol=0,
                               atol=1e-11)
    s = (r.t + 1.0) % 4.0
    np.testing.assert_allclose(r["x.y"], np.where(s < 2.0, s - 1.0, 3.0 - s), rtol=0,
                               atol=1e-9)


def test_chattering_is_reported_once(tmp_path):
    """x' = -sign(x) slides on x = 0 from t = 0.5: one report, one note, the run goes on
    with the relay following at the grid steps."""
    r = _run(tmp_path, CHATTER)
    assert r.status == "ok"
    kinds = [e.kind for e in r.events]
    assert kinds.count("chattering") == 1 and len(kinds) < 20
    assert abs(r.events[0].time - 0.5) < 1e-12
    assert len(r.notes) == 1 and "chattering" in r.notes[0] and "'relay' (Relay)" in r.notes[0]
    assert np.abs(r["x.y"][r.t > 0.6]).max() < 0.02


def test_limited_integrator_holds_and_leaves(tmp_path):
    """x' = sin t, x <= 0.5: 1 - cos t until pi/3, held until sin t < 0 (pi), then
    -0.5 - cos t."""
    r = _run(tmp_path, """
blocks:
  s: {type: Sine, amplitude: 1.0, frequency: 1.0}
  x: {type: LimitedIntegrator, upper: 0.5}
connections:
  - s.y -> x.u
simulation: {t_final: 5.0, step: 0.01, solver: rk4}
""", **{"simulation.rtol": 1e-12, "simulation.atol": 1e-12})
    t = r.t
    exact = np.where(t < math.pi / 3, 1 - np.cos(t), np.where(t < math.pi, 0.5,
                                                                -0.5 - np.cos(t)))
    np.testing.assert_allclose(r["x.y"], exact, rtol=0, atol=1e-10)
    assert [e.kind for e in r.events] == ["upper falling", "upper rising"]
    np.testing.assert_allclose([e.time for e in r.events], [math.pi / 3, math.pi], atol=1e-11)


def test_a_guard_that_jumps_at_a_declared_time_acts_there(tmp_path):
    """The projection holds theta at 0.5 until e steps at t = 1 (a segment boundary of
    solve_ivp): the update's sign jumps there and theta leaves the bound at once."""
    r = _run(tmp_path, """
blocks:
  W:  {type: Constant, value: [1.0]}
  e:  {type: Step, before: [-1.0], after: [1.0], time: 1.0}
  th: {type: AdaptationLaw, regressor_shape: [1], gamma: 2.0, theta0: 0.0, upper: 0.5,
       lower: -0.3}
connections:
  - W.y -> th.W
  - e.y -> th.e
simulation: {t_final: 1.5, step: 0.03, solver: rk4}
""")
    t = r.t
    exact = np.where(t < 0.25, 2 * t, np.where(t < 1.0, 0.5, np.maximum(0.5 - 2 * (t - 1.0),
                                                                          -0.3)))
    np.testing.assert_allclose(r["th.theta_hat"], exact, rtol=0, atol=1e-10)
    assert [(e.kind, round(e.time, 10)) for e in r.events] == [
        ("upper falling", 0.25), ("upper rising", 1.0), ("lower falling", 1.4)]


def test_batch_variants_have_their_own_events(tmp_path):
    """The batch is one ODE system; a crossing of one variant acts on that variant only."""
    path = tmp_path / "b.yaml"
    path.write_text(SAT.replace("upper: 1.0", "upper: U").replace(
        "blocks:", "parameters: {U: 1.0}\nblocks:"))
    over = {"simulation.solver": "dop853", **TOL}
    specs = [fwdstep.structure.spec.load_spec(str(path), {"U": u, **over}) for u in (1.0, 2.0)]
    r = fwdstep.simulate(fwdstep.compile_batch(specs))
    by = {v: [e.time for e in r.events if e.variant == v] for v in (0, 1)}
    np.testing.assert_allclose(by[0], [2.37], atol=1e-12)
    np.testing.assert_allclose(by[1], [(3.37 - 2.0) / 2.0], atol=1e-12)   # x' = -2 above 2
    exact1 = np.where(r.t < 0.685, 3.37 - 2 * r.t, 2 * np.exp(-(r.t - 0.685)))
    assert np.abs(r["i.y"][:, 1] - exact1).max() < 1e-9
