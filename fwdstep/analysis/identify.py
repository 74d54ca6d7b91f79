"""Parameter identification: least-squares estimate of a robot's parameters from a logged
run (q, qdot, tau), with filtered regressors so that qddot is never needed.

The robot obeys H(q) qddot + C(q, qdot) qdot + g(q) + F_v qdot = tau (F_v: per-joint
viscous friction, identified only with ``friction="viscous"``), linear in the parameters:
H zetad + C zeta + g = Y(q, qdot, zeta, zetad) theta (the diagram's regressor block, which
states exactly this, with a C satisfying Property 2: Hdot - 2C skew-symmetric, so
Hdot = C + C^T).  Written through the momentum H qdot,

    d/dt (M(q, qdot) theta) + N(q, qdot) theta = tau,
    M(q, v) = Y(q, 0, 0, v) - Y(q, 0, 0, 0)                 (H(q) v = M(q, v) theta)
    N(q, qdot) = G - sum_j qdot_j (Y(q, qdot, e_i, 0) - G)_j  (row i),  G = Y(q, qdot, 0, 0)
                                        (C qdot + g - Hdot qdot = g - C^T qdot)

so no acceleration appears, and no derivative of the regressor either: every term is the
block's own output (2 + 1 + n evaluations per sample, one batched call).  Property 2 is
checked at two samples against the exact Hdot qdot = sum_k dM/dq_k qdot_k
(``fwdstep.analysis.jacobian.BlockJacobian``); a regressor that violates it is refused.
With friction, N gains the columns diag(qdot) (parameters F_v, one per joint).  Both sides
go through the stable filter f(p) = lambda / (p + lambda) (zero initial state); since
f p w = lambda (w - f w) - lambda e^{-lambda t} w(0) exactly,

    Phi theta = tau_f,   Phi = lambda (M - M_f - e^{-lambda t} M(t_0)) + N_f,

one row per joint and logged time.  The filter runs on the logged samples, each step exact
for the cubic through four neighbouring samples (``exponential_filter``: O(h^4), so log
densely and do not log across a jump of tau).  ``theta = lstsq(Phi, tau_f)``; its columns'
singular values tell which parameters the run excites (``rank``: a rank-deficient Phi is
reported, the minimum-norm solution returned, and the directions not identified named).

Confidence intervals: the model is white noise of variance sigma^2 on the logged torques.
The filtered residuals are then F e (F the filter as a matrix over the samples), correlated
over about 1/lambda, so the plain OLS covariance sigma^2 (Phi^T Phi)^-1 would be far too
narrow.  The covariance is the exact sandwich sigma^2 (Phi^T Phi)^-1 Psi^T Psi
(Phi^T Phi)^-1 with Psi = F^T Phi (the adjoint filter, run backwards in time), and sigma^2
the residual sum of squares over its expectation's factor tr(F F^T) - tr((Phi^T Phi)^-1
Psi^T Psi); intervals theta +- z sigma_theta (normal quantile of the confidence level).
Noise on q and qdot enters the regressor nonlinearly (errors in variables): not covered,
it biases the estimate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fwdstep.core.errors import ConfigError

@dataclass
class Identification:
    """``theta`` (p,), ``std`` (p,), ``lower``/``upper`` (p,) at ``confidence``,
    ``residual_rms``, ``rank``, ``singular_values``, ``unidentified`` (unit directions of
    parameter space the run does not excite), ``bandwidth`` (lambda, rad/s), ``rows``,
    ``names``; ``truth`` (optional) covers the first len(truth) parameters (e.g. the
    regressor's, without the friction coefficients); ``notes``: why intervals are absent
    (NaN), if they are."""
    theta: np.ndarray
    std: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    confidence: float
    residual_rms: float
    rank: int
    singular_values: np.ndarray
    unidentified: np.ndarray
    bandwidth: float
    rows: int
    truth: np.ndarray | None = None
    names: list = field(default_factory=list)
    notes: list = field(default_factory=list)

    def to_dict(self) -> dict:
        out = {k: (v.tolist() if isinstance(v, np.ndarray) else v)
               for k, v in self.__dict__.items()}
        if self.truth is not None:
            k = len(self.truth)
            out["inside_interval"] = ((self.truth >= self.lower[:k]) &
                                      (self.truth <= self.upper[:k])).tolist()
            out["error"] = (self.theta[:k] - self.truth).tolist()
        return out


def _filter_plan(t: np.ndarray, lam: float):
    """(a, [(stencil start per step, weights)]) of ``exponential_filter``."""
    T = len(t)
    h = (t[-1] - t[0]) / (T - 1)
    if np.max(np.abs(np.diff(t) - h)) > 1e-6 * h:
        raise ConfigError("identification needs uniformly spaced log times (a fixed-step "
                          "run)")
    nodes, weights = np.polynomial.legendre.leggauss(8)
    s = 0.5 * h * (nodes + 1.0)
    kernel = 0.5 * h * weights * lam * np.exp(-lam * (h - s))

    def stencil(offsets):
        pts = np.asarray(offsets, dtype=float) * h
        c = []
        for j, pj in enumerate(pts):
            others = np.delete(pts, j)
            basis = np.prod([(s - o) / (pj - o) for o in others], axis=0)
            c.append(float(np.sum(kernel * basis)))
        return np.array(c)

    k = np.arange(T - 1)
    if T < 4:                          # too few samples for a cubic: linear between them
        return math.exp(-lam * h), k, stencil([0, 1]) * np.ones((T - 1, 1))
    lo = np.clip(k - 1, 0, T - 4)
    c = np.empty((T - 1, 4))
    c[:] = stencil([-1, 0, 1, 2])
    c[0] = stencil([0, 1, 2, 3])
    c[-1] = stencil([-2, -1, 0, 1])
    return math.exp(-lam * h), lo, c


def exponential_filter(t: np.ndarray, w: np.ndarray, lam: float,
                       adjoint: bool = False) -> np.ndarray:
    """z' = lam (w - z), z(t_0) = 0, over the samples (axis 0).  Each step is the exact
    solution for w equal to the cubic through four neighbouring samples (k-1 .. k+2,
    shifted at the ends): z_{k+1} = e^{-lam h} z_k + sum_j c_j w_{k+j}, the weights
    c_j = int_0^h lam e^{-lam (h - s)} l_j(s) ds of the Lagrange basis l_j by 8-point
    Gauss-Legendre (exact to round-off for lam h <= 1).  Local error O(h^5), global O(h^4).
    ``adjoint``: the transposed linear map (for the covariance of filtered noise)."""
    from scipy.signal import lfilter
    t = np.asarray(t, dtype=float)
    w = np.asarray(w, dtype=float)
    T = len(t)
    z = np.zeros_like(w)
    if T < 2:
        return z
    a, lo, c = _filter_plan(t, lam)
    n_c = c.shape[1]
    shape = (-1,) + (1,) * (w.ndim - 1)
    if not adjoint:
        u = sum(c[:, j].reshape(shape) * w[lo + j] for j in range(n_c))
        z[1:] = lfilter([1.0], [1.0, -a], u, axis=0)        # z_{k+1} = a z_k + u_k
        return z
    v = lfilter([1.0], [1.0, -a], w[1:][::-1], axis=0)[::-1]   # R^T: anti-causal
    for j in range(n_c):
        np.add.at(z, lo + j, c[:, j].reshape(shape) * v)
    return z


FRICTION = ("none", "viscous")


def _regressor(block):
    """The block's output port name, refusing blocks that are not Y(q, qdot, zeta, zetad)."""
    if list(block.inputs)[:4] != ["q", "qdot", "zeta", "zetad"] or len(block.outputs) != 1:
        raise ConfigError(f"block '{block.name}' ({block.type_name}) is not a regressor "
                          "Y(q, qdot, zeta, zetad) with one output")
    return next(iter(block.outputs))


def _evaluate(block, port, q, qdot, zeta, zetad) -> np.ndarray:
    """Y at B points (every argument (B, n)): (B, n, p)."""
    B = len(q)
    y = block.output(0.0, np.zeros((B, block.n_states)), (q, qdot, zeta, zetad))[0]
    return np.broadcast_to(y, (B,) + tuple(block.outputs[port].shape))


def _check_property2(block, port, q, qdot, M, N, samples) -> None:
    """N must equal Y(q, qdot, qdot, 0) - Hdot qdot with Hdot qdot = sum_k dM/dq_k qdot_k,
    the exact (or Richardson) Jacobian of the block: true iff Hdot = C + C^T along qdot."""
    from fwdstep.analysis.jacobian import BlockJacobian
    k = np.asarray(samples)
    qs, vs, zero = q[k], qdot[k], np.zeros_like(q[k])
    x = np.zeros((len(k), block.n_states))
    jac = BlockJacobian(block)
    out = f"y.{port}"
    dM = (jac.at(0.0, x, (qs, zero, zero, vs)).part(out, "u.q")
          - jac.at(0.0, x, (qs, zero, zero, zero)).part(out, "u.q"))      # (K, n p, n)
    Hdot = np.einsum("trk,tk->tr", dM, vs).reshape(M[k].shape)
    expected = _evaluate(block, port, qs, vs, vs, zero) - Hdot
    scale = max(float(np.abs(expected).max()), float(np.abs(M[k]).max()), 1e-300)
    worst = float(np.abs(N[k] - expected).max()) / scale
    if worst > 1e-6:
        raise ConfigError(f"block '{block.name}' ({block.type_name}): its C(q, qdot) does not "
                          f"satisfy Property 2 (Hdot = C + C^T; off by {worst:.2g} relative "
                          "at a logged sample), which identification's momentum form needs")


def regressor_terms(block, q: np.ndarray, qdot: np.ndarray, friction: str = "none") -> tuple:
    """M(q, qdot) and N(q, qdot) (module docstring), each (T, n, p), from the regressor
    block (inputs q, qdot, zeta, zetad; output Y (n, p)); ``friction="viscous"`` appends the
    n columns of F_v qdot (zero in M, diag(qdot) in N)."""
    port = _regressor(block)
    if friction not in FRICTION:
        raise ConfigError(f"friction '{friction}': expected one of {', '.join(FRICTION)}")
    T, n = q.shape
    zero = np.zeros_like(q)
    eye = np.broadcast_to(np.eye(n)[:, None, :], (n, T, n)).reshape(n * T, n)
    q_all = np.concatenate([q, q, q, np.tile(q, (n, 1))])
    v_all = np.concatenate([zero, zero, qdot, np.tile(qdot, (n, 1))])
    zeta_all = np.concatenate([zero, zero, zero, eye])
    zetad_all = np.concatenate([qdot, zero, zero, np.zeros((n * T, n))])
    Y = _evaluate(block, port, q_all, v_all, zeta_all, zetad_all)
    M = Y[:T] - Y[T:2 * T]
    G = Y[2 * T:3 * T]
    Ce = Y[3 * T:].reshape((n, T) + G.shape[1:]) - G[None]   # [i]: regressor of C e_i
    N = G - np.einsum("itjp,tj->tip", Ce, qdot)               # g - C^T qdot
    _check_property2(block, port, q, qdot, M, N,
                     sorted({int(np.argmax(np.abs(qdot).sum(axis=1))), T // 2}))
    if friction == "viscous":
        M = np.concatenate([M, np.zeros((T, n, n))], axis=2)
        N = np.concatenate([N, qdot[:, :, None] * np.eye(n)[None]], axis=2)
    return M, N


def parameter_names(block, friction: str = "none") -> list:
    """theta[0..p-1] of the regressor, then F_v[0..n-1] with viscous friction."""
    n, p = block.outputs[_regressor(block)].shape
    names = [f"theta[{i}]" for i in range(p)]
    return names + ([f"F_v[{i}]" for i in range(n)] if friction == "viscous" else [])


def filtered_regressor(t, q, qdot, block, bandwidth: float,
                       friction: str = "none") -> np.ndarray:
    """Phi (T, n, p) of the module docstring: the filtered momentum form."""
    t = np.asarray(t, dtype=float)
    q, qdot = (np.asarray(a, dtype=float).reshape(len(t), -1) for a in (q, qdot))
    lam = float(bandwidth)
    M, N = regressor_terms(block, q, qdot, friction)
    decay = np.exp(-lam * (t - t[0]))[:, None, None]
    return (lam * (M - exponential_filter(t, M, lam) - decay * M[0])
            + exponential_filter(t, N, lam))


def default_bandwidth(t) -> float:
    """min(20, 0.05 / log interval) rad/s."""
    return min(20.0, 0.05 / float(np.median(np.diff(np.asarray(t, dtype=float)))))


def _check_settings(bandwidth, confidence) -> None:
    """A filter that decays (lambda > 0, finite) and a confidence level in (0, 1): a
    negative lambda grows without bound, 0 filters nothing, a level outside (0, 1) has no
    normal quantile (NaN or empty intervals reported as a result)."""
    if bandwidth is not None and not (math.isfinite(float(bandwidth)) and bandwidth > 0):
        raise ConfigError(f"bandwidth {bandwidth!r}: the filter lambda/(p + lambda) needs a "
                          "finite lambda > 0 rad/s")
    if not (0.0 < float(confidence) < 1.0):
        raise ConfigError(f"confidence {confidence!r}: expected a level strictly between 0 "
                          "and 1 (e.g. 0.95)")


def _check_finite(t, arrays: dict) -> None:
    """Refuse a log holding NaN or infinities (a diverged run, a gap): least squares would
    fail in LAPACK or return NaN for every parameter."""
    for what, a in arrays.items():
        bad = ~np.isfinite(np.asarray(a, dtype=float).reshape(len(t), -1))
        if bad.any():
            k, j = np.argwhere(bad)[0]
            raise ConfigError(f"identification: the logged {what} is not finite at t = "
                              f"{t[k]:.6g} s (entry {j}, {int(bad.any(axis=1).sum())} "
                              "sample(s) in all); identify from a run without them")


def estimate(t, q, qdot, tau, block, bandwidth: float | None = None,
             confidence: float = 0.95, truth=None, friction: str = "none",
             signals: dict | None = None) -> Identification:
    """The least-squares estimate from logged arrays (module docstring); ``signals``: the
    names of q, qdot, tau for messages."""
    t = np.asarray(t, dtype=float)
    if len(t) < 3:
        raise ConfigError("identification needs at least 3 logged samples")
    _check_settings(bandwidth, confidence)
    label = {k: (f"{k} ({signals[k]})" if signals and signals.get(k) else k)
             for k in ("q", "qdot", "tau")}
    _check_finite(t, {"time": t, label["q"]: q, label["qdot"]: qdot, label["tau"]: tau})
    lam = float(bandwidth) if bandwidth is not None else default_bandwidth(t)
    Phi = filtered_regressor(t, q, qdot, block, lam, friction)
    return least_squares(t, Phi, tau, lam, confidence, truth,
                         parameter_names(block, friction))


def least_squares(t, Phi: np.ndarray, tau, bandwidth: float, confidence: float = 0.95,
                  truth=None, names=None) -> Identification:
    """theta = lstsq(Phi, f tau) and its intervals (module docstring), for a Phi of
    ``filtered_regressor`` (reusable for several torque records of one motion)."""
    from scipy.stats import norm
    t = np.asarray(t, dtype=float)
    _check_settings(bandwidth, confidence)
    lam = float(bandwidth)
    T, n, p = Phi.shape
    tau = np.asarray(tau, dtype=float).reshape(T, n)
    y = exponential_filter(t, tau, lam)
    A = Phi.reshape(T * n, p)
    b = y.reshape(T * n)
    theta, _, rank, sv = np.linalg.lstsq(A, b, rcond=None)
    r = (b - A @ theta).reshape(T, n)
    _, s, Vt = np.linalg.svd(A, full_matrices=False)
    tol = s.max() * max(A.shape) * np.finfo(float).eps if s.size else 0.0
    unidentified = Vt[s <= tol] if s.size else np.zeros((0, p))
    # white torque noise e (variance sigma^2): the filtered noise is F e, so
    # Cov(theta) = sigma^2 (A^T A)^-1 (F^T A)^T (F^T A) (A^T A)^-1, and
    # E |r|^2 = sigma^2 (tr(F F^T) - tr((A^T A)^-1 (F^T A)^T (F^T A)))
    Psi = exponential_filter(t, Phi, lam, adjoint=True).reshape(T * n, p)
    inv = np.linalg.pinv(A.T @ A)
    middle = Psi.T @ Psi
    impulse = np.zeros(T)
    impulse[min(3, T - 1)] = 1.0
    g = exponential_filter(t, impulse, lam)[min(3, T - 1):]
    trace_ffT = n * float(np.sum(np.cumsum(g * g)[:T]))
    trace_ffT += n * float(np.sum(g * g)) * max(0, T - len(g))
    dof = trace_ffT - float(np.trace(inv @ middle))
    notes = []
    if dof <= 1e-9 * trace_ffT:
        # the residual's expected size is not positive: the filtered samples are fewer
        # than the parameters (a run short against 1/lambda), so sigma is not estimable
        # (dividing by a clamped factor gave intervals of 1e144 reported as a result)
        sigma2 = math.nan
        notes.append(f"no intervals: the run's {T} samples filtered at lambda = {lam:g} "
                     f"rad/s leave no residual degrees of freedom for {p} parameters "
                     "(log a longer run, or raise --bandwidth)")
    else:
        sigma2 = float(np.sum(r * r)) / dof
    cov = sigma2 * inv @ middle @ inv
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    z = float(norm.ppf(0.5 + confidence / 2.0))
    return Identification(theta=theta, std=std, lower=theta - z * std, upper=theta + z * std,
                          confidence=confidence, residual_rms=float(np.sqrt(np.mean(r * r))),
                          rank=int(rank), singular_values=sv, unidentified=unidentified,
                          bandwidth=lam, rows=int(T * n),
                          truth=None if truth is None else np.asarray(truth, float).reshape(-1),
                          names=list(names) if names else [f"theta[{i}]" for i in range(p)],
                          notes=notes)


def _driver(d, block: str, port: str) -> str | None:
    for (blk, inp), (src, out) in d.structure.drivers.items():
        if blk == block and inp == port:
            return f"{src}.{out}"
    return None


def identify_run(run_dir: str, regressor: str, q=None, qdot=None, tau=None,
                 bandwidth=None, confidence: float = 0.95, truth=None,
                 friction: str = "none") -> tuple:
    """(``Identification``, the signal names used, the diagram) from a saved run directory
    (``fwdstep run D -o RUN``): the run's diagram is loaded again as it was run (its recorded
    copy and --set values, fwdstep.results.provenance), the
    regressor block taken from it, q/qdot default to the signals feeding the regressor's q
    and qdot inputs, tau to the input 'tau' of the block producing q; ``friction``: also
    estimate per-joint viscous friction ("viscous")."""
    from fwdstep.results.result import load_result
    from fwdstep.structure.compiler import load_diagram
    r = load_result(run_dir)
    path = r.stored.get("diagram")
    if not path:
        raise ConfigError(f"{run_dir}: the saved run names no diagram")
    prov = r.stored.get("provenance")
    if isinstance(prov, dict) and prov.get("diagram"):   # the copy of the diagram as run
        from fwdstep.results.provenance import recorded_diagram
        d = recorded_diagram(r.stored, run_dir)
    else:
        params = r.stored.get("parameters") or {}
        try:
            d = load_diagram(path, {k: v for k, v in params.items() if v is not None})
        except ConfigError:
            d = load_diagram(path)
    blocks = {b.name: b for b in d.blocks}
    if regressor not in blocks:
        raise ConfigError(f"--regressor '{regressor}': the run's diagram has no block "
                          f"'{regressor}'; blocks are: {', '.join(blocks)}", file=d.file)
    try:
        _regressor(blocks[regressor])
    except ConfigError as exc:
        raise ConfigError(f"--regressor: {exc}", file=d.file) from None
    q = q or _driver(d, regressor, "q")
    qdot = qdot or _driver(d, regressor, "qdot")
    if tau is None and q is not None:
        tau = _driver(d, q.rsplit(".", 1)[0], "tau")
    names = {"q": q, "qdot": qdot, "tau": tau}
    for what, sig in names.items():
        if sig is None:
            raise ConfigError(f"identification: no {what} signal is implied by the diagram "
                              f"(nothing drives it); pass --{what} SIGNAL, one of the "
                              f"run's logged signals: {', '.join(r.names)}", file=d.file)
        if sig not in r:
            raise ConfigError(f"identification needs the logged signal {what} "
                              f"('{sig}'); the run logged: {', '.join(r.names)}; run it with "
                              f"--set log=[{q}, {qdot}, {tau}] (and a dense log_every)",
                              file=d.file)
    if isinstance(truth, str):
        if truth not in r:
            raise ConfigError(f"--truth '{truth}' was not logged", file=d.file)
        values = np.asarray(r[truth], dtype=float).reshape(len(r.t), -1)
        moved = np.abs(values - values[0]).max(axis=0)
        if np.any(moved > 1e-12 * np.maximum(np.abs(values[0]), 1.0)):
            raise ConfigError(f"--truth '{truth}' changes during the run (by up to "
                              f"{moved.max():.3g}): the truth is a constant parameter "
                              "vector (e.g. the plant's arm.theta), not an estimate",
                              file=d.file)
        truth = values[0]
    p = len(parameter_names(blocks[regressor]))
    if truth is not None and np.size(truth) not in (p, len(parameter_names(blocks[regressor],
                                                                             friction))):
        raise ConfigError(f"--truth has {np.size(truth)} values; the regressor "
                          f"'{regressor}' has {p} parameters", file=d.file)
    ident = estimate(r.t, r[q], r[qdot], r[tau], blocks[regressor], bandwidth, confidence,
                     truth, friction, signals=names)
    return ident, names, d


__all__ = ["Identification", "estimate", "identify_run", "regressor_terms",
           "exponential_filter", "filtered_regressor", "least_squares", "parameter_names",
           "default_bandwidth", "FRICTION"]
