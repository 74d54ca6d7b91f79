"""Explicit fixed-step Runge-Kutta methods as Butcher-tableau data.

One generic stepper runs any of them: ``rk_step`` states the procedure once, from the
step plan the generated program and the compiled loop are also made of.  Each method documents its
order; ``tests/fwdstep/test_solvers.py`` fits the slope of log(error) against log(step) to
prove it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Tableau:
    name: str
    order: int
    a: tuple      # lower-triangular stage coefficients a[i][j], j < i
    b: tuple
    c: tuple

    @property
    def stages(self) -> int:
        return len(self.b)

    def check(self) -> None:
        """Consistency: c_i = sum_j a_ij and sum b = 1."""
        for i, row in enumerate(self.a):
            assert abs(sum(row) - self.c[i]) < 1e-15
        assert abs(sum(self.b) - 1.0) < 1e-15


TABLEAUX = {
    # forward Euler, order 1
    "euler": Tableau("euler", 1, a=((),), b=(1.0,), c=(0.0,)),
    # Heun's method (explicit trapezoid), order 2
    "heun": Tableau("heun", 2, a=((), (1.0,)), b=(0.5, 0.5), c=(0.0, 1.0)),
    # the classical Runge-Kutta method, order 4
    "rk4": Tableau("rk4", 4, a=((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0)),
                   b=(1 / 6, 1 / 3, 1 / 3, 1 / 6), c=(0.0, 0.5, 0.5, 1.0)),
}


def amplification(tableau: Tableau, z):
    """The stability function R(z) = 1 + z b^T (I - z A)^-1 1 of an explicit tableau at the
    complex numbers ``z``: one step of y' = lambda y multiplies y by R(h lambda).  For an
    explicit method it is the polynomial 1 + sum_k z^k b^T A^(k-1) 1 (A strictly lower
    triangular, so (I - z A)^-1 = sum_k (z A)^k ends at k = stages - 1)."""
    s = tableau.stages
    A = np.zeros((s, s))
    for i, row in enumerate(tableau.a):
        A[i, :len(row)] = row
    b = np.asarray(tableau.b)
    coeffs, v = [1.0], np.ones(s)
    for _ in range(s):
        coeffs.append(float(b @ v))
        v = A @ v
    z = np.asarray(z, dtype=complex)
    r = np.zeros_like(z)
    for c in reversed(coeffs):                  # Horner
        r = r * z + c
    return r


def stable_step(tableau: Tableau, lam: complex) -> float:
    """The largest step h with |R(h' lam)| <= 1 for every 0 < h' <= h: how far the ray
    through ``lam`` (Re lam < 0) stays in the method's stability region (rk4 on the
    negative real axis: 2.785293563405282 / |lam|).  Found by scanning the ray and
    bisecting its first exit to 1e-12 relative."""
    lam = complex(lam)
    if lam.real >= 0.0 or lam == 0:
        return math.inf
    unit = lam / abs(lam)
    radius = np.linspace(0.0, 8.0, 4001)[1:]  # every explicit region up to 4 stages lies in |z| < 8
    outside = np.abs(amplification(tableau, radius * unit)) > 1.0 + 1e-12
    if not outside.any():
        return math.inf
    k = int(np.argmax(outside))
    lo, hi = (radius[k - 1] if k else 0.0), radius[k]
    while hi - lo > 1e-12 * hi:
        mid = 0.5 * (lo + hi)
        if abs(amplification(tableau, mid * unit)) > 1.0 + 1e-12:
            hi = mid
        else:
            lo = mid
    return lo / abs(lam)


#: adaptive methods of scipy.integrate.solve_ivp (``fwdstep.run.ivp``): name -> scipy's name.
#: dop853: explicit Runge-Kutta of order 8 (Dormand-Prince), for checking a fixed-step run
#: against a tight tolerance; radau: implicit Runge-Kutta (Radau IIA) of order 5, for stiff
#: diagrams; lsoda: switches between Adams and BDF (ODEPACK) as stiffness comes and goes.
IVP_METHODS = {"dop853": "DOP853", "radau": "Radau", "lsoda": "LSODA"}


def step_plan(tableau: Tableau, h: float):
    """Precomputed, zero-free coefficient lists for one step of size h:
    ``stages[i] = (c_i*h, [(j, h*a_ij), ...])`` for i >= 1, and ``[(j, h*b_j), ...]``."""
    stages = []
    for i in range(1, tableau.stages):
        stages.append((tableau.c[i] * h,
                       [(j, h * a) for j, a in enumerate(tableau.a[i]) if a != 0.0]))
    final = [(j, h * b) for j, b in enumerate(tableau.b) if b != 0.0]
    return stages, final


def rk_step(f, t: float, x: np.ndarray, plan, k: list) -> np.ndarray:
    """One step of the procedure (``fwdstep.run.simulate``) from (t, x) with a step plan
    (``step_plan``): ``k[0] = f(t, x)``, ``k[i] = f(t + c_i h, x + sum_j h a_ij k_j)`` with the
    sums in the plan's order, and the new state ``x + sum_j h b_j k_j`` (a new array; x is
    not changed).  The generated program (``fwdstep.run.program``) and the compiled loop
    are made from the same plan and sum in the same order: the same numbers."""
    stages, final = plan
    k[0] = f(t, x)
    for s, (ch, coeffs) in enumerate(stages, start=1):
        xi = x.copy()
        for j, a in coeffs:
            xi += a * k[j]
        k[s] = f(t + ch, xi)
    for j, b in final:
        x = x + b * k[j]
    return x


def integrate_ode(f, x0, t_final: float, h: float, method: str = "rk4") -> np.ndarray:
    """Integrate ``x' = f(t, x)`` with a fixed step: ``rk_step``, the procedure of
    ``fwdstep.simulate``, for tests and for users who need a plain ODE."""
    tab = TABLEAUX[method]
    plan = step_plan(tab, h)
    x = np.array(x0, dtype=float)
    k = [None] * tab.stages
    for i in range(int(round(t_final / h))):
        x = rk_step(f, i * h, x, plan, k)
    return x
