"""diagrams/theorem6.yaml and its parts: the closed-loop identity of Theorem 6, convergence,
(a1) driven by q_d* signals, and the shipped diagrams running through the CLI.

The closed-loop identity (docs/theorem6.md derives it).  Along any run of the diagram,

    r := d/dt e + alpha* e + lam_D* W W^T e - W (theta_hat - theta),   e = Dqdot + alpha* Dq,

the residual of eq. (57), equals G*(p) R_t with Theorem 6's remainder

    R_t = p^ell s - Lambda (pI+K)^-1 p^(ell-1) [M sdot - sdot + C s + lam_D Y xi - tau_star],

up to the response to initial conditions of P(p) and (pI + K), which decays exponentially.
Both sides are computed here from logged signals, independently: r from e, W and theta_hat
(and qddot from the arm's model), G*(p) R_t from s, Y, xi and tau_star with M(q), C(q, qdot)
and scipy.signal.lsim.  Flipping the sign of h in (56) breaks the identity by ~2h.
"""
import os

import numpy as np
import pytest
from scipy import signal

import fwdstep
from fwdstep.blocks.robot import TwoLinkArm
from fwdstep.structure.spec import load_spec

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
THEOREM6 = os.path.join(ROOT, "diagrams", "theorem6.yaml")
SLOTINE_LI = os.path.join(ROOT, "diagrams", "slotine_li_disturbed.yaml")
REFERENCE = os.path.join(ROOT, "diagrams", "lib", "reference.yaml")


def run_logged(path, overrides):
    """Run with every signal logged at every step."""
    spec = load_spec(path, overrides)
    spec.simulation.log_every = 1
    spec.log = None
    return spec.parameters, fwdstep.simulate(fwdstep.structure.compiler.compile_spec(spec))


def arm_model(q, qdot):
    """M(q) and C(q, qdot) of the horizontal two-link arm (TwoLinkArm docstring), (T, 2, 2)."""
    a1, a2, a3, a4 = TwoLinkArm.parameter_vector()
    c2, s2 = np.cos(q[:, 1]), np.sin(q[:, 1])
    M = np.empty((len(q), 2, 2))
    M[:, 0, 0] = a1 + 2 * a3 * c2 + 2 * a4 * s2
    M[:, 0, 1] = M[:, 1, 0] = a2 + a3 * c2 + a4 * s2
    M[:, 1, 1] = a2
    hh = a3 * s2 - a4 * c2
    C = np.zeros_like(M)
    C[:, 0, 0] = -hh * qdot[:, 1]
    C[:, 0, 1] = -hh * (qdot[:, 0] + qdot[:, 1])
    C[:, 1, 0] = hh * qdot[:, 0]
    return M, C


def mv(A, x):
    return np.einsum("tij,tj->ti", A, x)


def lsim_channels(num, den, u, t):
    out = np.empty_like(u)
    for i in range(u.shape[1]):
        _, out[:, i], _ = signal.lsim((num, den), u[:, i], t)
    return out


def transient_fit_residual(t, D, rates, powers):
    """Largest misfit of D (T, n) by sum_k c_k t^j e^{-rate t}, per channel."""
    basis = np.stack([t ** j * np.exp(-rate * t) for rate, top in zip(rates, powers)
                      for j in range(top + 1)], axis=1)
    worst = 0.0
    for i in range(D.shape[1]):
        coef, *_ = np.linalg.lstsq(basis, D[:, i], rcond=None)
        worst = max(worst, np.abs(D[:, i] - basis @ coef).max())
    return worst


