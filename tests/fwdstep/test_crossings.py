"""Exact state events (fwdstep.run.crossings, issue 26): zero crossings located in time.

Every reference here is analytic: a saturated decay whose kink time is known in closed
form, a bouncing ball's apex heights e^(2k) h0, a relay's triangle wave, an anti-windup
integrator of sin t.  A kink integrated through costs RK4 its order (2.1 measured before);
located, the order stays 4.
"""
import math

import numpy as np
import pytest

import fwdstep
from tests.fwdstep.crossing_diagrams import BALL, CHATTER, RELAY, STOP


def _run(tmp_path, text, name="d.yaml", **kw):
    path = tmp_path / name
    path.write_text(text)
    return fwdstep.simulate(fwdstep.load_diagram(str(path)), **kw)


SAT = """
blocks:
  sat: {{type: Saturation, lower: -1.0, upper: {upper}}}
  neg: {{type: Gain, gain: -1.0}}
  i:   {{type: Integrator, initial: 3.37}}
connections:
  - i.y -> sat.u
  - sat.y -> neg.u
  - neg.y -> i.u
simulation: {{t_final: 5.0, step: {h!r}, solver: rk4}}
"""


def test_saturated_decay_keeps_rk4_order(tmp_path):
    """x' = -sat(x; -1, 1), x(0) = 3.37: x = 3.37 - t until t = 2.37, then e^-(t - 2.37)."""
    hs = (0.2, 0.1, 0.05)
    errors = []
    for h in hs:
        r = _run(tmp_path, SAT.format(upper=1.0, h=h))
        exact = np.where(r.t < 2.37, 3.37 - r.t, np.exp(-(r.t - 2.37)))
        errors.append(np.abs(r["i.y"] - exact).max())
        assert [(e.block, e.kind) for e in r.events] == [("sat", "upper falling")]
        assert abs(r.events[0].time - 2.37) < 1e-12
    order = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    assert order >= 3.5, (order, errors)
    assert errors[-1] <= 1e-6


def test_no_crossing_costs_no_number(tmp_path):
    """A Saturation that never saturates gives the numbers of a unit Gain, bit for bit
    (a step without a crossing is the plain procedure)."""
    r = _run(tmp_path, SAT.format(upper=100.0, h=0.1).replace("lower: -1.0", "lower: -100.0"),
             fuse=False)
    g = _run(tmp_path, SAT.format(upper=1.0, h=0.1).replace(
        "{type: Saturation, lower: -1.0, upper: 1.0}", "{type: Gain, gain: 1.0}"), "g.yaml",
        fuse=False)
    assert r.events == []
    np.testing.assert_array_equal(r["i.y"], g["i.y"])


def test_bouncing_ball_apex_heights(tmp_path):
    """Restitution 0.8 from 10 m: the apex after bounce k is 0.64^k * 10 m.  Between
    bounces p + v^2 / 2g is the apex height (energy), read at every recorded step."""
    r = _run(tmp_path, BALL)
    bounces = [e.time for e in r.events if e.kind == "reset rising"]
    assert abs(bounces[0] - math.sqrt(2 * 10 / 9.81)) < 1e-12
    apex = r["p.y"] + r["v.y"] ** 2 / (2 * 9.81)
    for k in range(10):
        flight = (r.t > bounces[k]) & (r.t < bounces[k + 1])
        assert flight.any()
        np.testing.assert_allclose(apex[flight], 10 * 0.64 ** (k + 1), rtol=0, atol=1e-9)


@pytest.mark.parametrize("backend", ["numpy", "compiled"])
def test_the_ball_never_falls_through_the_floor_unsaid(tmp_path, backend):
    """The bounces accumulate at the Zeno time t* = t1 (1 + e) / (1 - e) (t1 = sqrt(2 h0 /
    g), e = 0.8: 12.8506 s).  Once a bounce was shorter than a step, the guard crossed back
    and returned to its side within the step and the ball fell through the floor (p = -0.149
    m at 13 s) with no word.  Every bounce is now located until they recur more than the
    chattering limit within one step, just before t*, which the run says; until then the
    ball stays above the floor."""
    if backend == "compiled":
        pytest.importorskip("numba", reason="the compiled backend needs numba")
    r = _run(tmp_path, BALL, backend=backend)
    zeno = math.sqrt(2 * 10 / 9.81) * 1.8 / 0.2
    said = [e.time for e in r.events if e.kind == "chattering"]
    assert len(said) == 1 and zeno - 0.01 < said[0] < zeno
    assert any("chattering" in note for note in r.notes)
    assert r["p.y"][r.t < said[0]].min() > -1e-9


def test_relay_hysteresis_is_a_triangle_wave(tmp_path):
    """Off (+1) until x reaches 1, on (-1) until x falls to -1: switches at 1, 3, 5, 7."""
    r = _run(tmp_path, RELAY)
    times = [e.time for e in r.events]
    np.testing.assert_allclose(times, [1.0, 3.0, 5.0, 7.0], rtol=0, atol=1e-12)
    s = (r.t + 1.0) % 4.0                      # the triangle of period 4 through (0, 0)
    exact = np.where(s < 2.0, s - 1.0, 3.0 - s)
    np.testing.assert_allclose(r["x.y"], exact, rtol=0, atol=1e-12)


