"""AdaptationLaw: theta_hat' = -Gamma W^T e (eqs. (5), (58), (89), (105)) and its scalar
form (eqs. (88), (111), (112), (120))."""
from __future__ import annotations

import copy
import math
from types import SimpleNamespace

import numpy as np
import pytest

from fwdstep.blocks.adaptation import AdaptationLaw
from fwdstep.blocks.robot import Regressor, TwoLinkArm
from fwdstep.core.errors import ParameterError

SPD = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, -0.3], [0.0, -0.3, 4.0]])


def stacked(blocks):
    """What a batched sweep does: stack every run-time parameter along the batch axis."""
    clone = copy.copy(blocks[0])
    clone.p = SimpleNamespace(**{k: np.concatenate([getattr(b.p, k) for b in blocks])
                                 for k in vars(blocks[0].p)})
    clone.finalize(len(blocks))
    return clone


@pytest.mark.parametrize("gamma", [2.5, [1.0, 2.0, 0.5], SPD], ids=["scalar", "diag", "spd"])
def test_derivative_is_minus_gamma_w_transpose_e(gamma):
    rng = np.random.default_rng(1)
    law = AdaptationLaw("adapt", regressor_shape=[2, 3], gamma=gamma, theta0=[1.0, -2.0, 0.5])
    assert law.inputs["W"].shape == (2, 3) and law.outputs["theta_hat"].shape == (3,)
    assert law.feedthrough("theta_hat") == ()
    np.testing.assert_array_equal(law.x0, [[1.0, -2.0, 0.5]])
    G = np.asarray(gamma) if np.ndim(gamma) == 2 else np.diag(np.broadcast_to(gamma, 3))
    W = rng.normal(size=(20, 2, 3))
    e = rng.normal(size=(20, 2))
    x = rng.normal(size=(20, 3))
    dx = law.derivative(0.0, x, (W, e))
    assert dx.shape == (20, 3)
    for k in range(20):
        np.testing.assert_allclose(dx[k], -G @ W[k].T @ e[k], rtol=1e-14, atol=1e-15)
    (theta_hat,) = law.output(0.0, x, (W, e))
    np.testing.assert_array_equal(theta_hat, x)


def test_scalar_estimate_with_vector_regressor():
    rng = np.random.default_rng(2)
    law = AdaptationLaw("adapt", regressor_shape=[3], gamma=0.7, theta0=2.0)
    assert law.inputs["W"].shape == (3,) and law.outputs["theta_hat"].shape == ()
    np.testing.assert_array_equal(law.x0, [[2.0]])
    W = rng.normal(size=(10, 3))
    e = rng.normal(size=(10, 3))
    x = rng.normal(size=(10, 1))
    dx = law.derivative(0.0, x, (W, e))
    assert dx.shape == (10, 1)
    np.testing.assert_allclose(dx[:, 0], -0.7 * np.einsum("bi,bi->b", W, e), rtol=1e-14)
    (theta_hat,) = law.output(0.0, x, (W, e))
    assert theta_hat.shape == (10,)
    np.testing.assert_array_equal(theta_hat, x[:, 0])


def test_batched_gains_equal_separate_calls():
    rng = np.random.default_rng(3)
    gains = [SPD, np.diag([1.0, 3.0, 2.0]), 0.1 * np.eye(3)]
    laws = [AdaptationLaw("adapt", regressor_shape=[2, 3], gamma=g) for g in gains]
    batch = stacked(laws)
    W = rng.normal(size=(3, 2, 3))
    e = rng.normal(size=(3, 2))
    x = np.zeros((3, 3))
    dx = batch.derivative(0.0, x, (W, e))
    for k, law in enumerate(laws):
        np.testing.assert_allclose(dx[k], law.derivative(0.0, x[k:k + 1],
                                                         (W[k:k + 1], e[k:k + 1]))[0],
                                   rtol=1e-15, atol=0)
    # diagonal gains stacked, inputs of batch 1 broadcast against a batched state
    diag = stacked([AdaptationLaw("a", regressor_shape=[2, 3], gamma=g)
                    for g in ([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])])
    dx = diag.derivative(0.0, np.zeros((2, 3)), (W[:1], e[:1]))
    v = W[0].T @ e[0]
    np.testing.assert_allclose(dx, [-np.array([1.0, 2.0, 3.0]) * v,
                                    -np.array([4.0, 5.0, 6.0]) * v], rtol=1e-15)
    # unbatched block and inputs, batched state
    dx = laws[0].derivative(0.0, np.zeros((4, 3)), (W[:1], e[:1]))
    assert dx.shape == (4, 3)


