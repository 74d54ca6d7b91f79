"""ReferenceDynamics against the paper's equations (2), (14), (16), (29) as written.

The block is fed analytic signals q(t), q_d(t) (sums of sinusoids and polynomials with exact
derivatives of every order) and integrated with a small RK4 loop (h = 2e-3).  Two checks:

1. The equation itself: d^ell z + Lambda d^(ell-1) z equals the paper's right-hand side,
   with d^k z taken exactly from the realisation,
       z^(k) = C A^k x + sum_{i<k} C A^(k-1-i) B u^(i),
   and the input derivatives u^(i) analytic (A, B, C read off through derivative/output).
2. Independently, the high-order ODE as written, in companion form in z..z^(ell-1), solved
   by solve_ivp (DOP853, rtol 1e-11) from the block's initial derivatives: z(t) agrees to
   1e-8 relative (measured <= 1.4e-10).
"""
from __future__ import annotations

from math import comb, factorial

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fwdstep.blocks.reference import ReferenceDynamics, is_hurwitz
from fwdstep.structure.compiler import stack_blocks
from fwdstep.core.errors import ParameterError

N_JOINTS = 2
T_END = 2.0
STEP = 2e-3
LAMBDA_FULL = np.array([[3.0, 1.0], [1.0, 2.0]])
#: input port -> (signal, derivative order)
PORTS = {"q": ("q", 0), "qdot": ("q", 1), "q_d": ("q_d", 0), "qdot_d": ("q_d", 1),
         "qddot_d": ("q_d", 2)}


class Analytic:
    """f(t) = sum_i a_i sin(w_i t + phi_i) + sum_j c_j t^j per joint, any derivative exactly."""

    def __init__(self, amp, freq, phase, poly):
        self.amp, self.freq, self.phase = (np.asarray(v, dtype=float) for v in (amp, freq, phase))
        self.poly = np.asarray(poly, dtype=float)          # (degree+1, n), c_0 first

    def d(self, k: int, t: float) -> np.ndarray:
        """The k-th derivative at t, shape (n,)."""
        trig = (self.amp * self.freq ** k
                * np.sin(self.freq * t + self.phase + k * np.pi / 2)).sum(0)
        return trig + self._poly_derivative(k, t)

    def _poly_derivative(self, k, t):
        if k >= len(self.poly):
            return 0.0
        cache = self.__dict__.setdefault("_cache", {})
        if k not in cache:   # c_j j!/(j-k)!, j >= k, highest power first for polyval
            cache[k] = np.array([c * factorial(j) / factorial(j - k)
                                 for j, c in enumerate(self.poly) if j >= k])[::-1]
        coeffs = cache[k]
        out = coeffs[0]
        for c in coeffs[1:]:
            out = out * t + c
        return out

    def integral(self, t: float) -> np.ndarray:
        """int_0^t f."""
        trig = (self.amp / self.freq * (np.cos(self.phase) - np.cos(self.freq * t + self.phase))
                ).sum(0)
        return trig + sum(c * t ** (j + 1) / (j + 1) for j, c in enumerate(self.poly))


Q_D = Analytic(amp=[[0.8, -0.5], [0.3, 0.4]], freq=[[0.7, 1.1], [1.3, 0.6]],
               phase=[[0.2, 1.0], [-0.4, 0.5]], poly=[[0.3, -0.2], [0.2, 0.1]])
Q = Analytic(amp=[[0.8, -0.5], [0.3, 0.4], [0.15, 0.1]],
             freq=[[0.7, 1.1], [1.3, 0.6], [0.9, 1.7]],
             phase=[[0.2, 1.0], [-0.4, 0.5], [1.2, -0.3]],
             poly=[[0.5, -0.1], [0.2, 0.1], [0.05, -0.08]])


def make(variant, ell, lam=None, **extra):
    """A block with distinct-root coefficients for odd ell, critically damped for even."""
    if "alpha" not in extra and "alphas" not in extra:
        if ell % 2:
            roots = -np.array([1.0, 1.3, 1.7, 2.1, 2.6, 3.0][:ell + 1])
            extra["alphas"] = np.poly(roots)[1:][::-1]
        else:
            extra.update(alpha=1.2, kappa=0.8)
    if lam is not None:
        extra["Lambda"] = lam
    return ReferenceDynamics("ref", variant=variant, ell=ell, n=N_JOINTS, **extra)


