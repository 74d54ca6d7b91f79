"""Zero crossings on the compiled backend (issue 26, item 4): the compiled loop watches the
guards and hands the steps that cross to the NumPy path's locating machinery.

Each run is checked against the NumPy backend (another implementation of the step: the
generated NumPy program, not the LLVM stage) to 1e-12 -- states, logged signals, the events'
times, blocks and kinds -- and, where one exists, against the analytic answer (a kink at
t = 2.37, a relay's switches at 1, 3, 5, 7, a Stop at 1.234, a ball's apex heights).
"""
import math

import numpy as np
import pytest

import fwdstep
from fwdstep.structure.spec import load_spec
from tests.fwdstep.crossing_diagrams import BALL, CHATTER, RELAY, STOP

pytest.importorskip("numba")

SAT = """
parameters: {U: 1.0}
blocks:
  sat: {type: Saturation, lower: -1.0, upper: U}
  neg: {type: Gain, gain: -1.0}
  i:   {type: Integrator, initial: 3.37}
connections:
  - i.y -> sat.u
  - sat.y -> neg.u
  - neg.y -> i.u
simulation: {t_final: 5.0, step: 0.1, solver: rk4}
"""


# a declared time (the Step at 1.05) as well as crossings; records every 3rd step
STEPPED = SAT.replace("  i:   {type: Integrator, initial: 3.37}", """  i:   {type: Integrator, initial: 3.37}
  s:   {type: Step, time: 1.05, before: 0.0, after: 0.3}
  add: {type: Sum, signs: "++"}""").replace("  - sat.y -> neg.u", """  - sat.y -> add.u1
  - s.y -> add.u2
  - add.y -> neg.u""").replace("step: 0.1, solver: rk4", "step: 0.05, solver: rk4, log_every: 3")


def _both(tmp_path, text, overrides=None):
    path = tmp_path / "d.yaml"
    path.write_text(text)
    runs = [fwdstep.simulate(fwdstep.load_diagram(str(path), overrides), backend=b)
            for b in ("compiled", "numpy")]
    _same(*runs)
    return runs[0]


def _same(c, n):
    """The compiled run c gives the NumPy run n's numbers (1e-12) and events."""
    assert c.backend == "compiled" and n.backend == "numpy"
    assert c.status == n.status and c.message == n.message and c.notes == n.notes
    np.testing.assert_allclose(c.t, n.t, rtol=0, atol=1e-12)
    for name in n.names:
        np.testing.assert_allclose(c[name], n[name], rtol=0, atol=1e-12, err_msg=name)
    assert [(e.block, e.kind, e.variant) for e in c.events] == \
        [(e.block, e.kind, e.variant) for e in n.events]
    np.testing.assert_allclose([e.time for e in c.events], [e.time for e in n.events],
                               rtol=0, atol=1e-12)


def test_saturated_decay(tmp_path):
    """x' = -sat(x), x(0) = 3.37: x = 3.37 - t until 2.37, then e^-(t - 2.37)."""
    r = _both(tmp_path, SAT)
    assert r.notes == []
    assert [(e.block, e.kind) for e in r.events] == [("sat", "upper falling")]
    assert abs(r.events[0].time - 2.37) < 1e-12
    exact = np.where(r.t < 2.37, 3.37 - r.t, np.exp(-(r.t - 2.37)))
    assert np.abs(r["i.y"] - exact).max() < 1e-4


def test_limits_never_reached_give_the_numbers_of_no_limit(tmp_path):
    """A Saturation that never saturates: no event, and the numbers of a unit Gain, bit
    for bit (a step without a crossing is the plain compiled step)."""
    wide = SAT.replace("lower: -1.0, upper: U", "lower: -100.0, upper: 100.0")
    r = _both(tmp_path, wide)
    g = _both(tmp_path, wide.replace("{type: Saturation, lower: -100.0, upper: 100.0}",
                                     "{type: Gain, gain: 1.0}"))
    assert r.events == []
    np.testing.assert_array_equal(r["i.y"], g["i.y"])