def test_closed_loop_identity_of_theorem_6():
    """The residual of (57) is G*(p) R_t (eq. (61)), with h entering (56) as written."""
    ell, alpha, a_star, k = 2, 3.0, 3.0, 20.0
    P, r = run_logged(THEOREM6, {"ell": ell, "alpha": alpha, "a_star": a_star, "gamma": 100,
                                 "K": f"{k}*eye(2)", "t_final": 2.5, "step": 0.002})
    t = r.t
    theta = TwoLinkArm.parameter_vector()
    q, qdot = r["plant.q"], r["plant.qdot"]
    tau, tau_star = r["tq.tau"], r["dist.y"]
    M, C = arm_model(q, qdot)
    qddot = np.linalg.solve(M, (tau + tau_star - mv(C, qdot))[..., None])[..., 0]

    # left: the residual of (57), from e, W, theta_hat
    e, W, h = r["qds.e"], r["ea.W"], r["ea.h"]
    edot = qddot - r["qd.y_d2"] + a_star * (qdot - r["qd.y_d1"])
    residual = (edot + a_star * e + P["lam_D_star"] * mv(W, np.einsum("tij,ti->tj", W, e))
                - mv(W, r["adapt.theta_hat"] - theta))

    # right: G*(p) R_t = [L p^(ell-1)/P](sdot) - G(p)[M sdot - sdot + C s + lam_D Y xi - tau*]
    s, Y, xi = r["ref.s"], r["plant.Y"], r["tq.xi"]
    sdot = qddot - r["ref.zdot"]
    v = mv(M, sdot) - sdot + mv(C, s) + P["lam_D"] * mv(Y, xi) - tau_star
    L = [1.0, 2 * a_star, a_star ** 2]
    N = np.concatenate([L, np.zeros(ell - 1)])                 # L(p) p^(ell-1)
    den = np.poly(np.full(ell + 1, -alpha / P["kappa"]))        # P(p)
    _, v_f, _ = signal.lsim((-P["K"], np.eye(2), P["Lambda"], np.zeros((2, 2))), v, t)
    GRt = lsim_channels(N, den, sdot, t) - lsim_channels(N, den, v_f, t)

    window = t >= 0.3
    scale = np.abs(GRt[window]).max()
    assert scale > 0.05                          # the remainder is not negligible here
    rates, powers = [alpha / P["kappa"], k], [ell, 1]   # P(p) and (pI + K) modes
    misfit = transient_fit_residual(t[window], (residual - GRt)[window], rates, powers)
    assert misfit < 1e-4 * scale                 # RK4 and lsim interpolation errors
    # and it could fail: with +h in (56) the residual would be off by 2h
    wrong = transient_fit_residual(t[window], (residual - 2 * h - GRt)[window], rates, powers)
    assert wrong > 1000 * misfit


def test_converges_without_disturbance_to_a_set_point():
    """A constant q_d meets Theorem 1's assumption (d^ell q_d = 0): Dq -> 0."""
    spec = load_spec(THEOREM6, {"ell": 2, "dist_amplitude": [0, 0], "qd_amplitude": [0, 0],
                                "qd_offset": [0.5, -0.4], "t_final": 12, "step": 0.005})
    r = fwdstep.simulate(fwdstep.structure.compiler.compile_spec(spec))
    err = np.linalg.norm(r["qds.dq"], axis=1)
    assert err[0] == pytest.approx(np.hypot(0.2, 0.2))          # q0 = [0.3, -0.2]
    assert err[-1] < 1e-4                                         # stated tolerance
    assert np.all(np.isfinite(r["adapt.theta_hat"]))
    assert np.linalg.norm(r["qds.e"][-1]) < 1e-4