def signals_for(blk, q, q_d, k=0):
    """The k-th time derivative of every input of ``blk``, as a function of t."""
    sig = {"q": q, "q_d": q_d}
    return lambda t: tuple(sig[PORTS[name][0]].d(PORTS[name][1] + k, t)[None]
                           for name in blk.inputs)


def rk4(blk, u_of_t, x0, t_end=T_END, h=STEP):
    n_steps = int(round(t_end / h))
    ts = np.linspace(0.0, n_steps * h, n_steps + 1)
    xs = [x0]
    x = x0
    for i in range(n_steps):
        t = ts[i]
        k1 = blk.derivative(t, x, u_of_t(t))
        k2 = blk.derivative(t + h / 2, x + h / 2 * k1, u_of_t(t + h / 2))
        k3 = blk.derivative(t + h / 2, x + h / 2 * k2, u_of_t(t + h / 2))
        k4 = blk.derivative(t + h, x + h * k3, u_of_t(t + h))
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        xs.append(x)
    return ts, np.concatenate(xs)


def realisation_of(blk):
    """A, {input: B_j}, C_z of the block, read off through derivative() and output()."""
    n = blk.n_states
    zero_u = tuple(np.zeros((1,) + p.shape) for p in blk.inputs.values())
    eye = np.eye(n)
    A = np.stack([blk.derivative(0.0, eye[i:i + 1], zero_u)[0] for i in range(n)], 1)
    C = np.stack([blk.output(0.0, eye[i:i + 1], zero_u)[0][0] for i in range(n)], 1)
    B = {}
    for j, name in enumerate(blk.inputs):
        cols = []
        for m in range(N_JOINTS):
            u = list(zero_u)
            u[j] = np.eye(N_JOINTS)[m][None]
            cols.append(blk.derivative(0.0, np.zeros((1, n)), tuple(u))[0])
        B[name] = np.stack(cols, 1)
    return A, B, C


def z_derivatives(blk, x, t, q, q_d, orders, matrices=None):
    """{k: z^(k)(t)} exactly from the realisation and the analytic input derivatives."""
    A, B, C = matrices or realisation_of(blk)
    out = {}
    for k in orders:
        zk = C @ np.linalg.matrix_power(A, k) @ x
        for i in range(k):
            ui = signals_for(blk, q, q_d, i)(t)
            Bu = sum(B[name] @ ui[j][0] for j, name in enumerate(blk.inputs))
            zk = zk + C @ np.linalg.matrix_power(A, k - 1 - i) @ Bu
        out[k] = zk
    return out


def coefficients_of(blk, ell):
    """alpha_0..alpha_ell read back from the realisation (variant without Lambda)."""
    A, B, _ = realisation_of(blk)
    n = N_JOINTS
    alphas = np.empty(ell + 1)
    alphas[ell] = -B["qdot"][0, 0]
    alphas[ell - 1] = -B["q"][0, 0]
    for k in range(1, ell):
        alphas[ell - 1 - k] = -A[0, k * n]
    return alphas


def paper_rhs(variant, alphas, lam, q, q_d, t):
    """The right-hand side of (2)/(14)/(16)/(29) with Lambda z^(ell-1) moved to the left."""
    ell = len(alphas) - 1

    def dq(k):
        return q.d(k, t) - q_d.d(k, t)

    if variant == "eq2":       # -alpha_ell q^(ell) - alpha_{ell-1} dq^(ell-1) - ... - alpha_0 dq
        return -alphas[ell] * q.d(ell, t) - sum(alphas[k] * dq(k) for k in range(ell))
    rhs = -sum(alphas[k] * dq(k) for k in range(ell + 1))
    if variant in ("eq16", "eq29"):
        rhs = rhs + q_d.d(ell + 1, t)
    if variant == "eq29":      # + Lambda d^(ell-1)/dt^(ell-1) qdot
        rhs = rhs + lam @ q.d(ell, t)
    return rhs


CASES = ([(v, ell, None) for v in ("eq2", "eq14", "eq16") for ell in range(1, 6)]
         + [("eq29", ell, lam) for ell in range(1, 6) for lam in ("scalar", "full")])


def lambda_of(kind):
    return {None: (None, np.zeros((N_JOINTS, N_JOINTS))),
            "scalar": (2.5, 2.5 * np.eye(N_JOINTS)),
            "full": (LAMBDA_FULL, LAMBDA_FULL)}[kind]