def test_gradient_law_makes_lyapunov_function_decrease():
    """The sign convention: with e' = -k e + W (theta_hat - theta) (as eq. (57)),
    V = e^T e / 2 + (theta_hat - theta)^T Gamma^-1 (theta_hat - theta) / 2 has V' = -k e^T e;
    the integral identity V(T) - V(0) = -k int e^T e dt holds to the RK4 error."""
    law = AdaptationLaw("adapt", regressor_shape=[2, 3], gamma=SPD, theta0=0.0)
    theta = np.array([1.0, -0.5, 2.0])
    k_gain = 2.0
    G_inv = np.linalg.inv(SPD)

    def regressor(t):
        return np.array([[math.sin(t), 1.0, math.cos(2 * t)],
                         [math.cos(t), math.sin(3 * t), 1.0]])[None]

    def f(t, z):                      # z = [e (2), theta_hat (3), int e^T e]
        e, th = z[:, :2], z[:, 2:5]
        W = regressor(t)
        de = -k_gain * e + np.matmul(W, (th - theta)[:, :, None])[:, :, 0]
        dth = law.derivative(t, th, (W, e))
        return np.hstack([de, dth, np.sum(e * e, axis=1, keepdims=True)])

    def V(z):
        d = z[0, 2:5] - theta
        return 0.5 * z[0, :2] @ z[0, :2] + 0.5 * d @ G_inv @ d

    z = np.hstack([[[0.5, -0.2]], law.x0, [[0.0]]])
    V0, dt = V(z), 1e-3
    history = [V0]
    for step in range(5000):                         # 5 s
        t = step * dt
        k1 = f(t, z)
        k2 = f(t + dt / 2, z + dt / 2 * k1)
        k3 = f(t + dt / 2, z + dt / 2 * k2)
        k4 = f(t + dt, z + dt * k3)
        z = z + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        history.append(V(z))
    assert np.all(np.diff(history) <= 1e-12)          # V never increases
    assert abs(V(z) - V0 + k_gain * z[0, 5]) < 1e-10
    assert V(z) < 0.1 * V0                            # persistently exciting W: it converges
    assert np.linalg.norm(z[0, 2:5] - theta) < 0.5 * np.linalg.norm(theta)