def test_stop_block_ends_the_run_at_the_crossing(tmp_path):
    r = _run(tmp_path, STOP)
    assert r.status == "stopped"
    assert abs(r.t[-1] - 1.234) < 1e-12 and abs(r["x.y"][-1]) < 1e-12
    assert "stopped by block 'stop' (Stop) at t = 1.234" in r.message


def test_a_stopped_variant_of_a_sweep_says_so(tmp_path):
    """Each variant with a Stop block runs on its own and stops at x0 (x' = -1): the
    sweep's table said only 'ok', as for a variant that ran to t_final."""
    from fwdstep.sweeps.sweep import run_sweep
    path = tmp_path / "stop.yaml"
    path.write_text("parameters: {x0: 1.234}\n" + STOP.replace("initial: 1.234", "initial: x0"))
    result = run_sweep(str(path), grid={"x0": [0.5, 7.0]})
    stopped, through = result.variants
    assert stopped.status == "ok" and stopped.message == \
        "stopped by block 'stop' (Stop) at t = 0.5"
    assert through.status == "ok" and through.message == ""     # t_final = 5 < 7: no stop


def test_chattering_is_reported_once(tmp_path):
    """x' = -sign(x) (a Relay without hysteresis) slides on x = 0 from t = 0.5: one
    report, one note, and the run goes on (no storm of tiny steps)."""
    r = _run(tmp_path, CHATTER)
    assert r.status == "ok"
    kinds = [e.kind for e in r.events]
    assert kinds.count("chattering") == 1 and len(kinds) < 20
    assert abs(r.events[0].time - 0.5) < 1e-12
    assert len(r.notes) == 1 and "chattering" in r.notes[0] and "'relay' (Relay)" in r.notes[0]
    assert np.abs(r["x.y"][r.t > 0.6]).max() < 0.02


def test_limited_integrator_holds_at_the_limit_and_leaves_when_u_turns(tmp_path):
    """x' = sin t, x <= 0.5: 1 - cos t until t = pi/3, held at 0.5 until sin t < 0
    (t = pi), then 0.5 - (1 + cos t)."""
    r = _run(tmp_path, """
blocks:
  s: {type: Sine, amplitude: 1.0, frequency: 1.0}
  x: {type: LimitedIntegrator, upper: 0.5}
connections:
  - s.y -> x.u
simulation: {t_final: 5.0, step: 0.01, solver: rk4}
""")
    t = r.t
    exact = np.where(t < math.pi / 3, 1 - np.cos(t), np.where(t < math.pi, 0.5,
                                                                -0.5 - np.cos(t)))
    np.testing.assert_allclose(r["x.y"], exact, rtol=0, atol=1e-9)
    assert [e.kind for e in r.events] == ["upper falling", "upper rising"]
    np.testing.assert_allclose([e.time for e in r.events], [math.pi / 3, math.pi], atol=1e-12)


def test_batch_variants_have_their_own_events(tmp_path):
    path = tmp_path / "b.yaml"
    path.write_text(SAT.format(upper="U", h=0.05).replace("blocks:", "parameters: {U: 1.0}\nblocks:"))
    specs = [fwdstep.structure.spec.load_spec(str(path), {"U": u}) for u in (1.0, 2.0)]
    r = fwdstep.simulate(fwdstep.compile_batch(specs))
    by = {v: [e.time for e in r.events if e.variant == v] for v in (0, 1)}
    for v, u in enumerate((1.0, 2.0)):                 # each variant: its run alone
        alone = fwdstep.simulate(fwdstep.load_diagram(str(path), {"U": u}))
        np.testing.assert_allclose(r["i.y"][:, v], alone["i.y"], rtol=0, atol=1e-13)
        assert [e.time for e in alone.events] == by[v]
    np.testing.assert_allclose(by[0], [2.37], atol=1e-12)
    np.testing.assert_allclose(by[1], [(3.37 - 2.0) / 2.0], atol=1e-12)   # x' = -2 above 2


def test_compiled_backend_locates_them_too(tmp_path):
    """(More in test_compiled_crossings.py.)"""
    pytest.importorskip("numba")
    r = _run(tmp_path, SAT.format(upper=1.0, h=0.1), backend="compiled")
    n = _run(tmp_path, SAT.format(upper=1.0, h=0.1))
    assert r.backend == "compiled" and r.notes == []
    np.testing.assert_allclose(r["i.y"], n["i.y"], rtol=0, atol=1e-12)


def test_adaptation_law_projection_keeps_the_estimate_in_its_box(tmp_path):
    """theta' = -gamma W e with W = 1, e = -1 (then +1 from t = 1): theta = 2 t up to the
    bound 0.5 (t = 0.25), held there until e turns at t = 1, then 0.5 - 2 (t - 1)."""
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
    np.testing.assert_allclose(r["th.theta_hat"], exact, rtol=0, atol=1e-12)
    assert [(e.kind, round(e.time, 12)) for e in r.events] == [
        ("upper falling", 0.25), ("upper rising", 1.0), ("lower falling", 1.4)]