@pytest.mark.parametrize("variant, ell, lam_kind", CASES)
def test_block_satisfies_the_paper_equation_and_the_high_order_ode(variant, ell, lam_kind):
    lam_param, lam = lambda_of(lam_kind)
    blk = make(variant, ell, lam_param)
    alphas = blk.alphas
    u0 = signals_for(blk, Q, Q_D)(0.0)
    x0 = blk.initial_state(0.0, u0)
    ts, xs = rk4(blk, signals_for(blk, Q, Q_D), x0)
    matrices = realisation_of(blk)
    z_block = xs @ matrices[2].T

    # 1. the equation as written, at 21 times along the run (measured <= 1e-13 relative)
    for i in range(0, len(ts), 50):
        d = z_derivatives(blk, xs[i], ts[i], Q, Q_D, (ell - 1, ell), matrices)
        lhs = d[ell] + lam @ d[ell - 1]
        rhs = paper_rhs(variant, alphas, lam, Q, Q_D, ts[i])
        scale = max(1.0, np.abs(rhs).max(), np.abs(d[ell]).max())
        assert np.max(np.abs(lhs - rhs)) < 1e-11 * scale, (ts[i], lhs, rhs)

    # 2. the high-order ODE, companion form y = (z, z', ..., z^(ell-1)), from the same start
    init = z_derivatives(blk, x0[0], 0.0, Q, Q_D, range(ell), matrices)
    y0 = np.concatenate([init[k] for k in range(ell)])
    n = N_JOINTS

    def companion(t, y):
        dy = np.empty_like(y)
        dy[:-n] = y[n:]
        dy[-n:] = -lam @ y[-n:] + paper_rhs(variant, alphas, lam, Q, Q_D, t)
        return dy

    sol = solve_ivp(companion, (0.0, ts[-1]), y0, method="DOP853", t_eval=ts,
                    rtol=1e-11, atol=1e-12)
    assert sol.success
    z_ode = sol.y[:n].T
    scale = max(1.0, np.abs(z_ode).max())
    assert np.max(np.abs(z_block - z_ode)) < 1e-8 * scale


def paper_scheme(variant, alphas, lam, x, v):
    """The paper's degree-reduction schemes (13), (15), (17) as printed (and their eq29
    analogue from docs/reference-dynamics.md): states x_1 = z, x_2, ..., x_ell (rows of x).

    (13): x_j' = x_{j+1} - alpha_{ell+1-j} qdot + alpha_{ell-j} q_d,  x_ell' = -alpha_1 qdot
          - alpha_0 dq;  (15)/(17): x_j' = x_{j+1} - alpha_{ell+1-j} dqdot, x_ell' = -alpha_1
          dqdot - alpha_0 dq, plus qddot_d in x_1' for (17); (29): plus -Lambda z + Lambda qdot.
    """
    ell = len(alphas) - 1
    dq, dqdot = v["q"] - v["q_d"], v["qdot"] - v.get("qdot_d", 0.0)
    dx = np.empty_like(x)
    for j in range(1, ell + 1):                     # paper index j = 1..ell
        nxt = x[j] if j < ell else -alphas[0] * dq
        if variant == "eq2":
            drive = -alphas[ell + 1 - j] * v["qdot"] + (alphas[ell - j] * v["q_d"] if j < ell
                                                         else 0.0)
        else:
            drive = -alphas[ell + 1 - j] * dqdot
        dx[j - 1] = nxt + drive
    if variant in ("eq16", "eq29"):
        dx[0] += v["qddot_d"]
    if variant == "eq29":
        dx[0] += -lam @ x[0] + lam @ v["qdot"]
    return dx


def paper_coordinates(variant, alphas, x_block, q, q_d):
    """Our state (z, I_1..I_{ell-1}) -> the paper's (x_1..x_ell): x_1 = z and
    x_{j+1} = -alpha_{ell-j} e - sum_{m=1}^{ell-j} alpha_{ell-j-m} I_m, e = q (eq2) or dq."""
    ell = len(alphas) - 1
    z_and_I = x_block.reshape(ell, N_JOINTS)
    e = q if variant == "eq2" else q - q_d
    rows = [z_and_I[0]]
    for j in range(1, ell):
        rows.append(-alphas[ell - j] * e
                    - sum(alphas[ell - j - m] * z_and_I[m] for m in range(1, ell - j + 1)))
    return np.stack(rows)


