"""Every block whose regime changes at a level declares its guards (issue 26), so a loop
through it keeps RK4's order 4: the fitted order of the largest error on the grid over
h = 0.2, 0.1, 0.05 is >= 3.5, against the piecewise closed-form solution of each loop
(integrated through the kink, the order drops to about 2).
"""
import math

import numpy as np
import pytest

import fwdstep

HS = (0.2, 0.1, 0.05)


def _order(tmp_path, text, exact, signal):
    """The fitted order, the errors and the events of the runs at HS."""
    errors, events = [], None
    for h in HS:
        path = tmp_path / "d.yaml"
        path.write_text(text.replace("STEP", repr(h)))
        r = fwdstep.simulate(fwdstep.load_diagram(str(path)))
        assert r.status == "ok"
        y = np.asarray(r[signal]).reshape(len(r.t))
        errors.append(np.abs(y - exact(r.t)).max())
        events = [(e.block, e.kind) for e in r.events]
    return np.polyfit(np.log(HS), np.log(errors), 1)[0], errors, events


def _piecewise(t, pieces):
    """pieces: [(t_start, f)] in time order; f of the time since t_start."""
    out = np.empty_like(t)
    for k, (t0, f) in enumerate(pieces):
        t1 = pieces[k + 1][0] if k + 1 < len(pieces) else math.inf
        m = (t >= t0) & (t < t1)
        out[m] = f(t[m] - t0)
    return out


DEAD_ZONE = """
blocks:
  dz:  {type: DeadZone, lower: -1.0, upper: 1.0}
  one: {type: Constant, value: 1.0}
  s:   {type: Sum, signs: "--"}
  x:   {type: Integrator, initial: 3.0}
connections:
  - x.y -> dz.u
  - dz.y -> s.u1
  - one.y -> s.u2
  - s.y -> x.u
simulation: {t_final: 5.0, step: STEP, solver: rk4}
"""


def _dead_zone(t):
    """x' = -dz(x) - 1: 3 e^-t above 1 (to ln 3), 1 - s inside (2 s), -2 + e^-s below."""
    t1 = math.log(3.0)
    return _piecewise(t, [(0.0, lambda s: 3 * np.exp(-s)), (t1, lambda s: 1 - s),
                          (t1 + 2, lambda s: -2 + np.exp(-s))])


SWITCH = """
blocks:
  sw:  {type: Switch, threshold: 0.5}
  m1:  {type: Constant, value: -1.0}
  neg: {type: Gain, gain: -1.0}
  x:   {type: Integrator, initial: 2.0}
connections:
  - m1.y -> sw.u1
  - x.y -> sw.control
  - x.y -> neg.u
  - neg.y -> sw.u2
  - sw.y -> x.u
simulation: {t_final: 4.0, step: STEP, solver: rk4}
"""


def _switch(t):
    """x' = -1 while x >= 0.5 (to t = 1.5), then x' = -x."""
    return _piecewise(t, [(0.0, lambda s: 2 - s), (1.5, lambda s: 0.5 * np.exp(-s))])


RATE = """
blocks:
  u:  {type: Constant, value: 1.0}
  rl: {type: RateLimiter, rising: 0.5, time_constant: 0.5}
connections:
  - u.y -> rl.u
simulation: {t_final: 4.0, step: STEP, solver: rk4}
"""


def _rate(t):
    """y' = min(2 (1 - y), 0.5): the ramp 0.5 t up to y = 0.75 (t = 1.5), then the lag."""
    return _piecewise(t, [(0.0, lambda s: 0.5 * s), (1.5, lambda s: 1 - 0.25 * np.exp(-2 * s))])


LOOKUP = """
blocks:
  L:   {type: Lookup1D, breakpoints: [0.0, 1.0, 3.0], values: [0.0, 1.0, 1.5]}
  neg: {type: Gain, gain: -1.0, shape: [1]}
  x:   {type: Integrator, initial: [2.9]}
connections:
  - x.y -> L.u
  - L.y -> neg.u
  - neg.y -> x.u
simulation: {t_final: 4.0, step: STEP, solver: rk4}
"""