def test_bouncing_ball(tmp_path):
    """A limited integrator with reset: the apex after bounce k is 0.64^k * 10 m."""
    r = _both(tmp_path, BALL)
    bounces = [e.time for e in r.events if e.kind == "reset rising"]
    assert abs(bounces[0] - math.sqrt(2 * 10 / 9.81)) < 1e-12
    apex = r["p.y"] + r["v.y"] ** 2 / (2 * 9.81)
    for k in range(10):
        flight = (r.t > bounces[k]) & (r.t < bounces[k + 1])
        np.testing.assert_allclose(apex[flight], 10 * 0.64 ** (k + 1), rtol=0, atol=1e-9)


def test_relay_loop(tmp_path):
    """The relay's state (its mode) is a state: both paths read and set the same one."""
    r = _both(tmp_path, RELAY)
    np.testing.assert_allclose([e.time for e in r.events], [1.0, 3.0, 5.0, 7.0], rtol=0,
                               atol=1e-12)


def test_stop_block(tmp_path):
    r = _both(tmp_path, STOP)
    assert r.status == "stopped" and "at t = 1.234" in r.message
    assert abs(r.t[-1] - 1.234) < 1e-12 and abs(r["x.y"][-1]) < 1e-12


def test_chattering_goes_on_with_one_note(tmp_path):
    r = _both(tmp_path, CHATTER)
    assert [e.kind for e in r.events].count("chattering") == 1
    assert len(r.notes) == 1 and "chattering" in r.notes[0]


def test_declared_times_and_crossings(tmp_path):
    """A Step at 1.05 (a split step) in a loop whose saturation is left at 2.0654."""
    r = _both(tmp_path, STEPPED)
    # x' = -1 - 0.3 from 1.05 until x = 1: 3.37 - 1.05 - 1.3 (t - 1.05) = 1
    assert abs(r.events[0].time - (1.05 + (3.37 - 1.05 - 1.0) / 1.3)) < 1e-12


@pytest.mark.parametrize("chunk", [1, 7])
def test_chunk_boundaries(tmp_path, monkeypatch, chunk):
    """Crossings at the end of a compiled chunk (the loop's end check) and at its start."""
    from fwdstep.compiled import backend_numba
    monkeypatch.setattr(backend_numba, "CHUNK", chunk)
    _both(tmp_path, BALL.replace("t_final: 13.0", "t_final: 4.0"))
    _both(tmp_path, STOP)