@pytest.mark.parametrize("variant", ["eq2", "eq14", "eq16", "eq29"])
@pytest.mark.parametrize("ell", [1, 2, 4])
def test_paper_schemes_13_15_17_are_the_block_in_other_coordinates(variant, ell):
    """Integrate the paper's printed scheme next to the block: same z, and the paper's states
    are our states under the documented change of coordinates, all along the run."""
    lam_param, lam = (LAMBDA_FULL, LAMBDA_FULL) if variant == "eq29" else (None, 0 * np.eye(2))
    blk = make(variant, ell, lam_param)
    alphas = blk.alphas
    sig = {"q": Q, "q_d": Q_D}
    names = ("q", "qdot", "q_d", "qdot_d", "qddot_d")

    def values(t):
        return {name: sig[PORTS[name][0]].d(PORTS[name][1], t) for name in names}

    def joint(t, xx):
        u = tuple(values(t)[name][None] for name in blk.inputs)
        ours = blk.derivative(t, xx[None, :blk.n_states], u)[0]
        theirs = paper_scheme(variant, alphas, lam, xx[blk.n_states:].reshape(ell, N_JOINTS),
                              values(t))
        return np.concatenate([ours, theirs.ravel()])

    v0 = values(0.0)
    x0 = blk.initial_state(0.0, tuple(v0[name][None] for name in blk.inputs))[0]
    xx = np.concatenate([x0, paper_coordinates(variant, alphas, x0, v0["q"], v0["q_d"]).ravel()])
    h = 2 * STEP
    for i in range(int(round(T_END / h))):
        t = i * h
        k1 = joint(t, xx)
        k2 = joint(t + h / 2, xx + h / 2 * k1)
        k3 = joint(t + h / 2, xx + h / 2 * k2)
        k4 = joint(t + h, xx + h * k3)
        xx = xx + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        if i % 50 == 49:
            vt = values(t + h)
            mapped = paper_coordinates(variant, alphas, xx[:blk.n_states], vt["q"], vt["q_d"])
            theirs = xx[blk.n_states:].reshape(ell, N_JOINTS)
            assert np.max(np.abs(mapped - theirs)) < 1e-9 * max(1.0, np.abs(theirs).max())


@pytest.mark.parametrize("variant", ["eq2", "eq14", "eq16", "eq29"])
@pytest.mark.parametrize("ell", [1, 3, 5])
def test_arm_at_rest_on_target_stays_at_rest(variant, ell):
    blk = make(variant, ell, LAMBDA_FULL if variant == "eq29" else None)
    target = np.array([[0.7, -1.2]])
    zero = np.zeros((1, N_JOINTS))
    values = {"q": target, "q_d": target, "qdot": zero, "qdot_d": zero, "qddot_d": zero}
    u = tuple(values[name] for name in blk.inputs)
    x0 = blk.initial_state(0.0, u)
    z, zdot = blk.output(0.0, x0, u)
    assert np.all(x0 == 0) and np.all(z == 0) and np.all(zdot == 0)
    assert np.all(blk.derivative(0.0, x0, u) == 0)


@pytest.mark.parametrize("variant", ["eq2", "eq14", "eq16", "eq29"])
def test_perfect_tracking_gives_the_closed_form_z(variant):
    """q = q_d(t) exactly: I_k stay 0 and z is q_d' (eq16, eq29), q_d'(0) (eq14) or
    -alpha_ell (q_d(t) - q_d(0)) (eq2)."""
    ell = 3
    blk = make(variant, ell, 2.0 if variant == "eq29" else None)
    x0 = blk.initial_state(0.0, signals_for(blk, Q_D, Q_D)(0.0))
    ts, xs = rk4(blk, signals_for(blk, Q_D, Q_D), x0)
    z = xs[:, :N_JOINTS]
    if variant in ("eq16", "eq29"):
        expected = np.array([Q_D.d(1, t) for t in ts])
    elif variant == "eq14":
        expected = np.broadcast_to(Q_D.d(1, 0.0), z.shape)
    else:
        expected = -blk.alphas[ell] * np.array([Q_D.d(0, t) - Q_D.d(0, 0.0) for t in ts])
    assert np.max(np.abs(z - expected)) < 1e-9
    assert np.max(np.abs(xs[:, N_JOINTS:])) < 1e-12


