"""Theorems 2-5 (Sec. 4.2, eq. (16)-(45)) as shipped diagrams, checked against closed forms.

On the point mass the closed loops of Theorems 2 and 3 are linear, so the steady-state error
under a single-frequency disturbance is a transfer function evaluated at that frequency
(derivation in docs/theorems2-5.md); per axis, with P(p) = (p + alpha/kappa)^(ell+1):

    Theorem 2, (16) + (21):  Delta q = p^ell / (m p^(ell+2) + K P(p)) tau_star,
    Theorem 3, (29) + (28):  Delta q = p^(ell-1) (p + Lambda) / (P(p) (m p + K)) tau_star.

Theorem 5's storage function (38) must satisfy the first line of (39) along any run.
"""
from __future__ import annotations

import os

import numpy as np
import pytest
from scipy.integrate import cumulative_simpson

import fwdstep
from fwdstep.blocks.robot import TwoLinkArm

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
DIAGRAMS = os.path.join(ROOT, "diagrams")
ARM_DIAGRAMS = ["theorem2", "theorem3", "theorem4", "theorem5", "theorem3_vertical",
                "theorem4_vertical", "theorem5_vertical"]


def path(name: str) -> str:
    return os.path.join(DIAGRAMS, f"{name}.yaml")


def run(name: str, **overrides):
    return fwdstep.simulate(fwdstep.load_diagram(path(name), overrides=overrides))


def phasor(t, e, w):
    """Least-squares a, b of e = a sin(w t) + b cos(w t) + c; returns a + j b, which is the
    complex amplitude Z of e = Im(Z exp(j w t))."""
    basis = np.stack([np.sin(w * t), np.cos(w * t), np.ones_like(t)], axis=1)
    coef, *_ = np.linalg.lstsq(basis, e, rcond=None)
    return coef[0] + 1j * coef[1]


def closed_form(theorem: int, p: complex, ell: int, m: float, K: float, alpha: float,
                kappa: float, Lambda: float) -> complex:
    """Transfer function tau_star -> Delta q of the point-mass closed loop, at p."""
    P = np.polyval(np.poly([-alpha / kappa] * (ell + 1)), p)
    if theorem == 2:
        return p ** ell / (m * p ** (ell + 2) + K * P)
    return p ** (ell - 1) * (p + Lambda) / (P * (m * p + K))


# ----------------------------------------------------------------------------- structure
@pytest.mark.parametrize("name", [n for n in ARM_DIAGRAMS if n != "theorem2"]
                         + ["slotine_li_sine_disturbance"])
def test_theta_in_the_diagram_is_the_plants(name):
    """The feedforward parameters written out in the YAML are the arm's true theta."""
    spec = fwdstep.structure.spec.load_spec(path(name))
    gravity = spec.parameters.get("gravity", 0.0)
    true = TwoLinkArm.parameter_vector(gravity=gravity)
    np.testing.assert_allclose(spec.parameters["theta"], true, rtol=1e-15)
    if "theta_hat" in spec.parameters:                      # Theorems 4 and 5: a wrong estimate
        np.testing.assert_allclose(spec.parameters["theta_hat"],
                                   spec.parameters["theta_scale"] * true, rtol=1e-15)
    assert spec.parameters.get("theta_scale", 0.6) == 0.6   # the same wrong estimate everywhere


# ----------------------------------------------------------------- exact, on the point mass
CASES = [(theorem, ell, 1.0) for theorem in (2, 3) for ell in (1, 2, 3, 4)] + [(2, 3, 1.5),
                                                                               (3, 3, 1.5)]


@pytest.mark.parametrize("theorem, ell, kappa", CASES)
def test_point_mass_steady_state_error_is_the_transfer_function(theorem, ell, kappa):
    """Both axes, two amplitudes and phases, at w = 1.5 (above Remark 4's 'one')."""
    m, K, alpha, Lambda, w = 1.3, 40.0, 3.0, 1.0, 1.5
    amplitude, phase = np.array([1.0, 0.5]), np.array([0.0, 0.7])
    overrides = dict(ell=ell, K=K, alpha=alpha, kappa=kappa, m=m, q0=[0.0, 0.0],
                     qd_amplitude=[0.0, 0.0], dist_amplitude=amplitude.tolist(),
                     dist_frequency=w, dist_phase=phase.tolist(), t_final=30 * kappa,
                     step=0.01, log_every=1)
    if theorem == 3:
        overrides["Lambda"] = Lambda
    r = run(f"theorem{theorem}_pointmass", **overrides)
    tail = r.t >= r.t[-1] - 4 * (2 * np.pi / w)               # the last four periods
    G = closed_form(theorem, 1j * w, ell, m, K, alpha, kappa, Lambda)
    for axis in range(2):
        expected = G * amplitude[axis] * np.exp(1j * phase[axis])
        measured = phasor(r.t[tail], r["e.y"][tail, axis], w)
        assert abs(measured - expected) <= 1e-4 * abs(expected), (axis, measured, expected)


