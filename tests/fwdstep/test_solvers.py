"""Each fixed-step method shows its documented order of accuracy.

Problem with a known solution: the harmonic oscillator x'' = -w^2 x built from two
Integrators and a Gain (x(t) = cos(w t)), run through the full engine.  The slope of
log(error) against log(step) must match the tableau's order.
"""
import numpy as np
import pytest

import fwdstep
from fwdstep.core.solvers import TABLEAUX, integrate_ode
from fwdstep.structure.spec import load_spec

OSCILLATOR = """
parameters:
  w: 2
blocks:
  pos: {type: Integrator, shape: [1], initial: [1.0]}
  vel: {type: Integrator, shape: [1], initial: [0.0]}
  k: {type: Gain, gain: -w**2, shape: [1]}
connections:
  - pos.y -> k.u
  - k.y -> vel.u
  - vel.y -> pos.u
simulation: {t_final: 2, step: 0.01, solver: rk4}
log: [pos.y]
"""


def _final_error(path, solver, step):
    spec = load_spec(str(path))
    spec.simulation.solver = solver
    spec.simulation.step = step
    d = fwdstep.structure.compiler.compile_spec(spec)
    r = fwdstep.simulate(d)
    return abs(r["pos.y"][-1, 0] - np.cos(2.0 * r.t[-1]))


@pytest.mark.parametrize("solver", ["euler", "heun", "rk4"])
def test_order_of_accuracy(tmp_path, solver):
    path = tmp_path / "osc.yaml"
    path.write_text(OSCILLATOR)
    steps = np.array([0.02, 0.01, 0.005, 0.0025])
    errors = np.array([_final_error(path, solver, h) for h in steps])
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    order = TABLEAUX[solver].order
    assert abs(slope - order) < 0.15, (solver, slope, errors)


def test_tableaux_are_consistent():
    for tab in TABLEAUX.values():
        tab.check()


def test_integrate_ode_matches_exponential():
    x = integrate_ode(lambda t, x: -x, [1.0], 1.0, 0.01, "rk4")
    assert abs(x[0] - np.exp(-1.0)) < 1e-9


def test_logging_every_n_steps_keeps_exact_times(tmp_path):
    path = tmp_path / "osc.yaml"
    path.write_text(OSCILLATOR.replace("solver: rk4}", "solver: rk4, log_every: 7}"))
    r = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    # rows at steps 0, 7, 14, ..., 196 and the final time 2.0
    assert np.allclose(r.t[:-1], np.arange(0, 200, 7) * 0.01)
    assert r.t[-1] == pytest.approx(2.0)
    assert np.allclose(r["pos.y"][:, 0], np.cos(2 * r.t), atol=1e-7)