def test_eq16_with_ell_1_is_textbook_pid():
    """K_D zdot = K_D qddot_d - K_P dq' - K_I dq (22) with zero initial integral:
    z = qdot_d - (K_P/K_D) dq - (K_I/K_D) int_0^t dq."""
    K_D, K_P, K_I = 2.0, 10.0, 8.0
    blk = ReferenceDynamics("pid", variant="eq16", ell=1, n=N_JOINTS, alphas=[K_I / K_D, K_P / K_D])
    assert blk.n_states == N_JOINTS
    x0 = blk.initial_state(0.0, signals_for(blk, Q, Q_D)(0.0))
    ts, xs = rk4(blk, signals_for(blk, Q, Q_D), x0)
    pid = np.array([Q_D.d(1, t) - K_P / K_D * (Q.d(0, t) - Q_D.d(0, t))
                    - K_I / K_D * (Q.integral(t) - Q_D.integral(t)) for t in ts])
    assert np.max(np.abs(xs - pid)) < 1e-9


def test_z0_overrides_the_default_initial_z():
    blk = make("eq16", 2, z0=[0.5, -0.25])
    x0 = blk.initial_state(0.0, signals_for(blk, Q, Q_D)(0.0))
    assert np.array_equal(x0, [[0.5, -0.25, 0.0, 0.0]])


def test_batched_sweep_over_coefficients_and_z0():
    """Variants stacked by the engine's stack_blocks run as one batch, each as if alone."""
    singles = [make("eq29", 3, 2.0, alpha=1.0), make("eq29", 3, LAMBDA_FULL, alpha=2.0),
               make("eq29", 3, 1.0, alpha=1.5, z0=[1.0, 2.0])]
    stacked = stack_blocks([[make("eq29", 3, 2.0, alpha=1.0)],
                            [make("eq29", 3, LAMBDA_FULL, alpha=2.0)],
                            [make("eq29", 3, 1.0, alpha=1.5, z0=[1.0, 2.0])]])[0]
    u = signals_for(singles[0], Q, Q_D)(0.3)
    x = stacked.initial_state(0.3, u)
    assert x.shape == (3, stacked.n_states)
    x = x + np.random.default_rng(0).standard_normal(x.shape)
    dx = stacked.derivative(0.3, x, u)
    outs = stacked.output(0.3, x, u)
    for b, single in enumerate(singles):
        assert np.allclose(dx[b], single.derivative(0.3, x[b:b + 1], u)[0], atol=1e-12)
        for o, os in zip(outs, single.output(0.3, x[b:b + 1], u)):
            assert np.allclose(o[b], os[0], atol=1e-12)
    x0 = stacked.initial_state(0.3, u)
    for b, single in enumerate(singles):
        assert np.allclose(x0[b], single.initial_state(0.3, u)[0], atol=1e-14)


# --------------------------------------------------------------------------- coefficients
@pytest.mark.parametrize("ell", [1, 2, 4, 7])
@pytest.mark.parametrize("kappa", [1.0, 2.5])
def test_critically_damped_coefficients_are_binomial(ell, kappa):
    alpha = 1.7
    blk = make("eq16", ell, alpha=alpha, kappa=kappa)
    expected = np.poly(np.full(ell + 1, -alpha / kappa))[1:][::-1]   # (w + alpha/kappa)^(ell+1)
    got = coefficients_of(blk, ell)
    assert np.allclose(got, expected, rtol=1e-12, atol=0)
    assert np.allclose(got, [comb(ell + 1, k) * (alpha / kappa) ** (ell + 1 - k)
                             for k in range(ell + 1)], rtol=1e-12, atol=0)


@pytest.mark.parametrize("ell", [1, 3, 5])
def test_kappa_divides_the_roots(ell):
    roots = np.array([-1.0, -2.0, -0.5 + 1.0j, -0.5 - 1.0j, -3.0, -0.7][:ell + 1])
    alphas = np.real(np.poly(roots))[1:][::-1]
    kappa = 2.5
    blk = make("eq14", ell, alphas=alphas, kappa=kappa)
    got = np.roots(np.concatenate([[1.0], coefficients_of(blk, ell)[::-1]]))
    key = lambda r: (round(r.real, 6), round(r.imag, 6))       # noqa: E731
    assert np.allclose(sorted(got, key=key), sorted(roots / kappa, key=key), atol=1e-9)


def test_high_order_critically_damped_is_accepted_up_to_the_limit():
    blk = make("eq16", 60, alpha=1.0)
    assert blk.n_states == 60 * N_JOINTS
    assert is_hurwitz(blk.alphas)   # exact Routh test on the float coefficients
    with pytest.raises(ParameterError) as err:
        make("eq16", 61, alpha=1.0)
    assert str(err.value) == "block 'ref': ell = 61 is larger than the limit 60"


