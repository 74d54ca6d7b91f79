"""Robot plants and regressors against independent references (eq. (1), Properties 1-3)."""
from __future__ import annotations

import copy
import math
from types import SimpleNamespace

import numpy as np
import pytest

from fwdstep.blocks.robot import (NLinkArm, NLinkRegressor, PointMass, PointMassRegressor, Regressor,
                          TwoLinkArm)
from fwdstep.core.errors import ParameterError

SLOTINE_LI = dict(m1=1.0, l1=1.0, me=2.0, delta_e=30.0, I1=0.12, lc1=0.5, Ie=0.25, lce=0.6)
OTHER_ARM = dict(m1=1.5, l1=0.8, me=1.2, delta_e=-20.0, I1=0.05, lc1=0.3, Ie=0.1, lce=0.4)


# --------------------------------------------------------------------------- references
def reference_terms(prm: dict, gravity: float, q, qdot):
    """H, C, g of the two-link arm written directly from the physical parameters
    (Slotine & Li, Example 9.2), independently of blocks.robot."""
    m1, l1, me, I1, lc1, Ie, lce = (prm[k] for k in ("m1", "l1", "me", "I1", "lc1", "Ie", "lce"))
    de = math.radians(prm["delta_e"])
    a1 = I1 + m1 * lc1 ** 2 + Ie + me * lce ** 2 + me * l1 ** 2
    a2 = Ie + me * lce ** 2
    a3 = me * l1 * lce * math.cos(de)
    a4 = me * l1 * lce * math.sin(de)
    c2, s2 = math.cos(q[1]), math.sin(q[1])
    H = np.array([[a1 + 2 * a3 * c2 + 2 * a4 * s2, a2 + a3 * c2 + a4 * s2],
                  [a2 + a3 * c2 + a4 * s2, a2]])
    hh = a3 * s2 - a4 * c2
    C = np.array([[-hh * qdot[1], -hh * (qdot[0] + qdot[1])], [hh * qdot[0], 0.0]])
    ce = math.cos(q[0] + q[1] - de)
    g = np.array([(m1 * lc1 + me * l1) * gravity * math.cos(q[0]) + me * lce * gravity * ce,
                  me * lce * gravity * ce])
    dH_dq2 = np.array([[-2 * a3 * s2 + 2 * a4 * c2, -a3 * s2 + a4 * c2],
                       [-a3 * s2 + a4 * c2, 0.0]])
    return H, C, g, dH_dq2


def potential(prm: dict, gravity: float, q):
    de = math.radians(prm["delta_e"])
    return ((prm["m1"] * prm["lc1"] + prm["me"] * prm["l1"]) * gravity * np.sin(q[..., 0])
            + prm["me"] * prm["lce"] * gravity * np.sin(q[..., 0] + q[..., 1] - de))


def centres_of_mass(prm: dict, q):
    """Positions of the two centres of mass (link 2's at absolute angle q1 + q2 - delta_e,
    where Slotine & Li's H puts it), (2, 2) rows = bodies."""
    de = math.radians(prm["delta_e"])
    q12 = q[0] + q[1] - de
    return np.array([
        [prm["lc1"] * math.cos(q[0]), prm["lc1"] * math.sin(q[0])],
        [prm["l1"] * math.cos(q[0]) + prm["lce"] * math.cos(q12),
         prm["l1"] * math.sin(q[0]) + prm["lce"] * math.sin(q12)]])


def rk4(f, x0, dt, steps):
    x = np.array(x0, dtype=float)
    for k in range(steps):
        t = k * dt
        k1 = f(t, x)
        k2 = f(t + dt / 2, x + dt / 2 * k1)
        k3 = f(t + dt / 2, x + dt / 2 * k2)
        k4 = f(t + dt, x + dt * k3)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def stacked(blocks):
    """What a batched sweep does: stack every run-time parameter along the batch axis."""
    clone = copy.copy(blocks[0])
    clone.p = SimpleNamespace(**{k: np.concatenate([getattr(b.p, k) for b in blocks])
                                 for k in vars(blocks[0].p)})
    clone.finalize(len(blocks))
    return clone


def random_states(rng, count):
    q = rng.uniform(-math.pi, math.pi, (count, 2))
    qdot = rng.uniform(-3.0, 3.0, (count, 2))
    zeta = rng.uniform(-3.0, 3.0, (count, 2))
    zetad = rng.uniform(-10.0, 10.0, (count, 2))
    return q, qdot, zeta, zetad