def test_theorem1_lyapunov_identity_on_two_link_arm():
    """Eqs. (4)-(5) on the vertical TwoLinkArm (with z = -lam (q - q_d), as in Slotine-Li):
    V = s^T H s / 2 + Delta theta^T Delta theta / (2 gamma) obeys V' = -s^T K s (proof of
    Theorem 1, using Properties 2 and 3), so V(T) - V(0) = -int s^T K s dt to the RK4 error;
    this ties the plant, the regressor and the adaptation law together."""
    g, lam, k_gain, gamma = 9.81, 5.0, 20.0, 2.0
    qd = np.array([1.0, -0.5])
    arm = TwoLinkArm("arm", gravity=g)
    reg = Regressor("Y", gravity=g)
    law = AdaptationLaw("adapt", regressor_shape=[2, 7], gamma=gamma, theta0=0.0)
    theta = TwoLinkArm.parameter_vector(gravity=g)
    zero = np.zeros((1, 2))

    def signals(z):
        q, qdot, th = z[:, 0:2], z[:, 2:4], z[:, 4:11]
        zeta = -lam * (q - qd)
        s = qdot - zeta
        (Y,) = reg.output(0.0, None, (q, qdot, zeta, -lam * qdot))
        return s, Y, th

    def f(t, z):
        s, Y, th = signals(z)
        tau = -k_gain * s + np.matmul(Y, th[:, :, None])[:, :, 0]
        return np.hstack([arm.derivative(t, z[:, :4], (tau, zero)),
                          law.derivative(t, th, (Y, s)), k_gain * np.sum(s * s, 1)[:, None]])

    def V(z):
        s, _, th = signals(z)
        a1, a2, a3, a4 = theta[:4]
        c2, s2 = math.cos(z[0, 1]), math.sin(z[0, 1])
        h12 = a2 + a3 * c2 + a4 * s2
        H = np.array([[a1 + 2 * a3 * c2 + 2 * a4 * s2, h12], [h12, a2]])
        d = th[0] - theta
        return 0.5 * s[0] @ H @ s[0] + 0.5 * d @ d / gamma

    z = np.hstack([arm.x0, law.x0, [[0.0]]])
    V0, dt = V(z), 1e-3
    history = [V0]
    for step in range(3000):                          # 3 s
        t = step * dt
        k1 = f(t, z)
        k2 = f(t + dt / 2, z + dt / 2 * k1)
        k3 = f(t + dt / 2, z + dt / 2 * k2)
        k4 = f(t + dt, z + dt * k3)
        z = z + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        history.append(V(z))
    assert np.all(np.diff(history) <= 1e-9 * V0)       # V never increases
    # measured: |V(T) - V(0) + int s^T K s| / V(0) = 4.3e-7, 2.5e-8, 1.5e-9 at dt = 2e-3,
    # 1e-3, 5e-4 (RK4's fourth order: the identity itself is exact)
    assert abs(V(z) - V0 + z[0, 11]) < 1e-7 * V0
    assert z[0, 11] > 0.3 * V0                         # a real decrease (234 -> 145)


@pytest.mark.parametrize("params, message", [
    (dict(regressor_shape=[2, 2], gamma=[[1.0, 2.0], [0.0, 1.0]]), "symmetric positive"),
    (dict(regressor_shape=[2, 2], gamma=[[1.0, 2.0], [2.0, 1.0]]), "symmetric positive"),
    (dict(regressor_shape=[2, 2], gamma=-1.0), "positive number"),
    (dict(regressor_shape=[2, 2], gamma=[1.0, 0.0]), "positive number"),
    (dict(regressor_shape=[2, 3], gamma=[1.0, 2.0]), "has 2 numbers, not 1 or 3"),
    (dict(regressor_shape=[2], gamma=[1.0, 2.0]), "positive number"),
    (dict(regressor_shape=[2, 3], theta0=[1.0, 2.0]), "'theta0'"),
    (dict(regressor_shape=[2, 0]), "'regressor_shape'"),
    (dict(regressor_shape=[2, 3, 4]), "'regressor_shape'"),
    (dict(regressor_shape=[2.5]), "'regressor_shape'"),
    (dict(regressor_shape=[10**7, 10**6]), "limit"),
])
def test_rejects_bad_parameters(params, message):
    with pytest.raises(ParameterError, match=message):
        AdaptationLaw("adapt", **params)


