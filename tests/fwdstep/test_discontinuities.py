"""Exact discontinuities on a fixed step (fwdstep.run.events).

A source that jumps at T declares T; the run ends a step exactly at T, evaluates every stage
of that step before the jump and every stage of the next one after it.  Integrals of
piecewise-constant inputs are then exact for any explicit Runge-Kutta method (each piece is
a polynomial of degree 0), whether T is on the step grid or not, and a piecewise-smooth
problem keeps the method's full order.  Before this, the integral of a unit Step at 0.3
over [0, 1] with RK4, h = 0.1, was 0.7167 (issue 11).
"""
import math

import numpy as np
import pytest

import fwdstep
from fwdstep.run.events import SNAP, plan_events


def _run(tmp_path, text, name="d.yaml", **overrides):
    path = tmp_path / name
    path.write_text(text)
    return fwdstep.simulate(fwdstep.load_diagram(str(path), overrides=overrides or None))


INTEGRAL = """
blocks:
  src: {{type: {kind}, {params}}}
  i:   {{type: Integrator}}
connections:
  - src.y -> i.u
simulation: {{t_final: 1.0, step: 0.1, solver: {solver}}}
"""


@pytest.mark.parametrize("solver", ["rk4", "heun", "euler"])
@pytest.mark.parametrize("time, exact", [(0.3, 0.7), (0.35, 0.65), (0.0, 1.0), (1.0, 0.0),
                                         (0.1 + 0.2, 0.7), (0.7 + 1e-13, 0.3 - 1e-13)])
def test_step_integral_is_exact_on_and_off_the_grid(tmp_path, solver, time, exact):
    r = _run(tmp_path, INTEGRAL.format(kind="Step", params=f"after: 1.0, time: {time!r}",
                                       solver=solver))
    assert abs(r["i.y"][-1] - exact) < 1e-12


@pytest.mark.parametrize("delay, width, period", [(0.1, 0.2, 0.5), (0.05, 0.13, 0.31),
                                                  (0.0, 0.01, 0.1), (0.33, 0.07, 0.2)])
def test_pulse_integral_is_exact(tmp_path, delay, width, period):
    r = _run(tmp_path, INTEGRAL.format(
        kind="Pulse", params=f"high: 2.0, low: -1.0, period: {period}, width: {width}, "
                             f"delay: {delay}", solver="rk4"))
    # exact: the measure of the 'on' set in [0, 1]
    on = sum(max(0.0, min(1.0, delay + k * period + width) - (delay + k * period))
             for k in range(int(1.0 / period) + 2) if delay + k * period < 1.0)
    exact = 2.0 * on - 1.0 * (1.0 - on)
    assert abs(r["i.y"][-1] - exact) < 1e-12


def test_piecewise_constant_integral_and_values(tmp_path):
    r = _run(tmp_path, INTEGRAL.format(
        kind="PiecewiseConstant", params="times: [0.25, 0.3, 0.77], values: [1, -2, 4, 0.5]",
        solver="rk4"))
    exact = 0.25 * 1 + 0.05 * -2 + 0.47 * 4 + 0.23 * 0.5
    assert abs(r["i.y"][-1] - exact) < 1e-12
    np.testing.assert_array_equal(r["src.y"], np.where(
        r.t < 0.25, 1.0, np.where(r.t < 0.3, -2.0, np.where(r.t < 0.77, 4.0, 0.5))))


def test_batches_stay_exact_across_step_times(tmp_path):
    """Variants whose steps jump at the same time batch (and equal their single runs bit for
    bit); variants that jump at different times never share a batch, whose steps would be
    split at every variant's times (fwdstep.sweeps.sweep: batches are exact)."""
    path = tmp_path / "d.yaml"
    path.write_text(INTEGRAL.format(kind="Step", params="after: A, time: T", solver="rk4")
                    .replace("blocks:", "parameters: {T: 0.3, A: 1.0}\nblocks:")
                    .replace("type: Integrator", "type: TransferFunction, num: [1], den: [1, 1]"))
    specs = [fwdstep.structure.spec.load_spec(str(path), {"T": 0.35, "A": A}) for A in (1.0, -2.0, 0.5)]
    batch = fwdstep.simulate(fwdstep.compile_batch(specs))
    for k, A in enumerate((1.0, -2.0, 0.5)):
        single = fwdstep.simulate(fwdstep.load_diagram(str(path), {"T": 0.35, "A": A}))
        np.testing.assert_array_equal(batch["i.y"][:, k], single["i.y"])
    specs = [fwdstep.structure.spec.load_spec(str(path), {"T": T}) for T in (0.3, 0.35)]
    with pytest.raises(fwdstep.ConfigError, match="differ in structure"):
        fwdstep.compile_batch(specs)


