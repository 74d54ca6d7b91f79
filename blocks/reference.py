"""Reference dynamics of order ell + 1, realised by degree reduction (paper Sec. 3.2).

One mechanism covers eq. (2), (14), (16), (29) and (a1).  Per joint, with p = d/dt,

    p^(ell-1) (p + Lambda) z = c p^(ell+1) q_d - alpha_ell p^ell (q - sigma q_d)
                               - sum_{k<ell} alpha_k p^k (q - q_d) + Lambda p^ell q

and dividing by p^(ell-1) gives a realisation whose states are z and the multiple integrals
I_k = p^-k (q - q_d), k = 1..ell-1, which needs q, qdot, q_d (and qdot_d, qddot_d where the
variant uses them) only.  docs/reference-dynamics.md derives it and relates it to the paper's
schemes (13), (15), (17).
"""
from __future__ import annotations

from fractions import Fraction
from math import comb

import numpy as np

from fwdstep.core.block import Param
from fwdstep.core.errors import ParameterError
from fwdstep.core.linear import LinearBlock
from fwdstep.core.registry import register

from .linear import MAX_LINEAR_STATES

#: The largest accepted ell (the exact Hurwitz test and the float coefficients of a
#: critically damped polynomial, binom(61, 30) ~ 2e17, stay well-behaved up to here).
MAX_ELL = 60

#: variant -> (c, sigma, uses Lambda, input ports); see the module docstring.
VARIANTS = {
    "eq2": (0.0, 0.0, False, ("q", "qdot", "q_d")),
    "eq14": (0.0, 1.0, False, ("q", "qdot", "q_d", "qdot_d")),
    "eq16": (1.0, 1.0, False, ("q", "qdot", "q_d", "qdot_d", "qddot_d")),
    "eq29": (1.0, 1.0, True, ("q", "qdot", "q_d", "qdot_d", "qddot_d")),
}


def critically_damped(alpha: float, ell: int) -> np.ndarray:
    """alpha_0..alpha_ell of (w + alpha)^(ell+1): alpha_k = binom(ell+1, k) alpha^(ell+1-k)."""
    return np.array([comb(ell + 1, k) * alpha ** (ell + 1 - k) for k in range(ell + 1)],
                    dtype=float)


def time_scaled(alphas: np.ndarray, kappa: float) -> np.ndarray:
    """Remark 4: alpha_k -> alpha_k / kappa^(ell+1-k), which divides every root by kappa."""
    ell = len(alphas) - 1
    return np.array([a / kappa ** (ell + 1 - k) for k, a in enumerate(alphas)], dtype=float)


def polynomial_text(alphas: np.ndarray) -> str:
    """'w^3 + 1 w^2 - 2 w + 1' for alphas = [1, -2, 1] (alpha_0 first)."""
    ell = len(alphas) - 1
    text = f"w^{ell + 1}"
    for k in range(ell, -1, -1):
        a = alphas[k]
        power = f" w^{k}" if k >= 2 else (" w" if k == 1 else "")
        text += f" {'-' if a < 0 else '+'} {abs(a):g}{power}"
    return text


def is_hurwitz(alphas: np.ndarray) -> bool:
    """Exact Routh test of w^(ell+1) + alpha_ell w^ell + ... + alpha_0 on the given floats.

    The float coefficients are converted exactly to fractions, so the answer is not spoilt by
    round-off (numpy.roots of a 61-fold root scatters the roots by ~0.5 and can put some in
    the right half plane although the polynomial is Hurwitz).
    """
    coeffs = [Fraction(1)] + [Fraction(float(a)) for a in alphas[::-1]]
    if any(c <= 0 for c in coeffs):          # necessary condition, and cheap
        return False
    degree = len(coeffs) - 1
    width = degree // 2 + 1
    zero = Fraction(0)
    previous = (coeffs[0::2] + [zero] * width)[:width]
    current = (coeffs[1::2] + [zero] * width)[:width]
    for _ in range(degree - 1):
        if current[0] <= 0:
            return False
        ratio = previous[0] / current[0]
        following = [(previous[j + 1] if j + 1 < width else zero)
                     - ratio * (current[j + 1] if j + 1 < width else zero)
                     for j in range(width)]
        previous, current = current, following
    return current[0] > 0


def _marginal(r: complex) -> bool:
    return abs(r.real) <= 1e-9 * max(1.0, abs(r))


def _root_text(r: complex) -> str:
    real = 0.0 if _marginal(r) else r.real
    if abs(r.imag) <= 1e-4 * max(1.0, abs(r)):   # repeated roots scatter by ~eps^(1/m)
        return f"{real:.3g}"
    return f"{real:.3g}{r.imag:+.3g}j"


