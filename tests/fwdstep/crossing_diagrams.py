"""Small diagrams with state events, shared by the tests of the three paths that locate
zero crossings (tests/fwdstep/test_crossings.py: the fixed-step NumPy path,
test_compiled_crossings.py: the compiled backend, test_ivp_events.py: solve_ivp)."""

#: a bouncing ball: a limited integrator (velocity) reset by the position's crossing of 0,
#: restitution 0.8, dropped from 10 m
BALL = """
blocks:
  g:    {type: Constant, value: -9.81}
  v:    {type: LimitedIntegrator, initial: 0.0}
  p:    {type: Integrator, initial: 10.0}
  neg:  {type: Gain, gain: -1.0}
  rest: {type: Gain, gain: -0.8}
connections:
  - g.y -> v.u
  - v.y -> p.u
  - p.y -> neg.u
  - neg.y -> v.reset
  - v.y -> rest.u
  - rest.y -> v.value
simulation: {t_final: 13.0, step: 0.01, solver: rk4}
"""

#: x' = -relay(x) with hysteresis +-1: switches at t = 1, 3, 5, 7
RELAY = """
blocks:
  relay: {type: Relay, on_threshold: 1.0, off_threshold: -1.0, on_value: -1.0,
          off_value: 1.0}
  x:     {type: Integrator}
connections:
  - x.y -> relay.u
  - relay.y -> x.u
simulation: {t_final: 8.1, step: 0.3, solver: rk4}
"""

#: x' = -1 from 1.234, stopped when x crosses 0 (t = 1.234)
STOP = """
blocks:
  one:  {type: Constant, value: -1.0}
  x:    {type: Integrator, initial: 1.234}
  stop: {type: Stop}
connections:
  - one.y -> x.u
  - x.y -> stop.u
simulation: {t_final: 5.0, step: 0.1, solver: rk4}
"""

#: x' = -sign(x) (a relay without hysteresis): slides on x = 0 from t = 0.5
CHATTER = """
blocks:
  relay: {type: Relay, on_threshold: 0.0, off_threshold: 0.0, on_value: -1.0,
          off_value: 1.0}
  x:     {type: Integrator, initial: 0.5}
connections:
  - x.y -> relay.u
  - relay.y -> x.u
simulation: {t_final: 2.0, step: 0.01, solver: rk4}
"""
