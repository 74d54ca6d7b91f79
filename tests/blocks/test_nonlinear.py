"""Nonlinear blocks against analytic cases: Saturation, DeadZone, RateLimiter (closed-form ramp
then exponential), Friction, Switch, Lookup1D (against numpy.interp), batching, and errors."""
import math

import numpy as np
import pytest

import fwdstep
from fwdstep.blocks.nonlinear import DeadZone, Friction, Lookup1D, RateLimiter, Saturation, Switch
from fwdstep.structure.compiler import stack_blocks
from fwdstep.core.errors import ParameterError

NO_STATE = np.zeros((1, 0))


def test_saturation_clips_each_element_to_its_own_limits():
    blk = Saturation("s", lower=[-1.0, -2.0, 0.0], upper=[1.0, 0.5, 3.0])
    u = np.array([[-5.0, 0.2, 4.0], [0.3, -7.0, -1.0]])
    (y,) = blk.output(0.0, NO_STATE, (u,))
    np.testing.assert_array_equal(y, [[-1.0, 0.2, 3.0], [0.3, -2.0, 0.0]])
    assert blk.feedthrough("y") == ("u",)


def test_saturation_one_sided_and_scalar_limits():
    upper_only = Saturation("s", upper=2.0, shape=[3])
    (y,) = upper_only.output(0.0, NO_STATE, (np.array([[-100.0, 1.0, 5.0]]),))
    np.testing.assert_array_equal(y, [[-100.0, 1.0, 2.0]])
    scalar = Saturation("s", lower=-1.0, upper=1.0)
    assert scalar.inputs["u"].shape == ()
    (y,) = scalar.output(0.0, NO_STATE, (np.array([3.0, -0.25, -4.0]),))
    np.testing.assert_array_equal(y, [1.0, -0.25, -1.0])


def test_dead_zone_is_the_input_minus_its_saturation():
    blk = DeadZone("d", lower=-0.5, upper=[0.5, 1.0])
    u = np.array([[2.0, 2.0], [0.1, 0.9], [-3.0, -0.4], [-0.5, 1.0]])
    (y,) = blk.output(0.0, NO_STATE, (u,))
    expected = [[1.5, 1.0], [0.0, 0.0], [-2.5, 0.0], [0.0, 0.0]]
    np.testing.assert_array_equal(y, expected)


@pytest.mark.parametrize("cls,kw", [(Saturation, {"lower": 1.0, "upper": -1.0}),
                                     (DeadZone, {"lower": [0.0, 2.0], "upper": 1.0})])
def test_crossed_limits_are_refused(cls, kw):
    with pytest.raises(ParameterError, match="'lower' must not exceed 'upper'"):
        cls("b", **kw)


def test_saturation_needs_a_limit_and_limits_must_fit_the_shape():
    with pytest.raises(ParameterError, match="needs 'lower', 'upper' or both"):
        Saturation("s")
    with pytest.raises(ParameterError, match="does not broadcast to the signal shape"):
        Saturation("s", lower=[-1.0, -1.0, -1.0], shape=[2])


def _rate_limiter_run(tmp_path, T, rising, falling, t_final, step):
    path = tmp_path / "rl.yaml"
    path.write_text(f"""
description: rate limiter driven by a unit step up at 0 and down at {t_final / 2}
blocks:
  up:   {{type: Step, after: 1.0, time: 0.0}}
  down: {{type: Step, after: -1.0, time: {t_final / 2}}}
  u:    {{type: Sum, signs: "++"}}
  rl:   {{type: RateLimiter, rising: {rising}, falling: {falling}, time_constant: {T}}}
connections:
  - up.y -> u.u1
  - down.y -> u.u2
  - u.y -> rl.u
simulation: {{t_final: {t_final}, step: {step}, solver: rk4}}
log: [rl.y]
""")
    r = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    assert r.status == "ok"
    return r.t, r["rl.y"]