@pytest.mark.parametrize("ell, c", [(1, 0.5), (2, 9 / 8)])
def test_theorem2_needs_K_above_m_alpha_c(ell, c):
    """m p^(ell+2) + K (p + alpha)^(ell+1) is Hurwitz iff K > c m alpha, with c = 1/2 for
    ell = 1 and c = 9/8 for ell = 2 (Routh, exactly); 20% either side decays or grows."""
    m, alpha = 1.0, 2.0
    peaks = {}
    for factor in (0.8, 1.25):
        r = run("theorem2_pointmass", ell=ell, alpha=alpha, m=m, K=factor * c * m * alpha,
                qd_amplitude=[0.0, 0.0], dist_amplitude=[0.0, 0.0], t_final=30.0, step=0.01,
                log_every=1)
        norm = np.linalg.norm(r["e.y"], axis=1)
        peaks[factor] = norm[r.t >= 25].max() / norm[(r.t >= 5) & (r.t < 10)].max()
    assert peaks[0.8] > 3.0 and peaks[1.25] < 0.3, peaks


# ----------------------------------------------------------------- Theorem 5, eq. (38)-(39)
def inertia(q: np.ndarray, a: np.ndarray) -> np.ndarray:
    """H(q) of the two-link arm (T, 2, 2) from its lumped parameters a1..a4 (TwoLinkArm)."""
    c2, s2 = np.cos(q[:, 1]), np.sin(q[:, 1])
    h12 = a[1] + a[2] * c2 + a[3] * s2
    H = np.empty((len(q), 2, 2))
    H[:, 0, 0] = a[0] + 2 * a[2] * c2 + 2 * a[3] * s2
    H[:, 0, 1] = H[:, 1, 0] = h12
    H[:, 1, 1] = a[1]
    return H


@pytest.mark.parametrize("name", ["theorem5", "theorem5_vertical"])
def test_theorem5_storage_function_obeys_eq39(name):
    """V = s^T M s / 2 + lambda_D/(2 lambda) xi^T xi (38) and, integrated, the first line of
    (39): V(t) - V(0) = int [-s^T K s - lambda_D xi^T xi + xi^T Dtheta + s^T tau_star]
    + (xi(t) - xi(0))^T Dtheta / lambda, with Dtheta = theta_hat - theta constant."""
    d = fwdstep.load_diagram(path(name), overrides=dict(t_final=1.5, step=0.0005, log_every=1))
    prm = d.spec.parameters
    r = fwdstep.simulate(d)
    t, s, xi, tau_star = r.t, r["s.y"], r["xi.y"], r["dist.y"]
    K, lambda_D, lam = prm["K"], prm["lambda_D"], prm["lambda_f"]
    dtheta = prm["theta_hat"] - prm["theta"]
    H = inertia(r["arm.q"], prm["theta"])
    V = 0.5 * np.einsum("ti,tij,tj->t", s, H, s) + lambda_D / (2 * lam) * np.sum(xi ** 2, 1)
    rate = (-K * np.sum(s ** 2, 1) - lambda_D * np.sum(xi ** 2, 1) + xi @ dtheta
            + np.sum(s * tau_star, 1))
    integral = cumulative_simpson(rate, x=t, initial=0.0) + (xi - xi[0]) @ dtheta / lam
    change = V - V[0]
    assert np.max(np.abs(change - integral)) <= 1e-6 * np.max(np.abs(change))
    # the identity is not vacuous: dropping the disturbance term breaks it
    without = integral - cumulative_simpson(np.sum(s * tau_star, 1), x=t, initial=0.0)
    assert np.max(np.abs(change - without)) > 1e-3 * np.max(np.abs(change))
