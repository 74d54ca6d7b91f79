"""Hand-written NumPy RK4 loops of the benchmark closed loops: the 1.0 of every ratio.

Written the way one writes such a loop without a framework: the closed-loop right-hand side
as one NumPy function of the flat state (small arrays, ``np.linalg.solve`` for the
accelerations, ``Y @ theta``), and a classical RK4 loop that records the tracking error
every ``log_every`` steps.  The numbers (gains, q_d, initial state) are read from the
diagram's parameters by ``run_benchmarks.py``, and the recorded error is compared with the
diagram's, so both sides integrate the same closed loop.
"""
from __future__ import annotations

from math import comb

import numpy as np

# two-link arm (Slotine & Li): the lumped parameters a1..a4 of the horizontal arm
M1, L1, ME, DELTA_E, I1, LC1, IE, LCE = 1.0, 1.0, 2.0, np.radians(30.0), 0.12, 0.5, 0.25, 0.6
A1 = I1 + M1 * LC1 ** 2 + IE + ME * LCE ** 2 + ME * L1 ** 2
A2 = IE + ME * LCE ** 2
A3 = ME * L1 * LCE * np.cos(DELTA_E)
A4 = ME * L1 * LCE * np.sin(DELTA_E)


def arm_hc(q, qdot):
    """H(q) and C(q, qdot) of the two-link arm."""
    c2, s2 = np.cos(q[1]), np.sin(q[1])
    h12 = A2 + A3 * c2 + A4 * s2
    H = np.array([[A1 + 2 * A3 * c2 + 2 * A4 * s2, h12], [h12, A2]])
    hh = A3 * s2 - A4 * c2
    C = np.array([[-hh * qdot[1], -hh * (qdot[0] + qdot[1])], [hh * qdot[0], 0.0]])
    return H, C


def regressor(q, qdot, z, zd):
    """Y with H zd + C z = Y [a1, a2, a3, a4]."""
    c2, s2 = np.cos(q[1]), np.sin(q[1])
    v1 = qdot[1] * z[0] + (qdot[0] + qdot[1]) * z[1]
    v2 = qdot[0] * z[0]
    w1 = 2 * zd[0] + zd[1]
    return np.array([[zd[0], zd[1], c2 * w1 - s2 * v1, s2 * w1 + c2 * v1],
                     [0.0, zd[0] + zd[1], c2 * zd[0] + s2 * v2, s2 * zd[0] - c2 * v2]])


def rk4(f, x0, t_final, h, log_every, record):
    """Classical RK4; ``record(t, x)`` gives the row stored every ``log_every`` steps."""
    n = int(round(t_final / h))
    x = np.array(x0, dtype=float)
    rows = n // log_every + 1 + (1 if n % log_every else 0)
    log = np.empty((rows,) + np.shape(record(0.0, x)))
    r = 0
    for i in range(n):
        t = i * h
        if i % log_every == 0:
            log[r] = record(t, x)
            r += 1
        k1 = f(t, x)
        k2 = f(t + h / 2, x + h / 2 * k1)
        k3 = f(t + h / 2, x + h / 2 * k2)
        k4 = f(t + h, x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    log[r] = record(n * h, x)
    return x, log


def _matrix(value, n):
    value = np.asarray(value, dtype=float)
    return value * np.eye(n) if value.ndim == 0 else value


# ---------------------------------------------------------------- Slotine-Li, eq. (3)-(5)
def slotine_li(t_final, h, log_every, Lambda, K, Gamma, theta0, A, w, c, q0):
    """z = qdot_d - Lambda (q - q_d), zdot = qddot_d - Lambda (qdot - qdot_d), s = qdot - z,
    tau = -K s + Y(q, qdot, z, zdot) theta_hat, theta_hat' = -Gamma Y^T s, with
    q_d,i = c_i + A_i sin(w_i t).  State: q, qdot, theta_hat (8).  Returns (x, log of e)."""
    A, w, c = (np.asarray(v, dtype=float) for v in (A, w, c))
    K, Gam = _matrix(K, 2), _matrix(Gamma, 4)
    lam = np.asarray(Lambda, dtype=float)          # scalar (as the diagram's Gain) or matrix

    def desired(t):
        s, co = np.sin(w * t), np.cos(w * t)
        return c + A * s, A * w * co, -A * w * w * s

    def f(t, x):
        q, qdot, th = x[0:2], x[2:4], x[4:8]
        qd, qd_d, qd_dd = desired(t)
        e = q - qd
        z = qd_d - (lam @ e if lam.ndim else lam * e)
        zdot = qd_dd - (lam @ (qdot - qd_d) if lam.ndim else lam * (qdot - qd_d))
        s = qdot - z
        Y = regressor(q, qdot, z, zdot)
        tau = Y @ th - K @ s
        H, C = arm_hc(q, qdot)
        qddot = np.linalg.solve(H, tau - C @ qdot)
        return np.concatenate([qdot, qddot, -Gam @ (Y.T @ s)])

    x0 = np.concatenate([np.broadcast_to(q0, (2,)), [0.0, 0.0], theta0])
    return rk4(f, x0, t_final, h, log_every, lambda t, x: x[0:2] - desired(t)[0])


# ---------------------------------------------------------------- Theorem 1, eq. (2)-(5)
def theorem1(t_final, h, log_every, ell, alpha, K, Gamma, theta0, qd_coefficients, q0,
             z0=0.0):
    """Reference dynamics (2) realised by degree reduction: state z and the integrals
    I_k = p^-k (q - q_d), k = 1..ell-1 (as the ReferenceDynamics block documents):
        zdot = -alpha_ell qdot - alpha_{ell-1} (q - q_d) - sum_k alpha_{ell-1-k} I_k,
    critically damped alphas; q_d a polynomial (ascending coefficients per joint);
    s = qdot - z, tau = -K s + Y(q, qdot, z, zdot) theta_hat, theta_hat' = -Gamma Y^T s.
    State: q, qdot, theta_hat, z, I_1..I_{ell-1} (8 + 2 ell).  Returns (x, log of e)."""
    al = np.array([comb(ell + 1, k) * alpha ** (ell + 1 - k) for k in range(ell + 1)])
    coef = np.asarray(qd_coefficients, dtype=float)          # (2, degree + 1), ascending
    powers = np.arange(coef.shape[1])
    K, Gam = _matrix(K, 2), _matrix(Gamma, 4)
    nI = ell - 1
    integral_gains = al[ell - 2::-1][:nI] if nI else None   # alpha_{ell-2}, ..., alpha_0

    def desired(t):
        return coef @ (t ** powers)

    def f(t, x):
        q, qdot, th, z = x[0:2], x[2:4], x[4:8], x[8:10]
        e = q - desired(t)
        zdot = -al[ell] * qdot - al[ell - 1] * e
        if nI:
            I = x[10:].reshape(nI, 2)
            zdot = zdot - integral_gains @ I
        s = qdot - z
        Y = regressor(q, qdot, z, zdot)
        tau = Y @ th - K @ s
        H, C = arm_hc(q, qdot)
        qddot = np.linalg.solve(H, tau - C @ qdot)
        parts = [qdot, qddot, -Gam @ (Y.T @ s), zdot]
        if nI:
            parts += [e, x[10:-2]] if nI > 1 else [e]
        return np.concatenate(parts)

    x0 = np.concatenate([np.broadcast_to(q0, (2,)), [0.0, 0.0], theta0,
                         np.broadcast_to(z0, (2,)), np.zeros(2 * nI)])
    return rk4(f, x0, t_final, h, log_every, lambda t, x: x[0:2] - desired(t))