def test_rate_limiter_ramps_at_the_rate_then_converges_exponentially(tmp_path):
    """u = 1 on [0, 2): x' = min(R, (1 - x)/T) from 0 gives x = R t until t1 = (1 - R T)/R,
    then x = 1 - R T exp(-(t - t1)/T).  From t = 2 u = 0: x falls at exactly the falling
    rate F while x > F T, and on the ramps RK4 is exact."""
    T, R, F = 0.05, 2.0, 4.0
    t, y = _rate_limiter_run(tmp_path, T, R, F, t_final=4.0, step=0.001)
    t1 = (1.0 - R * T) / R
    rising = np.where(t <= t1, R * t, 1.0 - R * T * np.exp(-(t - t1) / T))
    first = t <= 2.0
    np.testing.assert_allclose(y[first], rising[first], atol=2e-6)
    # falling ramp from the value at t = 2 (the exponential phase is not quite over)
    y2 = 1.0 - R * T * math.exp(-(2.0 - t1) / T)
    t2 = 2.0 + (y2 - F * T) / F
    ramp = (t >= 2.0) & (t <= t2)
    np.testing.assert_allclose(y[ramp], y2 - F * (t[ramp] - 2.0), atol=2e-6)
    assert y[-1] == pytest.approx(0.0, abs=1e-9)


def test_rate_limiter_refuses_non_positive_rates_and_time_constant():
    with pytest.raises(ParameterError, match="'rising' and 'falling' must be positive"):
        RateLimiter("r", rising=[1.0, 0.0])
    with pytest.raises(ParameterError, match="'time_constant' must be positive"):
        RateLimiter("r", rising=1.0, time_constant=0.0)


def test_friction_coulomb_plus_viscous_opposes_the_velocity():
    blk = Friction("f", n=3, coulomb=[0.5, 0.3, 0.0], viscous=[0.2, 0.0, 1.5])
    qdot = np.array([[2.0, -1.0, -0.5], [0.0, 1e-9, 3.0]])
    (tau,) = blk.output(0.0, np.zeros((2, 3)), (qdot,))    # no sign held: sign(qdot)
    expected = -(np.array([0.5, 0.3, 0.0]) * np.sign(qdot) + np.array([0.2, 0.0, 1.5]) * qdot)
    np.testing.assert_array_equal(tau, expected)
    assert tau[1, 0] == 0.0        # sign(0) = 0: no Coulomb torque at rest


def test_smoothed_friction_is_tanh_and_tends_to_sign():
    qdot = np.array([[0.05, -0.2, 3.0]])
    smooth = Friction("f", n=3, coulomb=1.0, velocity_scale=0.1)
    (tau,) = smooth.output(0.0, np.zeros((1, 3)), (qdot,))
    np.testing.assert_allclose(tau, -np.tanh(qdot / 0.1), rtol=1e-15)
    sharp = Friction("f", n=3, coulomb=1.0, velocity_scale=1e-9)
    (tau,) = sharp.output(0.0, np.zeros((1, 3)), (qdot,))
    np.testing.assert_allclose(tau, -np.sign(qdot), rtol=1e-12)


def test_friction_stops_a_sliding_mass_in_the_analytic_time(tmp_path):
    """m qddot = -F_c sign(qdot) - F_v qdot from qdot0 = v0 > 0: qdot(t) = (v0 + c) e^{-a t} - c,
    a = F_v/m, c = F_c/F_v, until it stops at t* = ln(1 + v0/c)/a."""
    m, fc, fv, v0 = 2.0, 1.0, 0.5, 3.0
    path = tmp_path / "slide.yaml"
    path.write_text(f"""
description: a point mass sliding with Coulomb + viscous friction
blocks:
  mass: {{type: PointMass, mass: {m}, n: 1, qdot0: {v0}}}
  fr:   {{type: Friction, n: 1, coulomb: {fc}, viscous: {fv}}}
  zero: {{type: Constant, value: [0.0]}}
connections:
  - mass.qdot -> fr.qdot
  - fr.tau_f -> mass.tau_star
  - zero.y -> mass.tau
simulation: {{t_final: 1.5, step: 0.001, solver: rk4}}
log: [mass.qdot]
""")
    r = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    a, c = fv / m, fc / fv
    t_stop = math.log(1 + v0 / c) / a
    assert t_stop > 1.5
    np.testing.assert_allclose(r["mass.qdot"][:, 0], (v0 + c) * np.exp(-a * r.t) - c,
                               atol=1e-10)