@pytest.mark.parametrize("ell", [1, 3])
def test_reference_dynamics_a1_with_q_d_star_as_signals(tmp_path, ell):
    """lib/reference.yaml driven by analytic q and q_d* (sinusoids with their derivatives):
    z satisfies (a1), i.e. differs from the sinusoidal solution of
        p^(ell-1) (p + Lambda) z = p^(ell+1) q_d* - sum_k alpha_k p^k (q - q_d*) + Lambda p^ell q
    only by a solution of the homogeneous equation (t^j, j < ell - 1, and e^{-Lambda t})."""
    Lam = np.array([[3.0, 1.0], [1.0, 2.0]])
    alpha, w1, w2 = 1.5, 0.9, 2.3
    A1, phi1, A2 = np.array([0.4, -0.3]), np.array([0.3, 1.1]), np.array([0.5, 0.2])
    path = tmp_path / "a1.yaml"
    path.write_text(f"""
blocks:
  q:   {{type: Sine, amplitude: {A1.tolist()}, frequency: {w1}, phase: {phi1.tolist()}, derivatives: 1}}
  qds: {{type: Sine, amplitude: {A2.tolist()}, frequency: {w2}, derivatives: 2}}
  ref: {{type: subsystem, file: {REFERENCE},
         parameters: {{ell: {ell}, alpha: {alpha}, Lambda: {Lam.tolist()}}}}}
connections:
  - q.y -> ref.q
  - q.y_d1 -> ref.qdot
  - qds.y -> ref.q_d
  - qds.y_d1 -> ref.qdot_d
  - qds.y_d2 -> ref.qddot_d
simulation: {{t_final: 6, step: 0.002}}
log: [ref.z, ref.zdot, ref.s, q.y_d1]
""")
    r = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    t = r.t
    from fwdstep.blocks.reference import critically_damped
    alphas = critically_damped(alpha, ell)

    def steady(w, rhs):                 # rhs(s): (2, 2) complex; returns z phasor map
        s = 1j * w
        return np.linalg.solve(s ** ell * np.eye(2) + Lam * s ** (ell - 1), rhs(s))

    poly = lambda s: sum(a * s ** k for k, a in enumerate(alphas))  # noqa: E731
    Zq = steady(w1, lambda s: Lam * s ** ell - poly(s) * np.eye(2)) @ (A1 * np.exp(1j * phi1))
    Zd = steady(w2, lambda s: (s ** (ell + 1) + poly(s)) * np.eye(2)) @ A2.astype(complex)
    z_ss = np.imag(np.outer(np.exp(1j * w1 * t), Zq) + np.outer(np.exp(1j * w2 * t), Zd))
    zdot_ss = np.imag(np.outer(1j * w1 * np.exp(1j * w1 * t), Zq)
                      + np.outer(1j * w2 * np.exp(1j * w2 * t), Zd))
    rates = list(np.linalg.eigvalsh(Lam))
    basis = [t ** j for j in range(ell - 1)] + [np.exp(-lam * t) for lam in rates]
    B = np.stack(basis, axis=1) if basis else np.zeros((len(t), 0))
    for got, want in ((r["ref.z"], z_ss), (r["ref.zdot"], zdot_ss)):
        D = got - want
        for i in range(2):
            coef, *_ = np.linalg.lstsq(B, D[:, i], rcond=None)
            assert np.abs(D[:, i] - B @ coef).max() < 1e-6 * np.abs(want).max()
        assert np.abs(want).max() > 0.1
    np.testing.assert_allclose(r["ref.s"], r["q.y_d1"] - r["ref.z"], atol=1e-14)


@pytest.mark.parametrize("path", [THEOREM6, SLOTINE_LI], ids=["theorem6", "slotine_li"])
def test_shipped_diagram_runs_and_plots(tmp_path, path):
    """`fwdstep run` writes the error, torque and parameter-estimate figures."""
    import matplotlib
    matplotlib.use("Agg")
    from fwdstep.cli.commands import cmd_run
    out = tmp_path / "out"
    code = cmd_run(path, sets=["t_final=0.2"], outdir=str(out), quiet=True)
    assert code == 0
    written = set(os.listdir(out))
    for name in ("tracking_error", "torque", "parameter_estimates"):
        assert any(f.startswith(name) for f in written), written


def test_both_diagrams_share_the_disturbance_and_trajectory():
    """The baseline and Theorem 6 see the same q_d, tau_star and initial arm state."""
    a, b = load_spec(THEOREM6), load_spec(SLOTINE_LI)
    for key in ("q0", "qd_amplitude", "qd_offset", "qd_frequency", "dist_amplitude",
                "dist_frequency", "dist_phase", "theta0", "K"):
        np.testing.assert_array_equal(a.parameters[key], b.parameters[key], err_msg=key)