def check_hurwitz(name: str, alphas: np.ndarray) -> None:
    """Raise ParameterError naming the offending roots unless the polynomial is Hurwitz."""
    if is_hurwitz(alphas):
        return
    roots = np.roots(np.concatenate([[1.0], alphas[::-1]]))
    roots = sorted(roots, key=lambda r: (-r.real, -r.imag))
    bad = [r for r in roots if r.real >= 0 or _marginal(r)]
    if bad:
        listed = ", ".join(_root_text(r) for r in bad)
        verb = "has" if len(bad) == 1 else "have"
        why = f"root{'s' if len(bad) > 1 else ''} {listed} {verb} non-negative real part"
    else:  # unstable only in exact arithmetic: name the rightmost root numpy finds
        why = f"its rightmost root is {_root_text(roots[0])} (Routh test)"
    raise ParameterError(
        f"block '{name}': reference-dynamics polynomial {polynomial_text(alphas)} is not "
        f"Hurwitz: {why}", block=name)


def realisation(alphas: np.ndarray, lam: np.ndarray, c: float, sigma: float, n: int):
    """The degree-reduction realisation of the general reference dynamics.

    State x = [z, I_1, ..., I_{ell-1}] (each (n,)), I_k = p^-k (q - q_d):

        zdot  = -Lambda z + c qddot_d - alpha_ell (qdot - sigma qdot_d) + Lambda qdot
                - alpha_{ell-1} (q - q_d) - sum_{k=1}^{ell-1} alpha_{ell-1-k} I_k
        I_1'  = q - q_d,   I_k' = I_{k-1}  (k >= 2).

    Returns (A, B, C, D) in the form of ``LinearBlock.set_linear`` with the inputs q, qdot,
    q_d, qdot_d, qddot_d (the caller drops the inputs its variant does not declare).
    """
    ell = len(alphas) - 1
    N = n * ell
    eye = np.eye(n)
    row = slice(0, n)

    def at(k: int) -> slice:
        return slice(k * n, (k + 1) * n)

    A = np.zeros((N, N))
    A[row, row] = -lam
    for k in range(1, ell):
        A[row, at(k)] = -alphas[ell - 1 - k] * eye
    for k in range(2, ell):
        A[at(k), at(k - 1)] = eye
    B = {name: np.zeros((N, n)) for name in ("q", "qdot", "q_d", "qdot_d", "qddot_d")}
    B["q"][row] = -alphas[ell - 1] * eye
    B["q_d"][row] = alphas[ell - 1] * eye
    if ell >= 2:
        B["q"][at(1)] = eye
        B["q_d"][at(1)] = -eye
    B["qdot"][row] = lam - alphas[ell] * eye
    B["qdot_d"][row] = sigma * alphas[ell] * eye
    B["qddot_d"][row] = c * eye
    C = {"z": np.eye(n, N), "zdot": A[row].copy()}
    D = {("zdot", name): Bj[row].copy() for name, Bj in B.items()}
    return A, B, C, D


