"""The filtered regressor W = G(p) Y of eq. (50) and the error augmentation h of eq. (51).

G(p) = [N(p)/P(p)] Lambda (pI + K)^-1 is realised in diagrams/lib/error_augmentation.yaml
by the generic blocks StateSpace (A = -K, B = I, C = Lambda, column by column on the (n, p)
matrix Y) and TransferFunction (N/P on every element).  Checked here:

* the realisation the engine builds has the frequency response of the rational G(jw), for
  diagonal and for general (non-diagonal) symmetric K and Lambda, at several ell;
* a run through the engine reaches the sinusoidal steady state G(jw) predicts;
* W and h agree with an independent scipy.signal.lsim computation along a run with a
  time-varying theta_hat, and h is zero (to round-off) when theta_hat is constant.
"""
import os

import numpy as np
import pytest
from scipy import signal

import fwdstep
from fwdstep.structure.spec import load_spec

LIB = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "diagrams", "lib",
                                   "error_augmentation.yaml"))

K_DIAG = [[20.0, 0.0], [0.0, 8.0]]
LAMBDA_DIAG = [[5.0, 0.0], [0.0, 3.0]]
K_SYM = [[20.0, 6.0], [6.0, 8.0]]          # symmetric positive definite, not diagonal
LAMBDA_SYM = [[5.0, -2.0], [-2.0, 3.0]]


def polynomials(ell, a_star=1.5, root=2.0):
    """N(p) = p^(ell-1) (p + a*)^2 and P(p) = (p + root)^(ell+1), highest power first."""
    num = np.concatenate([[1.0, 2 * a_star, a_star ** 2], np.zeros(ell - 1)])
    den = np.poly(np.full(ell + 1, -root))
    return num, den


def harness(tmp_path, ell, K, Lam, y_source, theta_source, t_final=1.0, step=0.01):
    """A diagram around lib/error_augmentation.yaml with the given Y and theta_hat sources."""
    num, den = polynomials(ell)
    text = f"""
blocks:
{y_source}
{theta_source}
  ea: {{type: subsystem, file: {LIB},
       parameters: {{n: 2, p: 3, num: {num.tolist()}, den: {den.tolist()}, K: {K}, Lambda: {Lam}}}}}
connections:
  - Y.y -> ea.Y
  - theta.y -> ea.theta_hat
simulation: {{t_final: {t_final}, step: {step}, solver: rk4}}
"""
    path = tmp_path / "harness.yaml"
    path.write_text(text)
    return str(path)


CONSTANT_Y = "  Y: {type: Constant, value: [[1, 0, 2], [0, 1, -1]]}"
CONSTANT_THETA = "  theta: {type: Constant, value: [1, 2, 3]}"


def G_of(w, ell, K, Lam):
    """The rational G(jw) = N/P(jw) Lambda (jw I + K)^-1, a complex (2, 2) matrix."""
    num, den = polynomials(ell)
    s = 1j * w
    return np.polyval(num, s) / np.polyval(den, s) * np.asarray(Lam) @ np.linalg.inv(
        s * np.eye(2) + np.asarray(K))


def matrices(blk):
    """(A, B, C, D) of a single-input, single-output LinearBlock over flattened ports."""
    p = blk.p
    A = p.A_T[0].T
    n = A.shape[0]
    size_in = blk.inputs["u"].size
    B = p.B_T_0[0].T if hasattr(p, "B_T_0") else np.zeros((n, size_in))
    C = p.C_T_0[0].T
    D = p.D_T_0_0[0].T if hasattr(p, "D_T_0_0") else np.zeros((C.shape[0], size_in))
    return A, B, C, D


def series(first, second):
    """The state-space form of ``second`` after ``first``."""
    A1, B1, C1, D1 = first
    A2, B2, C2, D2 = second
    A = np.block([[A1, np.zeros((A1.shape[0], A2.shape[0]))], [B2 @ C1, A2]])
    B = np.vstack([B1, B2 @ D1])
    C = np.hstack([D2 @ C1, C2])
    return A, B, C, D2 @ D1


@pytest.mark.parametrize("ell", [1, 2, 4])
@pytest.mark.parametrize("K, Lam", [(K_DIAG, LAMBDA_DIAG), (K_SYM, LAMBDA_SYM)],
                         ids=["diagonal", "symmetric"])
def test_realisation_has_the_frequency_response_of_G(tmp_path, ell, K, Lam):
    d = fwdstep.load_diagram(harness(tmp_path, ell, K, Lam, CONSTANT_Y, CONSTANT_THETA))
    blocks = {b.name: b for b in d.blocks}
    for first, second, columns in (("ea/VY", "ea/W", 3), ("ea/VYth", "ea/GYth", 1)):
        A, B, C, D = series(matrices(blocks[first]), matrices(blocks[second]))
        assert A.shape[0] == (1 + ell + 1) * 2 * columns     # (pI+K)^-1, N/P per element
        assert np.all(np.linalg.eigvals(A).real < 0)
        np.testing.assert_array_equal(D, 0.0)                  # strictly proper: no loop
        for w in (0.0, 0.3, 1.0, 4.0, 25.0):
            H = C @ np.linalg.solve(1j * w * np.eye(A.shape[0]) - A, B)
            # C-order flattening of an (n, p) matrix: vec(G Y) = kron(G, I_p) vec(Y)
            expected = np.kron(G_of(w, ell, K, Lam), np.eye(columns))
            np.testing.assert_allclose(H, expected, rtol=1e-10, atol=1e-12)