# ------------------------------------------------------------------ ball projection
@pytest.mark.parametrize("gamma", [2.5, [1.0, 2.0, 0.5], SPD], ids=["scalar", "diag", "spd"])
def test_ball_projection_derivative_inside_and_on_the_sphere(gamma):
    """Inside: the plain law -Gamma W^T e.  On the sphere with the update pointing out:
    Ioannou & Sun's tau - Gamma d (d^T tau) / (d^T Gamma d), tangent to the sphere (for a
    scalar gain: tau less its normal component), all computed here with numpy."""
    rng = np.random.default_rng(7)
    c, r = np.array([0.5, -0.2, 1.0]), 2.0
    law = AdaptationLaw("a", regressor_shape=[2, 3], gamma=gamma, radius=r, center=c)
    G = np.diag(np.broadcast_to(np.asarray(gamma, dtype=float), (3,))) \
        if np.ndim(gamma) < 2 else SPD
    for _ in range(20):
        W, e = rng.standard_normal((1, 2, 3)), rng.standard_normal((1, 2))
        tau = -G @ W[0].T @ e[0]
        inside = c + 0.9 * r * rng.uniform(-1, 1, 3) / math.sqrt(3)
        dx = law.derivative(0.0, np.append(inside, 0.0)[None], (W, e))
        np.testing.assert_allclose(dx[0, :3], tau, rtol=1e-13, atol=1e-14)
        n = rng.standard_normal(3)
        n *= np.sign(n @ tau) / np.linalg.norm(n)          # an outward normal: n . tau > 0
        on = c + r * n
        dx = law.derivative(0.0, np.append(on, 1.0)[None], (W, e))
        d = on - c
        expected = tau - G @ d * (d @ tau) / (d @ G @ d)
        np.testing.assert_allclose(dx[0, :3], expected, rtol=1e-12, atol=1e-13)
        assert abs(d @ dx[0, :3]) < 1e-12
        if np.ndim(gamma) == 0:
            np.testing.assert_allclose(dx[0, :3], tau - n * (n @ tau), rtol=1e-12, atol=1e-13)
        assert law.zero_crossings(0.0, np.append(on, 1.0)[None], (W, e))[0, 0] < 0


BALL_LAW = """
blocks:
  W:  {type: Constant, value: [[1.0, 0.0], [0.0, 1.0]]}
  e:  {type: Step, before: [-1.0, 0.0], after: [1.0, 0.0], time: 2.0}
  th: {type: AdaptationLaw, regressor_shape: [2, 2], gamma: 1.0, theta0: [0.0, 0.5],
       radius: 1.0}
connections:
  - W.y -> th.W
  - e.y -> th.e
simulation: {t_final: 3.0, step: 0.05, solver: rk4}
"""


@pytest.mark.parametrize("solver, tol", [("rk4", 1e-7), ("dop853", 1e-9)])
def test_ball_projection_slides_on_the_sphere_and_leaves_it(tmp_path, solver, tol):
    """tau = (1, 0) from (0, 0.5): a straight line to the unit circle at t1 = sqrt(3)/2
    (angle pi/6), then the projected flow phi' = -sin(phi), tan(phi/2) = tan(pi/12)
    e^-(t - t1); at t = 2 the update turns to (-1, 0), inward: it leaves the sphere and
    goes straight on.  The estimate never leaves the ball."""
    import fwdstep
    path = tmp_path / "ball.yaml"
    path.write_text(BALL_LAW)
    r = fwdstep.simulate(fwdstep.load_diagram(str(path), overrides={
        "simulation.solver": solver, "simulation.rtol": 1e-11, "simulation.atol": 1e-11}))
    t, th = r.t, r["th.theta_hat"]
    t1 = math.sqrt(0.75)
    phi = 2 * np.arctan(math.tan(math.pi / 12) * np.exp(-(np.minimum(t, 2.0) - t1)))
    on = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    exact = np.where((t < t1)[:, None], np.stack([t, 0.5 + 0 * t], axis=1), on)
    exact = np.where((t >= 2.0)[:, None], on - np.stack([t - 2.0, 0 * t], axis=1), exact)
    np.testing.assert_allclose(th, exact, rtol=0, atol=tol)
    assert np.linalg.norm(th, axis=1).max() <= 1.0 + 1e-12
    assert [e.kind for e in r.events] == ["ball falling", "ball rising"]
    np.testing.assert_allclose([e.time for e in r.events], [t1, 2.0], atol=1e-12)


@pytest.mark.parametrize("params, message", [
    ({"lower": -1.0, "radius": 1.0}, "one projection"),
    ({"radius": 1.0, "theta0": [1.0, 1.0]}, "theta0 in the ball"),
    ({"radius": 0.0}, "'radius' must be positive"),
    ({"radius": 1.0, "center": [1.0, 2.0, 3.0]}, "'center' must be a number or 2 numbers"),
])
def test_ball_projection_rejects_bad_parameters(params, message):
    with pytest.raises(ParameterError, match=message):
        AdaptationLaw("a", regressor_shape=[1, 2], **params)