@pytest.mark.parametrize("chunk", [7, 2000])
def test_batch_each_variant_its_own_events(tmp_path, monkeypatch, chunk):
    """Three variants crossing at different times (one per chunk when it is 7 steps)."""
    from fwdstep.compiled import backend_numba
    monkeypatch.setattr(backend_numba, "CHUNK", chunk)
    path = tmp_path / "b.yaml"
    path.write_text(STEPPED)
    us = (1.0, 2.0, 0.5)
    runs = [fwdstep.simulate(fwdstep.compile_batch([load_spec(str(path), {"U": u})
                                                    for u in us]), backend=b)
            for b in ("compiled", "numpy")]
    _same(*runs)
    by = {v: [e.time for e in runs[0].events if e.variant == v] for v in range(3)}
    # variant 1 (U = 2): x' = -2 until x = 2 at 0.685, before the Step
    np.testing.assert_allclose(by[1], [(3.37 - 2.0) / 2.0], atol=1e-12)
    assert len(by[0]) == len(by[2]) == 1 and by[0][0] < by[2][0]
    for v, u in enumerate(us):                       # each variant: its run alone
        alone = fwdstep.simulate(fwdstep.load_diagram(str(path), {"U": u}),
                                 backend="compiled")
        np.testing.assert_allclose(runs[0]["i.y"][:, v], alone["i.y"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(by[v], [e.time for e in alone.events], rtol=0,
                                   atol=1e-12)


def test_untraceable_stage_takes_the_numpy_path_with_a_note(tmp_path):
    """A table lookup does not trace into scalar code: the run says so and uses NumPy."""
    path = tmp_path / "l.yaml"
    path.write_text("""
blocks:
  lk:  {type: Lookup1D, breakpoints: [-1.0, 0.0, 1.0], values: [1.0, 0.0, 1.0]}
  neg: {type: Gain, gain: -1.0}
  i:   {type: Integrator, initial: 2.0}
connections:
  - i.y -> lk.u
  - lk.y -> neg.u
  - neg.y -> i.u
simulation: {t_final: 3.0, step: 0.1, solver: rk4}
""")
    r = fwdstep.simulate(fwdstep.load_diagram(str(path)), backend="compiled")
    assert r.backend == "numpy"
    assert len(r.notes) == 1 and "'lk' (Lookup1D) has zero crossings" in r.notes[0]
    assert [e.kind for e in r.events] == ["b2 falling"] and abs(r.events[0].time - 1.0) < 1e-12


def test_relay_batch_thresholds_per_variant(tmp_path):
    """A guard method (Relay.zero_crossings) reads each variant's own parameters."""
    path = tmp_path / "r.yaml"
    path.write_text(RELAY.replace("blocks:", "parameters: {T: 1.0}\nblocks:").replace(
        "on_threshold: 1.0, off_threshold: -1.0", "on_threshold: T, off_threshold: -1.0"))
    ts = (1.0, 0.5, 1.5)
    runs = [fwdstep.simulate(fwdstep.compile_batch([load_spec(str(path), {"T": t})
                                                    for t in ts]), backend=b)
            for b in ("compiled", "numpy")]
    _same(*runs)
    for v, t in enumerate(ts):       # up to T at t = T, then down to -1 at T + (T + 1)
        first = [e.time for e in runs[0].events if e.variant == v][:2]
        np.testing.assert_allclose(first, [t, 2 * t + 1], rtol=0, atol=1e-12)


def test_other_guarded_blocks(tmp_path):
    """DeadZone, RateLimiter, Switch and an AdaptationLaw with projection (a declared time
    too): traced guards, the NumPy path's numbers and events."""
    r = _both(tmp_path, """
blocks:
  s:   {type: Sine, amplitude: 2.0, frequency: 1.3}
  dz:  {type: DeadZone, lower: -0.5, upper: 0.7}
  rl:  {type: RateLimiter, rising: 0.8, falling: 0.6, time_constant: 0.01}
  sw:  {type: Switch, threshold: 0.5}
  c1:  {type: Constant, value: 1.0}
  c2:  {type: Constant, value: -1.0}
  i:   {type: Integrator, initial: 0.3}
  sum: {type: Sum, signs: "++"}
connections:
  - s.y -> dz.u
  - s.y -> rl.u
  - c1.y -> sw.u1
  - s.y -> sw.control
  - c2.y -> sw.u2
  - dz.y -> sum.u1
  - sw.y -> sum.u2
  - sum.y -> i.u
simulation: {t_final: 6.0, step: 0.01, solver: rk4}
log: [i.y, rl.y, dz.y, sw.y]
""")
    assert {e.block for e in r.events} == {"dz", "rl", "sw"}
    r = _both(tmp_path, """
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
    assert [(e.kind, round(e.time, 12)) for e in r.events] == [
        ("upper falling", 0.25), ("upper rising", 1.0), ("lower falling", 1.4)]


DIVERGING = SAT.replace("parameters: {U: 1.0}", "parameters: {U: 1.0, A: 0.0}").replace(
    "  i:   {type: Integrator, initial: 3.37}", """  i:   {type: Integrator, initial: 3.37}
  a:   {type: Gain, gain: A}
  j:   {type: Integrator, initial: 1.0}""").replace("  - neg.y -> i.u", """  - neg.y -> i.u
  - j.y -> a.u
  - a.y -> j.u""").replace("step: 0.1", "step: 0.05")


def _run_or_failed(d, backend):
    try:
        return fwdstep.simulate(d, backend=backend)
    except fwdstep.SimulationError as exc:
        return exc.result


def test_a_diverging_run_keeps_the_rows_of_the_plain_procedure(tmp_path):
    """x' = 12 x leaves the bound at 1.55 s, before the saturation's kink: both backends
    keep the rows the same diagram without guards keeps (no record of the state beyond
    the bound)."""
    path = tmp_path / "d.yaml"
    path.write_text(DIVERGING)
    plain = tmp_path / "g.yaml"
    plain.write_text(DIVERGING.replace("{type: Saturation, lower: -1.0, upper: U}",
                                       "{type: Gain, gain: 1.0}"))
    ref = _run_or_failed(fwdstep.load_diagram(str(plain), {"A": 12.0}), "numpy")
    for backend in ("compiled", "numpy"):
        r = _run_or_failed(fwdstep.load_diagram(str(path), {"A": 12.0}), backend)
        assert r.status == ref.status == "diverged" and r.message == ref.message
        np.testing.assert_array_equal(r.t, ref.t)
        np.testing.assert_allclose(r["j.y"], ref["j.y"], rtol=1e-15)


@pytest.mark.parametrize("chunk", [7, 2000])
def test_batch_with_a_diverging_variant(tmp_path, monkeypatch, chunk):
    """One variant diverges (1.55 s), the others cross at 2.37 s: the NumPy path's
    general procedure goes on for them (it overran its record by a row before), and the
    compiled backend gives its numbers and events."""
    from fwdstep.compiled import backend_numba
    monkeypatch.setattr(backend_numba, "CHUNK", chunk)
    path = tmp_path / "b.yaml"
    path.write_text(DIVERGING)
    specs = [load_spec(str(path), {"A": a}) for a in (0.0, 12.0, 0.0)]
    c, n = (_run_or_failed(fwdstep.compile_batch(specs), b) for b in ("compiled", "numpy"))
    assert c.status == n.status == "partially diverged" and c.message == n.message
    for name in n.names:
        np.testing.assert_allclose(c[name], n[name], rtol=0, atol=1e-12, err_msg=name)
    assert [(e.block, e.kind, e.variant) for e in c.events] == [
        ("sat", "upper falling", 0), ("sat", "upper falling", 2)]
    np.testing.assert_allclose([e.time for e in c.events], [2.37, 2.37], atol=1e-12)
    np.testing.assert_allclose([e.time for e in n.events], [2.37, 2.37], atol=1e-12)


@pytest.mark.parametrize("chatter", [False, True])
def test_sampled_loop_and_friction(tmp_path, chatter):
    """A ZeroOrderHold (discrete updates at 0.07 s, off the grid; one at t_final) before
    the Saturation, and a Friction block, which chatters at v = 0 (the NumPy path then
    runs the rest); with ``chatter``, a relay chatters from 0.5 s."""
    text = """
blocks:
  sat: {type: Saturation, lower: -1.0, upper: 1.0}
  zoh: {type: ZeroOrderHold, period: 0.07}
  neg: {type: Gain, gain: -1.0}
  i:   {type: Integrator, initial: 3.37}
  fr:  {type: Friction, n: 1, coulomb: 0.2, viscous: 0.1}
  v:   {type: Integrator, initial: [1.0], shape: [1]}
connections:
  - i.y -> zoh.u
  - zoh.y -> sat.u
  - sat.y -> neg.u
  - neg.y -> i.u
  - v.y -> fr.qdot
  - fr.tau_f -> v.u
simulation: {t_final: 4.9, step: 0.05, solver: rk4, log_every: 2}
"""
    if chatter:
        text = text.replace("connections:", CHATTER.split("connections:")[0].split(
            "blocks:")[1] + "connections:").replace(
            "simulation:", "  - x.y -> relay.u\n  - relay.y -> x.u\nsimulation:")
    r = _both(tmp_path, text)
    assert ("sat", "upper falling") in [(e.block, e.kind) for e in r.events]
    # the Friction's held sign sticks at v = 0 near t = 4.05 s (stiction)
    assert {e.block for e in r.events if e.kind == "chattering"} == (
        {"fr", "relay"} if chatter else {"fr"})


def test_clip_ball_projection_and_a_plugin_guard(tmp_path):
    """Clip (limits as signals), AdaptationLaw's ball projection and the documented
    CrossingCounter plugin (examples/plugins): traced, the NumPy path's numbers."""
    import os
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    r = _both(tmp_path, SAT.replace("{type: Saturation, lower: -1.0, upper: U}",
                                    "{type: Clip, symmetric: true}\n  lim: {type: Constant, "
                                    "value: 1.0}").replace("connections:",
                                                           "connections:\n  - lim.y -> sat.limit"))
    assert abs(r.events[0].time - 2.37) < 1e-12
    _both(tmp_path, """
blocks:
  W:  {type: Constant, value: [[1.0, 0.5]]}
  e:  {type: Step, before: [-1.0], after: [1.0], time: 1.0}
  th: {type: AdaptationLaw, regressor_shape: [1, 2], gamma: 2.0, theta0: 0.0, radius: 0.5}
connections:
  - W.y -> th.W
  - e.y -> th.e
simulation: {t_final: 1.5, step: 0.03, solver: rk4}
""")
    path = tmp_path / "count.yaml"
    path.write_text("""
blocks:
  s: {type: Sine, amplitude: 1.0, frequency: 1.0}
  c: {type: CrossingCounter}
connections:
  - s.y -> c.u
simulation: {t_final: 14.0, step: 0.1, solver: rk4}
""")
    counter = os.path.join(root, "examples", "plugins", "crossing_counter.py")
    c, n = (fwdstep.simulate(fwdstep.load_diagram(str(path), plugins=[counter]), backend=b)
            for b in ("compiled", "numpy"))
    _same(c, n)
    np.testing.assert_allclose([e.time for e in c.events], np.pi * np.arange(1, 5), atol=1e-12)


def test_failed_variant_at_a_chunk_ending_on_a_declared_time(tmp_path, monkeypatch):
    """A variant diverges (1.3 s) in the chunk that ends on the step split at the Step's
    1.6 s (step 31, chunks of 31): the NumPy path goes on from there and sees the Relay's
    guard jump at 1.6 s (the signs at the end of the step before, as its own run has
    them)."""
    from fwdstep.compiled import backend_numba
    monkeypatch.setattr(backend_numba, "CHUNK", 31)
    text = DIVERGING.replace("  a:   {type: Gain, gain: A}", """  a:   {type: Gain, gain: A}
  st:  {type: Step, time: 1.6, before: 0.0, after: -5.0}
  add: {type: Sum, signs: "++"}
  relay: {type: Relay, on_threshold: 1.0, off_threshold: -1.0}""").replace(
        "  - j.y -> a.u", """  - j.y -> a.u
  - i.y -> add.u1
  - st.y -> add.u2
  - add.y -> relay.u""")
    path = tmp_path / "b.yaml"
    path.write_text(text)
    specs = [load_spec(str(path), {"A": a}) for a in (0.0, 14.0)]
    c, n = (_run_or_failed(fwdstep.compile_batch(specs), b) for b in ("compiled", "numpy"))
    assert c.status == n.status == "partially diverged"
    for name in n.names:
        np.testing.assert_allclose(c[name], n[name], rtol=0, atol=1e-12, err_msg=name)
    ev = [(e.block, e.kind, e.variant) for e in n.events]
    assert [(e.block, e.kind, e.variant) for e in c.events] == ev
    assert ("relay", "switch falling", 0) in ev
    np.testing.assert_allclose([e.time for e in c.events], [e.time for e in n.events],
                               atol=1e-12)


@pytest.mark.slow
def test_a_fresh_compile_of_a_guarded_batch_prints_no_numba_warning(tmp_path):
    """The first compile of a batch whose loop watches guards (empty caches) printed numba's
    NumbaExperimentalFeatureWarning, colour codes and all, on the user's terminal."""
    import os
    import subprocess
    import sys
    path = tmp_path / "ball.yaml"
    path.write_text(BALL)
    env = dict(os.environ, FWDSTEP_CACHE_DIR=str(tmp_path / "fc"),
               NUMBA_CACHE_DIR=str(tmp_path / "nc"))
    done = subprocess.run([sys.executable, "-c", "import sys; from fwdstep.cli.arguments "
                           "import main; sys.exit(main())", "sweep", str(path),
                           "--grid", "v.initial=0,1,2", "--backend", "compiled", "-q",
                           "-o", str(tmp_path / "out")], capture_output=True, text=True,
                          env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "Warning" not in done.stderr and "\x1b[" not in done.stderr, done.stderr