ORDER = """
blocks:
  u:   {{type: Step, after: 1.0, time: {T!r}}}
  w:   {{type: Sine, amplitude: 1.0, frequency: 0.5}}
  s:   {{type: Sum, signs: "++"}}
  sys: {{type: TransferFunction, num: [1], den: [1, 1], initial: 0.5}}
connections:
  - u.y -> s.u1
  - w.y -> s.u2
  - s.y -> sys.u
simulation: {{t_final: 2.0, step: {h!r}, solver: {solver}}}
"""


def _exact_order_problem(t, T):
    """x' = -x + H(t - T) + sin(t / 2), x(0) = 0.5."""
    w = 0.5
    forced = (math.sin(w * t) - w * math.cos(w * t) + w * math.exp(-t)) / (1 + w * w)
    step = 1 - math.exp(-(t - T)) if t >= T else 0.0
    return 0.5 * math.exp(-t) + forced + step


@pytest.mark.parametrize("solver, order", [("rk4", 4), ("heun", 2), ("euler", 1)])
def test_piecewise_smooth_problem_keeps_the_method_order(tmp_path, solver, order):
    """The jump at T = 1/3 is off the grid for every step; the fitted slope of log(error)
    against log(h) is the method's order (it was 1 for every method)."""
    T = 1.0 / 3.0
    steps = [0.1, 0.05, 0.025, 0.0125]
    errors = []
    for h in steps:
        r = _run(tmp_path, ORDER.format(T=T, h=h, solver=solver))
        errors.append(abs(r["sys.y"][-1] - _exact_order_problem(2.0, T)))
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - order) < 0.15, (slope, errors)


def test_stage_times_are_on_the_correct_side(tmp_path):
    """A step that ends at the jump sees only the left value, the next step only the right
    one: with Euler-free RK4 stages that is visible in the recorded output too."""
    r = _run(tmp_path, INTEGRAL.format(kind="Step", params="after: 1.0, time: 0.3",
                                       solver="rk4"))
    np.testing.assert_array_equal(r["src.y"], (r.t >= 0.3 - 1e-12).astype(float))
    np.testing.assert_allclose(r["i.y"], np.maximum(r.t - 0.3, 0.0), atol=1e-15)


def test_events_are_merged_and_snapped_to_the_grid(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text(INTEGRAL.format(kind="PiecewiseConstant",
                                    params="times: [0.3, 0.35, 0.9999999999999], "
                                           "values: [0, 1, 2, 3]", solver="rk4"))
    d = fwdstep.load_diagram(str(path))
    plan = plan_events(d, 0.1, 10)
    # 0.3 = 3 h up to rounding: steps 2 (ends there) and 3 (starts there) are touched
    assert plan.steps[2][-1].hi < 0.3 <= plan.steps[3][0].lo
    # 0.35 splits step 3 in two
    assert [(s.a, s.b) for s in plan.steps[3]] == [(0.30000000000000004, 0.35),
                                                   (0.35, 0.4)]
    # 1 - 1e-13 is within SNAP h of t_final: it happens at t_final
    assert abs(1.0 - 0.9999999999999) < SNAP * 0.1 and plan.final is not None


@pytest.mark.parametrize("times", [[0.1, 0.3, 0.7], [0.05, 0.333, 0.71, 0.9]])
def test_piecewise_linear_integral_is_exact_and_values_interpolate(tmp_path, times):
    """A ramp's kinks are declared: RK4 integrates each linear piece exactly, on the grid
    or off it (without the kinks declared the error is O(h^2) per kink)."""
    values = [0.5, -1.0, 2.0, 0.25][:len(times)]
    r = _run(tmp_path, INTEGRAL.format(kind="PiecewiseLinear",
                                       params=f"times: {times}, values: {values}",
                                       solver="rk4"))
    knots = np.array([0.0] + times + [1.0])
    level = np.interp(knots, times, values)
    exact = np.sum((level[1:] + level[:-1]) / 2 * np.diff(knots))   # the trapezoids are exact
    assert abs(r["i.y"][-1] - exact) < 1e-12
    np.testing.assert_allclose(r["src.y"], np.interp(r.t, times, values), rtol=0, atol=1e-15)