def test_switch_scalar_control_picks_the_whole_signal():
    blk = Switch("s", threshold=0.5, shape=[2])
    u1 = np.array([[1.0, 2.0], [1.0, 2.0], [1.0, 2.0]])
    u2 = -u1
    control = np.array([0.5, 0.49, 7.0])
    (y,) = blk.output(0.0, blk.initial_state(0.0, (u1, control, u2)), (u1, control, u2))
    np.testing.assert_array_equal(y, [[1.0, 2.0], [-1.0, -2.0], [1.0, 2.0]])


def test_switch_per_element_control():
    blk = Switch("s", shape=[3], per_element=True)
    assert blk.inputs["control"].shape == (3,)
    u = (np.ones((1, 3)), np.array([[1.0, -1.0, 0.0]]), np.zeros((1, 3)))
    (y,) = blk.output(0.0, blk.initial_state(0.0, u), u)
    np.testing.assert_array_equal(y, [[1.0, 0.0, 1.0]])


def test_lookup_interpolates_like_numpy_interp_and_clamps():
    bp, v = [0.0, 1.0, 3.0, 3.5], [0.0, 2.0, 1.0, 4.0]
    blk = Lookup1D("l", breakpoints=bp, values=v, n=5)
    u = np.random.default_rng(1).uniform(-2.0, 6.0, (4, 5))
    u[0, :4] = bp                                       # exactly at the breakpoints
    (y,) = blk.output(0.0, NO_STATE, (u,))
    np.testing.assert_allclose(y, np.interp(u, bp, v), rtol=0, atol=1e-15)


def test_lookup_linear_extrapolation_extends_the_end_segments():
    blk = Lookup1D("l", breakpoints=[0.0, 1.0, 2.0], values=[1.0, 3.0, 2.0],
                   extrapolation="linear", n=2)
    (y,) = blk.output(0.0, NO_STATE, (np.array([[-1.0, 4.0]]),))
    np.testing.assert_allclose(y, [[-1.0, 0.0]], atol=1e-15)  # 1 + 2*(-1); 2 - 1*(4 - 2)


def test_lookup_refuses_bad_tables():
    with pytest.raises(ParameterError, match="at least 2 strictly increasing numbers"):
        Lookup1D("l", breakpoints=[0.0, 0.0, 1.0], values=[1.0, 2.0, 3.0])
    with pytest.raises(ParameterError, match="one value per breakpoint"):
        Lookup1D("l", breakpoints=[0.0, 1.0], values=[1.0, 2.0, 3.0])


def test_batched_limits_and_tables_match_single_variants():
    cases = [
        (Saturation, [{"lower": -1.0, "upper": 1.0, "shape": [2]},
                      {"lower": -0.2, "upper": 0.3, "shape": [2]}], (2,)),
        (Lookup1D, [{"breakpoints": [0.0, 1.0], "values": [0.0, 1.0], "n": 2},
                    {"breakpoints": [-1.0, 2.0], "values": [5.0, -1.0], "n": 2}], (2,)),
        (Friction, [{"n": 2, "coulomb": 0.5, "velocity_scale": 0.0},
                    {"n": 2, "coulomb": 0.5, "velocity_scale": 0.1}], (2,)),
    ]
    rng = np.random.default_rng(4)
    for cls, variants, shape in cases:
        singles = [cls("b", **v) for v in variants]
        big = stack_blocks([[cls("b", **v)] for v in variants])[0]
        u = rng.standard_normal((len(variants),) + shape)
        x = np.zeros((len(variants), big.n_states))     # (Friction: no sign held)
        (yb,) = big.output(0.0, x, (u,))
        for i, single in enumerate(singles):
            (ys,) = single.output(0.0, x[i:i + 1], (u[i:i + 1],))
            np.testing.assert_array_equal(yb[i], ys[0])