def test_sinusoidal_steady_state_through_the_engine(tmp_path):
    """Y = Y0 sin(w t): after the transients, W = Im(G(jw) Y0 e^{jwt}) column by column."""
    ell, w = 2, 1.3
    Y0 = np.array([[1.0, 0.0, 2.0], [0.5, 1.0, -1.0]])
    y_source = ("  Y0: {type: Constant, value: " + str(Y0.tolist()) + "}\n"
                f"  sin: {{type: Sine, amplitude: 1, frequency: {w}}}\n"
                "  Y: {type: ScalarProduct, shape: [2, 3]}")
    path = harness(tmp_path, ell, K_SYM, LAMBDA_SYM, y_source, CONSTANT_THETA, t_final=14,
                   step=0.005)
    text = open(path).read().replace("connections:\n",
                                     "connections:\n  - sin.y -> Y.k\n  - Y0.y -> Y.u\n")
    open(path, "w").write(text)
    r = fwdstep.simulate(fwdstep.load_diagram(path))
    t = r.t[-1]
    expected = np.imag(G_of(w, ell, K_SYM, LAMBDA_SYM) @ Y0 * np.exp(1j * w * t))
    np.testing.assert_allclose(r["ea.W"][-1], expected, atol=1e-6)
    assert np.abs(expected).max() > 0.1


def _rich_sources():
    y_source = ("  Y0: {type: Constant, value: [[1, 0, 2], [0.5, 1, -1]]}\n"
                "  Y1: {type: Constant, value: [[0, 1, 0], [2, -1, 0.5]]}\n"
                "  s1: {type: Sine, amplitude: 1, frequency: 0.7}\n"
                "  s2: {type: Sine, amplitude: 2, frequency: 3.1, phase: 0.4}\n"
                "  p1: {type: ScalarProduct, shape: [2, 3]}\n"
                "  p2: {type: ScalarProduct, shape: [2, 3]}\n"
                "  Y: {type: Sum, signs: \"++\", shape: [2, 3]}")
    wiring = ("  - s1.y -> p1.k\n  - Y0.y -> p1.u\n  - s2.y -> p2.k\n  - Y1.y -> p2.u\n"
              "  - p1.y -> Y.u1\n  - p2.y -> Y.u2\n")
    return y_source, wiring


def _run_rich(tmp_path, theta_source, theta_wiring=""):
    y_source, wiring = _rich_sources()
    path = harness(tmp_path, 3, K_SYM, LAMBDA_SYM, y_source, theta_source, t_final=3,
                   step=0.002)
    text = open(path).read().replace("connections:\n", "connections:\n" + wiring + theta_wiring)
    open(path, "w").write(text)
    spec = load_spec(path)
    spec.log = None
    return fwdstep.simulate(fwdstep.structure.compiler.compile_spec(spec))


def _lsim_G(t, u, ell, K, Lam):
    """G(p) applied to u (T, 2, ...) from rest, with scipy: (pI+K)^-1, then Lambda, then N/P.

    lsim interpolates u linearly between samples: an error of about h^2 |u''| / 8."""
    num, den = polynomials(ell)
    flat = u.reshape(len(t), 2, -1)
    out = np.empty_like(flat)
    for c in range(flat.shape[2]):
        _, v, _ = signal.lsim((-np.asarray(K), np.eye(2), np.asarray(Lam), np.zeros((2, 2))),
                              flat[:, :, c], t)
        for i in range(2):
            _, out[:, i, c], _ = signal.lsim((num, den), v[:, i], t)
    return out.reshape(u.shape)


def test_W_and_h_match_an_independent_computation(tmp_path):
    theta = "  theta: {type: Sine, amplitude: [1, 0.5, 2], frequency: [0.5, 1.5, 2.5], offset: [0.2, 0, -1]}"
    r = _run_rich(tmp_path, theta)
    t, Y, th = r.t, r["Y.y"], r["theta.y"]
    W = _lsim_G(t, Y, 3, K_SYM, LAMBDA_SYM)
    GYth = _lsim_G(t, np.einsum("tij,tj->ti", Y, th), 3, K_SYM, LAMBDA_SYM)
    h = np.einsum("tij,tj->ti", W, th) - GYth
    scale = np.abs(W).max()
    np.testing.assert_allclose(r["ea.W"], W, atol=2e-5 * scale)
    np.testing.assert_allclose(r["ea.h"], h, atol=2e-5 * scale)
    assert np.abs(h).max() > 0.05 * scale          # a varying estimate gives a real h


def test_h_vanishes_for_a_constant_estimate(tmp_path):
    """[G(p) Y] theta - G(p)[Y theta] = 0 for constant theta (both filters start at rest)."""
    r = _run_rich(tmp_path, "  theta: {type: Constant, value: [0.7, -1.2, 2.5]}")
    W = r["ea.W"]
    assert np.abs(W).max() > 0.1
    np.testing.assert_allclose(r["ea.h"], 0.0, atol=1e-12 * np.abs(W).max())