# --------------------------------------------------------------------------- parameters
def test_parameter_vector_is_slotine_li():
    # Slotine & Li, Example 9.2: a1 = 3.34, a2 = 0.97, a3 = 1.04, a4 = 0.6
    theta = TwoLinkArm.parameter_vector()
    np.testing.assert_allclose(theta, [3.34, 0.97, 1.2 * math.cos(math.pi / 6), 0.6],
                               rtol=1e-14)
    g = 9.81
    theta_g = TwoLinkArm.parameter_vector(gravity=g)
    np.testing.assert_allclose(theta_g[4:], [2.5 * g, 1.2 * g * math.cos(math.pi / 6),
                                             1.2 * g * 0.5], rtol=1e-14)
    np.testing.assert_array_equal(theta_g[:4], theta)
    with pytest.raises(ParameterError, match="no parameter 'mass'"):
        TwoLinkArm.parameter_vector(mass=1.0)


@pytest.mark.parametrize("bad, message", [
    (dict(I1=0.0, Ie=0.0, lc1=0.0), "not positive definite"),
    (dict(me=-1.0), "'me' must be positive"),
    (dict(q0=[1.0, 2.0, 3.0]), "'q0'"),
])
def test_two_link_arm_rejects_bad_parameters(bad, message):
    with pytest.raises(ParameterError, match=message):
        TwoLinkArm("arm", **bad)


def test_two_link_arm_ports_and_initial_state():
    arm = TwoLinkArm("arm", q0=[0.3, -0.4], qdot0=1.5)
    np.testing.assert_array_equal(arm.x0, [[0.3, -0.4, 1.5, 1.5]])
    assert arm.inputs["tau_star"].optional and not arm.inputs["tau"].optional
    assert arm.feedthrough("q") == () and arm.feedthrough("qdot") == ()
    q, qdot = arm.output(0.0, arm.x0, (np.zeros((1, 2)), np.zeros((1, 2))))
    np.testing.assert_array_equal(q, [[0.3, -0.4]])
    np.testing.assert_array_equal(qdot, [[1.5, 1.5]])


# --------------------------------------------------------------------------- Properties 1-3
@pytest.mark.parametrize("prm", [SLOTINE_LI, OTHER_ARM])
def test_property1_inertia_symmetric_positive_definite(prm):
    lowest = []
    for q2 in np.linspace(-math.pi, math.pi, 361):
        H = reference_terms(prm, 0.0, [0.7, q2], [0.0, 0.0])[0]
        np.testing.assert_array_equal(H, H.T)
        lowest.append(np.linalg.eigvalsh(H)[0])
    assert min(lowest) > 0.05


