"""The reformulated PID (22)-(23) is the textbook PID, and both reject a constant disturbance.

K_D zdot = K_D qddot_d - K_P Delta qdot - K_I Delta q integrates to
z = qdot_d - K_D^-1 (K_P Delta q + K_I int Delta q) + c with c = z(0) - qdot_d(0) +
K_D^-1 K_P Delta q(0), so tau = -K_D (qdot - z) = -K_D Delta qdot - K_P Delta q -
K_I int Delta q - K_D c: the textbook PID exactly when z(0) = qdot_d(0) - K_D^-1 K_P Delta q(0).
The two diagrams integrate the same ODE in coordinates (q, qdot, z) and (q, qdot, int Delta q)
that differ by a time-varying affine map, so their RK4 solutions differ by O(h^4) only:
3.4e-10 in qdot at h = 1e-3 below, 2.0e-11 at h = 5e-4.
"""
from __future__ import annotations

import os

import numpy as np
import pytest

import fwdstep

DIAGRAMS = os.path.join(os.path.dirname(__file__), "..", "..", "diagrams")


def run(name: str, **overrides):
    path = os.path.join(DIAGRAMS, f"{name}.yaml")
    return fwdstep.simulate(fwdstep.load_diagram(path, overrides=overrides))


# a sinusoidal q_d with a phase and offset (so qdot_d(0) != 0 and Delta q(0) != 0), a
# sinusoidal-plus-constant disturbance, and unequal diagonal gains
TRACKING = dict(t_final=3.0, step=0.001, log_every=1, kD=[60.0, 25.0], kP=[300.0, 90.0],
                kI=[500.0, 70.0], q0=[0.4, -0.3], qd_amplitude=[0.5, 0.3], qd_frequency=0.7,
                qd_phase=[0.4, -1.0], qd_offset=[0.1, 0.2], dist_amplitude=[2.0, 1.0],
                dist_frequency=2.0, dist_offset=[0.5, -0.3])


@pytest.mark.parametrize("gravity", [0.0, 9.81])
def test_reformulated_pid_is_the_textbook_pid(gravity):
    classic = run("pid_classic", gravity=gravity, **TRACKING)
    reform = run("pid_reformulated", gravity=gravity, **TRACKING)
    for signal in ("arm.q", "arm.qdot"):
        np.testing.assert_allclose(reform[signal], classic[signal], rtol=0, atol=1e-9)
    scale = np.max(np.abs(classic["tau.y"]))
    np.testing.assert_allclose(reform["tau.y"], classic["tau.y"], rtol=0, atol=1e-9 * scale)
    assert np.max(np.abs(classic["e.y"])) > 0.1          # a real tracking transient


def test_another_initial_z_is_a_different_controller():
    """The identity needs z(0) = qdot_d(0) - K_D^-1 K_P Delta q(0): moving z(0) by 0.05
    adds the constant torque -K_D c, and the trajectories part."""
    classic = run("pid_classic", **TRACKING)
    spec = fwdstep.structure.spec.load_spec(os.path.join(DIAGRAMS, "pid_reformulated.yaml"), TRACKING)
    z0 = spec.parameters["z0"] + 0.05
    reform = run("pid_reformulated", z0=z0.tolist(), **TRACKING)
    assert np.max(np.abs(reform["arm.q"] - classic["arm.q"])) > 1e-3


def test_theorem2_with_ell_1_is_pid():
    """(16) with ell = 1 and tau = -K s: K_D = K, K_P = K alpha_1, K_I = K alpha_0, and the
    reference dynamics start from z(0) = qdot_d(0) - alpha_1 Delta q(0)."""
    K, alpha = 100.0, 2.0
    common = dict(t_final=3.0, step=0.001, log_every=1)
    t2 = run("theorem2", ell=1, K=K, alpha=alpha, **common)
    pid = run("pid_classic", kD=[K, K], kP=[2 * alpha * K] * 2, kI=[alpha ** 2 * K] * 2,
              **common)
    np.testing.assert_allclose(t2["arm.q"], pid["arm.q"], rtol=0, atol=1e-9)


REGULATION = dict(t_final=10.0, step=0.002, log_every=5, q0=[0.0, 0.0],
                  qd_amplitude=[0.0, 0.0], qd_offset=[0.5, -0.4], dist_amplitude=[0.0, 0.0],
                  dist_offset=[3.0, -1.5])


@pytest.mark.parametrize("name", ["pid_classic", "pid_reformulated"])
@pytest.mark.parametrize("gravity", [0.0, 9.81])
def test_pid_rejects_a_constant_disturbance(name, gravity):
    """Constant q_d and tau_star (and gravity, on the vertical arm): Delta q -> 0 and the
    torque settles at the value that holds the arm there against the disturbance."""
    r = run(name, gravity=gravity, **REGULATION)
    assert np.max(np.abs(r["e.y"][-1])) < 1e-5
    assert np.max(np.abs(r["arm.qdot"][-1])) < 1e-5
    if gravity == 0.0:
        np.testing.assert_allclose(r["tau.y"][-1], [-3.0, 1.5], atol=1e-4)


def test_without_the_integral_a_constant_disturbance_stays():
    """The same run with K_I = 0 (PD): the error settles at K_P^-1 tau_star, not 0."""
    r = run("pid_classic", kI=[0.0, 0.0], **REGULATION)
    np.testing.assert_allclose(r["e.y"][-1], np.array([3.0, -1.5]) / 400.0, rtol=1e-3)