def _lookup(t):
    """x' = -(0.75 + 0.25 x) above 1: x = 5.9 e^(-t/4) - 3 (to 4 ln(5.9 / 4)), then
    x' = -x."""
    t1 = 4 * math.log(5.9 / 4)
    return _piecewise(t, [(0.0, lambda s: 5.9 * np.exp(-s / 4) - 3), (t1, lambda s: np.exp(-s))])


FRICTION = """
blocks:
  f:   {type: Friction, n: 1, coulomb: 1.0, viscous: 1.0}
  push: {type: Constant, value: [-2.0]}
  s:   {type: Sum, signs: "++", shape: [1]}
  v:   {type: Integrator, initial: [2.0]}
connections:
  - v.y -> f.qdot
  - f.tau_f -> s.u1
  - push.y -> s.u2
  - s.y -> v.u
simulation: {t_final: 3.0, step: STEP, solver: rk4}
"""


def _friction(t):
    """v' = -sign(v) - v - 2: 5 e^-t - 3 while v > 0 (to ln(5/3)), then e^-s - 1."""
    t1 = math.log(5 / 3)
    return _piecewise(t, [(0.0, lambda s: 5 * np.exp(-s) - 3), (t1, lambda s: np.exp(-s) - 1)])


CLIP = """
blocks:
  lim: {type: Constant, value: 1.0}
  c:   {type: Clip}
  neg: {type: Gain, gain: -1.0}
  x:   {type: Integrator, initial: 3.37}
connections:
  - x.y -> c.u
  - lim.y -> c.limit
  - c.y -> neg.u
  - neg.y -> x.u
simulation: {t_final: 5.0, step: STEP, solver: rk4}
"""


def _clip(t):
    """x' = -clip(x, -1, 1): 3.37 - t up to t = 2.37, then e^-(t - 2.37)."""
    return _piecewise(t, [(0.0, lambda s: 3.37 - s), (2.37, lambda s: np.exp(-s))])


RELAY = """
blocks:
  r:   {type: Relay, on_threshold: 0.5, off_threshold: 0.2, on_value: 0.0, off_value: 1.0}
  s:   {type: Sum, signs: "+-"}
  x:   {type: Integrator}
connections:
  - x.y -> r.u
  - r.y -> s.u1
  - x.y -> s.u2
  - s.y -> x.u
simulation: {t_final: 5.0, step: STEP, solver: rk4}
"""


def _relay(t):
    """x' = relay - x: off (1) rises 1 - (1 - x0) e^-s to 0.5, on (0) decays to 0.2."""
    pieces, t0, x0, on = [], 0.0, 0.0, False
    while t0 < 6.0:
        if on:
            pieces.append((t0, lambda s, x0=x0: x0 * np.exp(-s)))
            t0, x0 = t0 + math.log(x0 / 0.2), 0.2
        else:
            pieces.append((t0, lambda s, x0=x0: 1 - (1 - x0) * np.exp(-s)))
            t0, x0 = t0 + math.log((1 - x0) / 0.5), 0.5
        on = not on
    return _piecewise(t, pieces)


@pytest.mark.parametrize("text, exact, signal, first", [
    (DEAD_ZONE, _dead_zone, "x.y", ("dz", "upper falling")),
    (SWITCH, _switch, "x.y", ("sw", "control falling")),
    (RATE, _rate, "rl.y", ("rl", "rising falling")),
    (LOOKUP, _lookup, "x.y", ("L", "b1 falling")),
    (FRICTION, _friction, "v.y", ("f", "qdot falling")),
    (CLIP, _clip, "x.y", ("c", "upper falling")),
    (RELAY, _relay, "x.y", ("r", "switch rising")),
], ids=["DeadZone", "Switch", "RateLimiter", "Lookup1D", "Friction", "Clip", "Relay"])
def test_rk4_keeps_its_order_through_the_block(tmp_path, text, exact, signal, first):
    order, errors, events = _order(tmp_path, text, exact, signal)
    assert events[0] == first
    assert order >= 3.5, (order, errors)