@pytest.mark.parametrize("prm", [SLOTINE_LI, OTHER_ARM])
def test_model_is_the_rigid_two_link_arm(prm):
    """H, C qdot and g agree with Lagrange's equations for the two rigid bodies: kinetic
    energy sum_i (m_i |v_i|^2 + I_i omega_i^2) / 2 and potential g sum_i m_i y_i, from
    finite differences of the centre-of-mass positions (independent of the a1..a7 algebra)."""
    rng = np.random.default_rng(9)
    gravity, h = 9.81, 1e-6
    masses = np.array([prm["m1"], prm["me"]])
    for _ in range(20):
        q = rng.uniform(-math.pi, math.pi, 2)
        qdot = rng.uniform(-3.0, 3.0, 2)
        J = np.stack([(centres_of_mass(prm, q + h * e) - centres_of_mass(prm, q - h * e)) / (2 * h)
                      for e in np.eye(2)], axis=-1)            # (body, xy, joint)
        Jw = np.array([[1.0, 0.0], [1.0, 1.0]])              # body angular rates
        H_rigid = (sum(masses[i] * J[i].T @ J[i] for i in range(2))
                   + prm["I1"] * np.outer(Jw[0], Jw[0]) + prm["Ie"] * np.outer(Jw[1], Jw[1]))

        def potential_rigid(qq):
            return gravity * masses @ centres_of_mass(prm, qq)[:, 1]

        g_rigid = np.array([(potential_rigid(q + h * e) - potential_rigid(q - h * e)) / (2 * h)
                            for e in np.eye(2)])
        H, C, g, dH_dq2 = reference_terms(prm, gravity, q, qdot)
        np.testing.assert_allclose(H, H_rigid, rtol=0, atol=1e-8)
        np.testing.assert_allclose(g, g_rigid, rtol=0, atol=1e-7)
        # Lagrange: C qdot = Hdot qdot - d/dq (qdot^T H qdot / 2)
        dT_dq2 = 0.5 * qdot @ dH_dq2 @ qdot
        np.testing.assert_allclose(C @ qdot, dH_dq2 * qdot[1] @ qdot - [0.0, dT_dq2],
                                   rtol=0, atol=1e-12)
        # and the blocks agree with this reference (gravity column signs included)
        arm = TwoLinkArm("arm", **prm, gravity=gravity)
        dx = arm.derivative(0.0, np.hstack([q, qdot])[None], (np.zeros((1, 2)),) * 2)
        np.testing.assert_allclose(dx[0, 2:], np.linalg.solve(H_rigid, -C @ qdot - g_rigid),
                                   rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("prm", [SLOTINE_LI, OTHER_ARM])
def test_property2_hdot_minus_2c_skew_symmetric(prm):
    rng = np.random.default_rng(2)
    q, qdot, _, _ = random_states(rng, 100)
    h = 1e-5
    for k in range(100):
        H, C, _, dH_dq2 = reference_terms(prm, 0.0, q[k], qdot[k])
        Hdot = dH_dq2 * qdot[k, 1]
        H_plus = reference_terms(prm, 0.0, q[k] + h * qdot[k], qdot[k])[0]
        H_minus = reference_terms(prm, 0.0, q[k] - h * qdot[k], qdot[k])[0]
        np.testing.assert_allclose(Hdot, (H_plus - H_minus) / (2 * h), rtol=0, atol=1e-8)
        N = Hdot - 2 * C
        np.testing.assert_allclose(N + N.T, 0.0, rtol=0, atol=1e-12)


@pytest.mark.parametrize("gravity", [0.0, 9.81])
@pytest.mark.parametrize("prm", [SLOTINE_LI, OTHER_ARM])
def test_property3_regressor_times_theta_equals_dynamics(prm, gravity):
    rng = np.random.default_rng(3)
    q, qdot, zeta, zetad = random_states(rng, 100)
    reg = Regressor("Y", gravity=gravity)
    theta = TwoLinkArm.parameter_vector(**prm, gravity=gravity)
    assert reg.outputs["Y"].shape == (2, theta.size) == (2, 7 if gravity else 4)
    (Y,) = reg.output(0.0, None, (q, qdot, zeta, zetad))       # one batch of 100
    assert Y.shape == (100, 2, theta.size)
    for k in range(100):
        H, C, g, _ = reference_terms(prm, gravity, q[k], qdot[k])
        np.testing.assert_allclose(Y[k] @ theta, H @ zetad[k] + C @ zeta[k] + g,
                                   rtol=0, atol=1e-12)
        (Yk,) = reg.output(0.0, None, (q[k:k + 1], qdot[k:k + 1], zeta[k:k + 1],
                                       zetad[k:k + 1]))
        np.testing.assert_allclose(Yk[0], Y[k], rtol=1e-15, atol=1e-15)  # float fast path


def test_regressor_broadcasts_batch_one_inputs():
    rng = np.random.default_rng(4)
    q, qdot, zeta, zetad = random_states(rng, 5)
    reg = Regressor("Y", gravity=1.0)
    (Y,) = reg.output(0.0, None, (q[:1], qdot, zeta[:1], zetad))
    (Y_full,) = reg.output(0.0, None, (np.repeat(q[:1], 5, 0), qdot,
                                       np.repeat(zeta[:1], 5, 0), zetad))
    np.testing.assert_array_equal(Y, Y_full)


# --------------------------------------------------------------------------- eq. (1)
@pytest.mark.parametrize("gravity", [0.0, 9.81])
@pytest.mark.parametrize("prm", [SLOTINE_LI, OTHER_ARM])
def test_derivative_matches_linear_solve(prm, gravity):
    rng = np.random.default_rng(5)
    q, qdot, _, _ = random_states(rng, 100)
    tau = rng.normal(0.0, 10.0, (100, 2))
    tau_star = rng.normal(0.0, 3.0, (100, 2))
    arm = TwoLinkArm("arm", **prm, gravity=gravity)
    x = np.hstack([q, qdot])
    dx = arm.derivative(0.0, x, (tau, tau_star))
    assert dx.shape == (100, 4)
    np.testing.assert_array_equal(dx[:, :2], qdot)
    for k in range(100):
        H, C, g, _ = reference_terms(prm, gravity, q[k], qdot[k])
        qddot = np.linalg.solve(H, tau[k] + tau_star[k] - C @ qdot[k] - g)
        np.testing.assert_allclose(dx[k, 2:], qddot, rtol=1e-12, atol=1e-12)
        single = arm.derivative(0.0, x[k:k + 1], (tau[k:k + 1], tau_star[k:k + 1]))  # floats
        np.testing.assert_allclose(single[0, 2:], qddot, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(single[0], dx[k], rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("gravity", [0.0, 9.81])
def test_energy_conserved_without_torque(gravity):
    """tau = 0: d/dt (0.5 qdot^T H qdot + P(q)) = qdot^T (Hdot/2 - C) qdot = 0 (Property 2)."""
    prm = SLOTINE_LI
    arm = TwoLinkArm("arm", **prm, gravity=gravity)
    rng = np.random.default_rng(6)
    x0 = np.hstack([rng.uniform(-math.pi, math.pi, (8, 2)), rng.uniform(-2, 2, (8, 2))])
    zero = (np.zeros((1, 2)), np.zeros((1, 2)))

    def energy(x):
        e = np.empty(x.shape[0])
        for k in range(x.shape[0]):
            H = reference_terms(prm, gravity, x[k, :2], x[k, 2:])[0]
            e[k] = 0.5 * x[k, 2:] @ H @ x[k, 2:]
        return e + potential(prm, gravity, x[:, :2])

    drift = {}
    for dt in (2e-3, 1e-3):                                    # 2 s, 8 arms at once
        x = rk4(lambda t, x: arm.derivative(t, x, zero), x0, dt, round(2.0 / dt))
        assert np.max(np.abs(x[:, 2:] - x0[:, 2:])) > 0.1    # the arms really moved
        e0 = energy(x0)
        drift[dt] = np.max(np.abs(energy(x) - e0) / np.maximum(np.abs(e0), 1.0))
    # measured: 1.8e-12 (horizontal), 1.5e-8 (vertical) at dt = 1e-3, shrinking ~20x per
    # halving of dt: the only energy error is RK4's, so the model conserves energy exactly.
    assert drift[1e-3] < (1e-11 if gravity == 0.0 else 1e-7)
    assert drift[2e-3] / drift[1e-3] > 10.0


def test_batched_parameters_equal_separate_calls():
    rng = np.random.default_rng(7)
    arms = [TwoLinkArm("arm", **SLOTINE_LI), TwoLinkArm("arm", **OTHER_ARM, gravity=9.81),
            TwoLinkArm("arm", **SLOTINE_LI, gravity=-3.0)]
    batch = stacked(arms)
    x = rng.normal(size=(3, 4))
    tau = rng.normal(size=(3, 2))
    tau_star = rng.normal(size=(3, 2))
    dx = batch.derivative(0.0, x, (tau, tau_star))
    outs = batch.output(0.0, x, (tau, tau_star))
    for k, arm in enumerate(arms):
        u = (tau[k:k + 1], tau_star[k:k + 1])
        np.testing.assert_allclose(dx[k], arm.derivative(0.0, x[k:k + 1], u)[0],
                                   rtol=1e-14, atol=1e-15)
        for got, want in zip(outs, arm.output(0.0, x[k:k + 1], u)):
            np.testing.assert_array_equal(got[k], want[0])
    # an unbatched input (tau_star unconnected: zeros of batch 1) broadcasts
    dx0 = batch.derivative(0.0, x, (tau, np.zeros((1, 2))))
    for k, arm in enumerate(arms):
        np.testing.assert_allclose(
            dx0[k], arm.derivative(0.0, x[k:k + 1], (tau[k:k + 1], np.zeros((1, 2))))[0],
            rtol=1e-14, atol=1e-15)


# --------------------------------------------------------------------------- point masses
def test_point_mass_infers_axes_and_solves_constant_force():
    pm = PointMass("pm", mass=[1.0, 2.0, 4.0], q0=[1.0, 0.0, -1.0], qdot0=0.5)
    assert pm.n_states == 6 and pm.inputs["tau"].shape == (3,)
    assert pm.inputs["tau_star"].optional
    assert pm.feedthrough("q") == () and pm.feedthrough("qdot") == ()
    tau = np.array([[2.0, -2.0, 1.0]])
    tau_star = np.array([[0.0, 1.0, 3.0]])
    x = rk4(lambda t, x: pm.derivative(t, x, (tau, tau_star)), pm.x0, 0.01, 100)  # t = 1
    acc = (tau + tau_star)[0] / np.array([1.0, 2.0, 4.0])
    np.testing.assert_allclose(x[0, :3], np.array([1.0, 0.0, -1.0]) + 0.5 + 0.5 * acc,
                               rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(x[0, 3:], 0.5 + acc, rtol=1e-13, atol=1e-13)
    q, qdot = pm.output(1.0, x, (tau, tau_star))
    np.testing.assert_array_equal(np.hstack([q, qdot]), x)


def test_point_mass_shared_scalar_mass_and_batch():
    pms = [PointMass("pm", mass=2.0, n=2), PointMass("pm", mass=[1.0, 5.0])]
    batch = stacked(pms)
    x = np.arange(8.0).reshape(2, 4)
    tau = np.array([[1.0, 2.0], [3.0, 4.0]])
    dx = batch.derivative(0.0, x, (tau, np.zeros((1, 2))))
    np.testing.assert_array_equal(dx, [[2.0, 3.0, 0.5, 1.0], [6.0, 7.0, 3.0, 0.8]])
    np.testing.assert_array_equal(PointMass.parameter_vector(mass=2.0, n=2), [2.0, 2.0])
    with pytest.raises(ParameterError, match="'mass' must be positive"):
        PointMass("pm", mass=[1.0, 0.0])
    with pytest.raises(ParameterError, match="'mass'"):
        PointMass("pm", mass=[1.0, 2.0], n=3)


def test_point_mass_regressor_property3():
    rng = np.random.default_rng(8)
    masses = np.array([0.5, 2.0, 3.0])
    pm = PointMass("pm", mass=masses)
    reg = PointMassRegressor("Y", n=3)
    assert reg.feedthrough("Y") == ("zetad",)
    assert list(reg.inputs) == list(Regressor("Y2").inputs)
    zetad = rng.normal(size=(10, 3))
    zeros = np.zeros((1, 3))
    (Y,) = reg.output(0.0, None, (zeros, zeros, zeros, zetad))
    theta = PointMass.parameter_vector(mass=masses)
    np.testing.assert_allclose(np.einsum("bij,j->bi", Y, theta), zetad * masses, rtol=1e-15)
    # and the plant agrees: with tau = Y theta, qddot = zetad
    x = np.zeros((10, 6))
    dx = pm.derivative(0.0, x, (np.einsum("bij,j->bi", Y, theta), zeros))
    np.testing.assert_allclose(dx[:, 3:], zetad, rtol=1e-15)


# --------------------------------------------------------------------------- n-link arm
THREE_LINKS = dict(lengths=[1.0, 0.8, 0.5], masses=[2.0, 1.0, 0.5], com=[0.4, 0.5, 0.2],
                   com_angle=[0.0, 15.0, -40.0], inertias=[0.2, 0.05, 0.01])


def chain_reference(lengths, masses, com, com_angle, inertias, gravity, q, qdot):
    """H, the Jacobians' time derivative and g for a planar chain, with loops over links
    (Jv_i[:, k] = d(centre of mass i)/dq_k, k <= i); C = sum_i m_i Jv_i^T dJv_i/dt."""
    n = len(lengths)
    lengths, masses, com, inertias = (np.asarray(v, dtype=float)
                                      for v in (lengths, masses, com, inertias))
    gam = np.radians(com_angle)

    def jacobians(qq):
        phi = np.cumsum(qq)
        J = np.zeros((n, 2, n))
        for i in range(n):
            for k in range(i + 1):
                for j in range(k, i):
                    J[i, :, k] += lengths[j] * np.array([-math.sin(phi[j]), math.cos(phi[j])])
                J[i, :, k] += com[i] * np.array([-math.sin(phi[i] + gam[i]),
                                                 math.cos(phi[i] + gam[i])])
        return J

    def heights(qq):
        phi = np.cumsum(qq)
        y = np.zeros(n)
        for i in range(n):
            y[i] = sum(lengths[j] * math.sin(phi[j]) for j in range(i)) \
                + com[i] * math.sin(phi[i] + gam[i])
        return y

    J = jacobians(q)
    Jw = np.tril(np.ones((n, n)))                    # omega_i = sum_{k <= i} qdot_k
    H = sum(masses[i] * J[i].T @ J[i] + inertias[i] * np.outer(Jw[i], Jw[i]) for i in range(n))
    h = 1e-5
    Jdot = (jacobians(q + h * qdot) - jacobians(q - h * qdot)) / (2 * h)
    C = sum(masses[i] * J[i].T @ Jdot[i] for i in range(n))
    g = np.array([gravity * masses @ (heights(q + h * e) - heights(q - h * e)) / (2 * h)
                  for e in np.eye(n)])
    return H, C, g


def test_n_link_arm_with_two_links_is_the_two_link_arm():
    prm = SLOTINE_LI
    kw = dict(lengths=[prm["l1"], 1.0], masses=[prm["m1"], prm["me"]],
              com=[prm["lc1"], prm["lce"]], com_angle=[0.0, -prm["delta_e"]],
              inertias=[prm["I1"], prm["Ie"]])
    rng = np.random.default_rng(10)
    q, qdot, zeta, zetad = random_states(rng, 50)
    tau = rng.normal(0.0, 5.0, (50, 2))
    for gravity in (0.0, 9.81):
        arm2 = TwoLinkArm("a", **prm, gravity=gravity)
        armn = NLinkArm("n", **kw, gravity=gravity)
        x = np.hstack([q, qdot])
        np.testing.assert_allclose(armn.derivative(0.0, x, (tau, np.zeros((1, 2)))),
                                   arm2.derivative(0.0, x, (tau, np.zeros((1, 2)))),
                                   rtol=1e-11, atol=1e-11)
        (Y,) = NLinkRegressor("Y", lengths=kw["lengths"], gravity=gravity).output(
            0.0, None, (q, qdot, zeta, zetad))
        (Y2,) = Regressor("Y2", gravity=gravity).output(0.0, None, (q, qdot, zeta, zetad))
        np.testing.assert_allclose(Y @ NLinkArm.parameter_vector(**kw),
                                   Y2 @ TwoLinkArm.parameter_vector(**prm, gravity=gravity),
                                   rtol=1e-12, atol=1e-11)


@pytest.mark.parametrize("gravity", [0.0, 9.81])
def test_n_link_regressor_and_plant_match_loop_reference(gravity):
    rng = np.random.default_rng(11)
    q, qdot, zeta, zetad = (rng.uniform(-2.0, 2.0, (20, 3)) for _ in range(4))
    theta = NLinkArm.parameter_vector(**THREE_LINKS)
    assert theta.size == 12
    (Y,) = NLinkRegressor("Y", lengths=THREE_LINKS["lengths"], gravity=gravity).output(
        0.0, None, (q, qdot, zeta, zetad))
    assert Y.shape == (20, 3, 12)
    arm = NLinkArm("arm", **THREE_LINKS, gravity=gravity)
    tau = rng.normal(size=(20, 3))
    dx = arm.derivative(0.0, np.hstack([q, qdot]), (tau, np.zeros((1, 3))))
    for k in range(20):
        H, C, g = chain_reference(**THREE_LINKS, gravity=gravity, q=q[k], qdot=qdot[k])
        assert np.linalg.eigvalsh(H)[0] > 0.0
        N = (C + C.T) - 2 * C        # Hdot - 2C = C^T - C with C = sum m J^T Jdot: skew
        np.testing.assert_allclose(N, -N.T, atol=1e-12)
        np.testing.assert_allclose(Y[k] @ theta, H @ zetad[k] + C @ zeta[k] + g,
                                   rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(dx[k, 3:], np.linalg.solve(H, tau[k] - C @ qdot[k] - g),
                                   rtol=1e-8, atol=1e-8)


def test_n_link_arm_conserves_energy_and_batches():
    rng = np.random.default_rng(12)
    arm = NLinkArm("arm", **THREE_LINKS, gravity=9.81)
    x0 = np.hstack([rng.uniform(-math.pi, math.pi, (4, 3)), rng.uniform(-1, 1, (4, 3))])
    zero = (np.zeros((1, 3)), np.zeros((1, 3)))

    def energy(x):
        out = []
        for row in x:
            H = chain_reference(**THREE_LINKS, gravity=0.0, q=row[:3], qdot=row[3:])[0]
            phi = np.cumsum(row[:3])
            gam = np.radians(THREE_LINKS["com_angle"])
            y = [sum(THREE_LINKS["lengths"][j] * math.sin(phi[j]) for j in range(i))
                 + THREE_LINKS["com"][i] * math.sin(phi[i] + gam[i]) for i in range(3)]
            out.append(0.5 * row[3:] @ H @ row[3:] + 9.81 * np.dot(THREE_LINKS["masses"], y))
        return np.array(out)

    x = rk4(lambda t, x: arm.derivative(t, x, zero), x0, 2e-3, 500)   # 1 s, 4 arms
    assert np.max(np.abs(x - x0)) > 1.0
    drift = np.abs(energy(x) - energy(x0)) / np.abs(energy(x0)).clip(1.0)
    assert np.max(drift) < 2e-5   # measured: 4.1e-6 at dt = 2e-3, 1.4e-7 at 1e-3 (RK4 error)
    # stacked parameters == separate calls
    other = dict(THREE_LINKS, masses=[1.0, 3.0, 0.2], com_angle=[10.0, 0.0, 5.0])
    arms = [arm, NLinkArm("arm", **other, gravity=9.81), NLinkArm("arm", **other, gravity=2.0)]
    batch = stacked(arms)
    tau = rng.normal(size=(3, 3))
    dx = batch.derivative(0.0, x0[:3], (tau, np.zeros((1, 3))))
    for k, a in enumerate(arms):
        np.testing.assert_allclose(
            dx[k], a.derivative(0.0, x0[k:k + 1], (tau[k:k + 1], np.zeros((1, 3))))[0],
            rtol=1e-14, atol=1e-14)


def test_n_link_arm_rejects_bad_parameters():
    with pytest.raises(ParameterError, match="'masses'"):
        NLinkArm("arm", lengths=[1.0, 1.0], masses=[1.0, 2.0, 3.0])
    with pytest.raises(ParameterError, match="singular"):
        NLinkArm("arm", lengths=[1.0, 1.0], com=[0.5, 0.0], inertias=[0.1, 0.0])
    with pytest.raises(ParameterError, match="'lengths'"):
        NLinkRegressor("Y", lengths=[1.0, -1.0])
    with pytest.raises(ParameterError, match="limit"):
        NLinkArm("arm", lengths=np.ones(1000))


# --------------------------------------------------------------------------- theta directly
PAPER_THETA = [3.34, 0.97, 1.0392305, 0.6]


def _derivative(arm, x, tau):
    return arm.derivative(0.0, x, (tau, np.zeros_like(tau)))


def test_two_link_arm_takes_theta_exactly_as_written_and_matches_the_physical_arm():
    arm = TwoLinkArm("arm", theta=PAPER_THETA)
    assert arm.p.theta[0].tolist() == PAPER_THETA + [0.0, 0.0, 0.0]       # no round trip
    assert TwoLinkArm.parameter_vector(theta=PAPER_THETA).tolist() == PAPER_THETA
    rng = np.random.default_rng(3)
    x, tau = rng.normal(size=(1, 4)), rng.normal(size=(1, 2))
    # the physical defaults' theta, given as theta: the same plant, bit for bit
    for gravity in (0.0, 9.81):
        physical = TwoLinkArm("arm", gravity=gravity)
        full = TwoLinkArm.parameter_vector(gravity=gravity)
        given = TwoLinkArm("arm", theta=full.tolist())
        np.testing.assert_array_equal(_derivative(given, x, tau), _derivative(physical, x, tau))
    # and the given theta is the plant's: H qddot + C qdot = tau with H, C from a1..a4
    a1, a2, a3, a4 = PAPER_THETA
    q2, (qd1, qd2) = x[0, 1], x[0, 2:]
    c2, s2 = math.cos(q2), math.sin(q2)
    H = np.array([[a1 + 2 * a3 * c2 + 2 * a4 * s2, a2 + a3 * c2 + a4 * s2],
                  [a2 + a3 * c2 + a4 * s2, a2]])
    hh = a3 * s2 - a4 * c2
    C = np.array([[-hh * qd2, -hh * (qd1 + qd2)], [hh * qd1, 0.0]])
    qddot = _derivative(arm, x, tau)[0, 2:]
    np.testing.assert_allclose(H @ qddot + C @ x[0, 2:], tau[0], rtol=0, atol=1e-13)


@pytest.mark.parametrize("params, message", [
    ({"theta": PAPER_THETA, "m1": 2.0},
     "block 'arm': give either 'theta' or the physical parameters, not both ('theta' and "
     "'m1' are set)"),
    ({"theta": PAPER_THETA, "gravity": 9.81},
     "block 'arm': give either 'theta' or the physical parameters, not both ('theta' and "
     "'gravity' are set)"),
    ({"theta": [1, 2, 3]},
     "block 'arm' parameter 'theta' must have 4 numbers [a1, a2, a3, a4]: horizontal arm, no "
     "gravity columns; 5 numbers [a1, ..., a5]: gravity through a3, a4 and the known g / l1 "
     "(a6 = g a3 / l1, a7 = g a4 / l1); 7 numbers [a1, ..., a7]: a5..a7 carry the "
     "gravitational acceleration; got shape (3,)"),
    ({"theta": PAPER_THETA, "payload": 1.0},
     "block 'arm': a 'payload' needs the physical parameters (me changes), not 'theta'"),
    ({"theta": [1.0, 0.97, 1.04, 0.6]},
     "block 'arm' parameters give an inertia matrix that is not positive definite for every "
     "q2 (need a2 > 0 and a2 (a1 - a2) > a3^2 + a4^2: I1, Ie or lc1 > 0)"),
])
def test_two_link_theta_errors(params, message):
    with pytest.raises(ParameterError) as info:
        TwoLinkArm("arm", **params)
    assert str(info.value) == message


def test_n_link_arm_takes_theta_and_matches_the_physical_arm():
    physical = dict(lengths=[1.0, 0.8, 0.5], masses=[2.0, 1.0, 0.5], com=[0.4, 0.3, 0.2],
                    com_angle=[0.0, 20.0, -10.0], inertias=[0.15, 0.08, 0.03], gravity=9.81)
    theta = NLinkArm.parameter_vector(**physical)
    given = NLinkArm("arm", lengths=physical["lengths"], gravity=9.81, theta=theta)
    assert NLinkArm.parameter_vector(lengths=physical["lengths"], theta=theta).tolist() \
        == theta.tolist()
    rng = np.random.default_rng(4)
    x, tau = rng.normal(size=(1, 6)), rng.normal(size=(1, 3))
    np.testing.assert_array_equal(_derivative(given, x, tau),
                                  _derivative(NLinkArm("arm", **physical), x, tau))
    with pytest.raises(ParameterError, match="not both"):
        NLinkArm("arm", lengths=[1.0, 1.0], masses=2.0, theta=np.ones(8))
    with pytest.raises(ParameterError, match="4 numbers per link"):
        NLinkArm("arm", lengths=[1.0, 1.0], theta=np.ones(7))
    with pytest.raises(ParameterError, match="negative inertia"):
        NLinkArm("arm", lengths=[1.0, 1.0], theta=[1, 1, 0, 0.5, 1, 0, 0, 0.5])


def test_a_regressor_without_the_plants_gravity_is_refused_at_load_time(tmp_path):
    import textwrap

    import fwdstep
    from fwdstep.core.errors import WiringError
    base = """\
        blocks:
          arm: {type: TwoLinkArm, gravity: 9.81}
          Y: {type: Regressor%s}
          tau: {type: Constant, value: [0, 0]}
        connections:
          - tau.y -> arm.tau
          - arm.q -> Y.q
          - arm.qdot -> Y.qdot, Y.zeta, Y.zetad
        simulation: {t_final: 0.01, step: 0.001}
        """
    bad = tmp_path / "bad.yaml"
    bad.write_text(textwrap.dedent(base % ""))
    with pytest.raises(WiringError) as info:
        fwdstep.load_diagram(str(bad))
    assert str(info.value) == (
        f"{bad}:7: connection arm.q -> Y.q: the plant has gravity terms (a5..a7 != 0) but the "
        "regressor has none (gravity: 0, p = 4: [a1, a2, a3, a4]: horizontal arm, no gravity "
        "columns); give the Regressor the plant's gravity")
    good = tmp_path / "good.yaml"
    good.write_text(textwrap.dedent(base % ", gravity: 9.81"))
    fwdstep.load_diagram(str(good))
    nlink = tmp_path / "nlink.yaml"
    nlink.write_text(textwrap.dedent("""\
        blocks:
          arm: {type: NLinkArm, lengths: [1, 0.5], gravity: 9.81}
          Y: {type: NLinkRegressor, lengths: [1, 0.6], gravity: 9.81}
          tau: {type: Constant, value: [0, 0]}
        connections:
          - tau.y -> arm.tau
          - arm.q -> Y.q
          - arm.qdot -> Y.qdot, Y.zeta, Y.zetad
        simulation: {t_final: 0.01, step: 0.001}
        """))
    with pytest.raises(WiringError) as info:
        fwdstep.load_diagram(str(nlink))
    assert str(info.value) == (
        f"{nlink}:7: connection arm.q -> Y.q: the regressor's lengths ([1.0, 0.6]) differ from "
        "the plant's ([1.0, 0.5]); give both blocks the same lengths")


def test_five_parameter_gravity_form_equals_the_seven_parameter_form():
    """p = 5: a6 = (g/l1) a3, a7 = (g/l1) a4 folded into columns 3, 4 (TWO_LINK_FORMS)."""
    prm = dict(OTHER_ARM, gravity=9.81)
    theta7 = TwoLinkArm.parameter_vector(**prm)
    theta5 = TwoLinkArm.parameter_vector(**prm, p=5)
    assert theta5.tolist() == theta7[:5].tolist()
    Y7 = Regressor("Y7", gravity=9.81)
    Y5 = Regressor("Y5", gravity=9.81, p=5, l1=OTHER_ARM["l1"])
    rng = np.random.default_rng(5)
    for _ in range(5):
        u = tuple(rng.normal(size=(1, 2)) for _ in range(4))
        expected = Y7.output(0.0, None, u)[0][0] @ theta7
        np.testing.assert_allclose(Y5.output(0.0, None, u)[0][0] @ theta5, expected,
                                   rtol=1e-13, atol=1e-13)
    # the plant from the five numbers is the physical plant (a6, a7 recomputed: round-off)
    arm5 = TwoLinkArm("arm", theta=theta5.tolist(), gravity=9.81, l1=OTHER_ARM["l1"])
    x, tau = rng.normal(size=(1, 4)), rng.normal(size=(1, 2))
    np.testing.assert_allclose(_derivative(arm5, x, tau), _derivative(TwoLinkArm("arm", **prm),
                                                                       x, tau), rtol=1e-13)
    # a 5-form regressor with another l1 than the plant's is refused at load time
    assert Y5.check_source("q", TwoLinkArm("arm", **prm), "q") is None
    message = Y5.check_source("q", TwoLinkArm("arm", **dict(prm, l1=1.0)), "q")
    assert message.startswith("the regressor's 5-parameter form needs a6 = (g/l1) a3")
    with pytest.raises(ParameterError, match="needs gravity != 0 and l1 > 0"):
        Regressor("Y", p=5, l1=1.0)
    with pytest.raises(ParameterError, match="needs 'gravity'"):
        TwoLinkArm("arm", theta=theta5.tolist())