def test_exact_hurwitz_test():
    assert is_hurwitz(np.array([1.0, 1.0]))                 # w^2 + w + 1
    assert is_hurwitz(np.array([1.0, 2.0, 2.0]))            # (w+1)(w^2+w+1)
    assert not is_hurwitz(np.array([1.0, 1.0, 1.0]))        # roots +-j
    assert not is_hurwitz(np.array([2.0, 1.0, 1.0]))        # w^3+w^2+w+2: RHP pair
    assert not is_hurwitz(np.array([0.0, 1.0, 1.0]))        # root at 0


# --------------------------------------------------------------------------- refusals
@pytest.mark.parametrize("params, message", [
    (dict(alphas=[1.0, -2.0, 1.0]),
     "block 'ref': reference-dynamics polynomial w^3 + 1 w^2 - 2 w + 1 is not Hurwitz: roots "
     "0.574+0.369j, 0.574-0.369j have non-negative real part"),
    (dict(alphas=[1.0, 0.0, 1.0]),
     "block 'ref': reference-dynamics polynomial w^3 + 1 w^2 + 0 w + 1 is not Hurwitz: roots "
     "0.233+0.793j, 0.233-0.793j have non-negative real part"),
    (dict(alphas=[0.0, 1.0, 1.0]),
     "block 'ref': reference-dynamics polynomial w^3 + 1 w^2 + 1 w + 0 is not Hurwitz: root 0 "
     "has non-negative real part"),
    (dict(alphas=[1.0, 1.0, 1.0], kappa=2.0),   # the time-scaled polynomial is reported
     "block 'ref': reference-dynamics polynomial w^3 + 0.5 w^2 + 0.25 w + 0.125 is not "
     "Hurwitz: roots 0+0.5j, 0-0.5j have non-negative real part"),
    (dict(alpha=-1.0, ell=1),
     "block 'ref': reference-dynamics polynomial w^2 - 2 w + 1 is not Hurwitz: roots 1, 1 have "
     "non-negative real part"),
    (dict(alphas=[1.0, 2.0]),
     "block 'ref' parameter 'alphas' must list alpha_0..alpha_ell, 3 numbers for ell = 2, got "
     "shape (2,)"),
    (dict(alphas=[1.0, 2.0, 2.0], alpha=1.0),
     "block 'ref' needs exactly one of 'alphas' (alpha_0..alpha_ell) or 'alpha' (critically "
     "damped), got both"),
    (dict(), "block 'ref' needs exactly one of 'alphas' (alpha_0..alpha_ell) or 'alpha' "
             "(critically damped), got neither"),
    (dict(alpha=1.0, kappa=0.0), "block 'ref' parameter 'kappa' must be positive, got 0"),
    (dict(alpha=1.0, Lambda=1.0), "block 'ref' parameter 'Lambda' is only used by variant "
                                  "eq29, not eq16"),
    (dict(variant="eq29", alpha=1.0),
     "block 'ref' variant eq29 needs parameter 'Lambda' (a positive number, 2 positive "
     "numbers, or a symmetric positive definite 2x2 matrix)"),
    (dict(variant="eq29", alpha=1.0, Lambda=[[1.0, 0.5], [0.0, 1.0]]),
     "block 'ref' parameter 'Lambda' must be symmetric; max |Lambda - Lambda^T| = 0.5"),
    (dict(variant="eq29", alpha=1.0, Lambda=[[1.0, 2.0], [2.0, 1.0]]),
     "block 'ref' parameter 'Lambda' must be positive definite; its eigenvalues are -1, 3"),
    (dict(variant="eq29", alpha=1.0, Lambda=[1.0, -1.0]),
     "block 'ref' parameter 'Lambda' must be positive definite; its diagonal is 1, -1"),
    (dict(variant="eq29", alpha=1.0, Lambda=np.eye(3)),
     "block 'ref' parameter 'Lambda' has shape (3, 3), expected (2, 2) for n = 2"),
    (dict(alpha=1.0, z0=[1.0, 2.0, 3.0]),
     "block 'ref' parameter 'z0' must be a number or 2 numbers (n = 2), got shape (3,)"),
    (dict(alpha=1.0, ell=0), "block 'ref' parameter 'ell' must be at least 1, got 0"),
])
def test_bad_parameters_are_refused_with_exact_messages(params, message):
    full = {"variant": "eq16", "ell": 2, "n": N_JOINTS, **params}
    with pytest.raises(ParameterError) as err:
        ReferenceDynamics("ref", **full)
    assert str(err.value) == message