@register
class ReferenceDynamics(LinearBlock):
    """Reference dynamics (2)/(14)/(16)/(29)/(a1) of order ell+1, realised by degree reduction.

    Equation (per joint; Lambda = 0 except in eq29, where it is a symmetric positive definite
    matrix acting on the joint vector):

        d^ell z/dt^ell + Lambda d^(ell-1) z/dt^(ell-1)
            = c d^(ell+1) q_d/dt^(ell+1) - alpha_ell d^ell (q - sigma q_d)/dt^ell
              - sum_{k<ell} alpha_k d^k (q - q_d)/dt^k + Lambda d^ell q/dt^ell

    with (c, sigma) = (0, 0) for eq. (2), (0, 1) for eq. (14), (1, 1) for eq. (16) and
    eq. (29); eq. (a1) is eq29 with q_d* fed into q_d, qdot_d, qddot_d.  Dividing by
    p^(ell-1) gives the realisation (states z and I_k = p^-k (q - q_d), k = 1..ell-1)

        zdot = -Lambda z + c qddot_d - alpha_ell (qdot - sigma qdot_d) + Lambda qdot
               - alpha_{ell-1} (q - q_d) - sum_{k=1}^{ell-1} alpha_{ell-1-k} I_k,
        I_1' = q - q_d,  I_k' = I_{k-1},

    which needs q, qdot, q_d and the derivatives of q_d up to the second only
    (docs/reference-dynamics.md).  Initial state (from the inputs at t0): I_k = 0 and
    z = qdot_d - alpha_ell (q - q_d) (qdot_d = 0 in eq2), or z = z0 when given; an arm at
    rest on target stays at rest, and eq16 with ell = 1 is PID: z = qdot_d - alpha_1 dq -
    alpha_0 int dq.  State order: [z, I_1, ..., I_{ell-1}], each (n,).

    Ports:
        | port    | direction | shape | feedthrough |
        | q       | in        | (n,)  | -           |
        | qdot    | in        | (n,)  | -           |
        | q_d     | in        | (n,)  | -           |
        | qdot_d  | in        | (n,) (eq14, eq16, eq29) | - |
        | qddot_d | in        | (n,) (eq16, eq29) | - |
        | z       | out       | (n,)  | -           |
        | zdot    | out       | (n,)  | q, qdot, q_d, qdot_d, qddot_d (those declared) |

    Parameters:
        variant: eq2, eq14, eq16 or eq29 (which paper equation; decides the inputs).
        ell: the order parameter ell >= 1 (the dynamics have order ell+1), at most 60.
        n: number of joints.
        alphas: alpha_0..alpha_ell (alpha_0 first), w^(ell+1) + alpha_ell w^ell + ... +
            alpha_0 Hurwitz; or
        alpha: critically damped coefficients, alpha_k = binom(ell+1, k) alpha^(ell+1-k).
        kappa: Remark 4 time scale, alpha_k -> alpha_k / kappa^(ell+1-k) (roots / kappa);
            default 1.
        Lambda: eq29 only: positive scalar, (n,) positive diagonal, or (n, n) symmetric
            positive definite.
        z0: initial z, scalar or (n,) (default qdot_d(0) - alpha_ell (q(0) - q_d(0))).
    """

    params = {
        "variant": Param("choice", doc="paper equation: eq2, eq14, eq16 or eq29",
                         choices=tuple(VARIANTS)),
        "ell": Param("int", doc="order parameter ell >= 1 (dynamics of order ell+1)"),
        "n": Param("int", doc="number of joints"),
        "alphas": Param("array", default=None, doc="alpha_0..alpha_ell, alpha_0 first"),
        "alpha": Param("float", default=None, doc="critically damped: roots all at -alpha"),
        "kappa": Param("float", default=1.0, doc="Remark 4 time scale (roots divided by "
                       "kappa)"),
        "Lambda": Param("array", default=None, doc="eq29: scalar, (n,) or (n, n) symmetric "
                        "positive definite"),
        "z0": Param("array", default=None, doc="initial z (default qdot_d - alpha_ell dq)"),
    }
    example = {"variant": "eq29", "ell": 3, "n": 2, "alpha": 2.0, "kappa": 1.5,
               "Lambda": [[2.0, 0.5], [0.5, 1.0]]}
    init_from_inputs = True
    inspection_attributes = ("alphas",)   # sweeps may batch different alphas

    def setup(self, variant, ell, n, alphas, alpha, kappa, Lambda, z0):
        c, sigma, uses_lambda, inputs = VARIANTS[variant]
        if ell < 1:
            raise ParameterError(f"block '{self.name}' parameter 'ell' must be at least 1, "
                                 f"got {ell}", block=self.name)
        self.require_size("ell", ell, MAX_ELL)
        if n < 1:
            raise ParameterError(f"block '{self.name}' parameter 'n' must be at least 1, "
                                 f"got {n}", block=self.name)
        self.require_size("number of states n*ell", n * ell, MAX_LINEAR_STATES)
        alphas = self._coefficients(ell, alphas, alpha, kappa)
        lam = self._lambda(variant, uses_lambda, Lambda, n)
        A, B, C, D = realisation(alphas, lam, c, sigma, n)

        for name in inputs:
            self.declare_input(name, (n,))
        self.declare_output("z", (n,), feedthrough=())
        self.declare_output("zdot", (n,), feedthrough=inputs)
        self.set_linear(A, {k: B[k] for k in inputs}, C,
                        {key: Dk for key, Dk in D.items() if key[1] in inputs})
        self.state_labels = [f"z[{i}]" for i in range(n)] + [
            f"I{k}[{i}]" for k in range(1, ell) for i in range(n)]
        self.alphas = alphas               # for inspection; run time uses self.p only

        # run-time data for initial_state, uniform across variants so sweeps can stack them
        self.set_param("alpha_top", alphas[ell])
        self.set_param("use_z0", 0.0 if z0 is None else 1.0)
        self.set_param("z0", np.zeros(n) if z0 is None else self._vector("z0", z0, n))
        self._n = n
        self._ell = ell
        self._qdot_d = inputs.index("qdot_d") if "qdot_d" in inputs else None

    # ------------------------------------------------------------------ parameter checks
    def _coefficients(self, ell, alphas, alpha, kappa) -> np.ndarray:
        if (alphas is None) == (alpha is None):
            raise ParameterError(
                f"block '{self.name}' needs exactly one of 'alphas' (alpha_0..alpha_ell) or "
                f"'alpha' (critically damped), got {'both' if alpha is not None else 'neither'}",
                block=self.name)
        if not kappa > 0:
            raise ParameterError(f"block '{self.name}' parameter 'kappa' must be positive, "
                                 f"got {kappa:g}", block=self.name)
        if alphas is not None:
            alphas = np.asarray(alphas, dtype=float)
            if alphas.shape != (ell + 1,):
                raise ParameterError(
                    f"block '{self.name}' parameter 'alphas' must list alpha_0..alpha_ell, "
                    f"{ell + 1} numbers for ell = {ell}, got shape {alphas.shape}",
                    block=self.name)
        else:
            alphas = critically_damped(alpha, ell)
        with np.errstate(over="ignore"):
            alphas = time_scaled(alphas, kappa)
        if not np.all(np.isfinite(alphas)):
            raise ParameterError(
                f"block '{self.name}': reference-dynamics coefficients overflow for ell = "
                f"{ell} (alpha_0 = {alphas[0]:g}); use a smaller alpha or ell", block=self.name)
        if alpha is not None and alpha > 0:
            return alphas                  # (w + alpha/kappa)^(ell+1): Hurwitz by construction
        check_hurwitz(self.name, alphas)
        return alphas

    def _vector(self, key, value, n) -> np.ndarray:
        arr = np.asarray(value, dtype=float)
        if arr.ndim > 1 or arr.size not in (1, n):
            raise ParameterError(f"block '{self.name}' parameter '{key}' must be a number or "
                                 f"{n} numbers (n = {n}), got shape {arr.shape}",
                                 block=self.name)
        return np.broadcast_to(arr, (n,)).copy()

    def _lambda(self, variant, uses_lambda, Lambda, n) -> np.ndarray:
        if not uses_lambda:
            if Lambda is not None:
                raise ParameterError(
                    f"block '{self.name}' parameter 'Lambda' is only used by variant eq29, "
                    f"not {variant}", block=self.name)
            return np.zeros((n, n))
        if Lambda is None:
            raise ParameterError(
                f"block '{self.name}' variant eq29 needs parameter 'Lambda' (a positive number, "
                f"{n} positive numbers, or a symmetric positive definite {n}x{n} matrix)",
                block=self.name)
        L = np.asarray(Lambda, dtype=float)
        if L.ndim <= 1:
            diag = self._vector("Lambda", L, n)
            if np.any(diag <= 0):
                raise ParameterError(
                    f"block '{self.name}' parameter 'Lambda' must be positive definite; its "
                    f"diagonal is {', '.join(f'{d:g}' for d in diag)}", block=self.name)
            return np.diag(diag)
        if L.shape != (n, n):
            raise ParameterError(f"block '{self.name}' parameter 'Lambda' has shape {L.shape}, "
                                 f"expected ({n}, {n}) for n = {n}", block=self.name)
        asym = float(np.max(np.abs(L - L.T)))
        if asym > 1e-12 * max(1.0, float(np.max(np.abs(L)))):
            raise ParameterError(f"block '{self.name}' parameter 'Lambda' must be symmetric; "
                                 f"max |Lambda - Lambda^T| = {asym:g}", block=self.name)
        L = 0.5 * (L + L.T)
        eig = np.linalg.eigvalsh(L)
        if eig[0] <= 0:
            raise ParameterError(
                f"block '{self.name}' parameter 'Lambda' must be positive definite; its "
                f"eigenvalues are {', '.join(f'{e:.3g}' for e in eig)}", block=self.name)
        return L

    # ------------------------------------------------------------------ run time
    def initial_state(self, t0, u):
        """I_k = 0; z = z0 if given, else qdot_d(t0) - alpha_ell (q(t0) - q_d(t0))."""
        p = self.p
        z = -p.alpha_top[:, None] * (u[0] - u[2])
        if self._qdot_d is not None:
            z = z + u[self._qdot_d]
        z = np.where(p.use_z0[:, None] > 0, p.z0, z)
        x = np.zeros((z.shape[0], self.n_states))
        x[:, :self._n] = z
        return x
