"""Gradient adaptation laws for the parameter estimates of the forwardstepping controllers."""
from __future__ import annotations

import numpy as np

from fwdstep.core import kernelops as ko
from fwdstep.core.block import MAX_SIGNAL_SIZE, Block, Param, as_written
from fwdstep.core.errors import ParameterError
from fwdstep.core.registry import register


@register
class AdaptationLaw(Block):
    """Gradient adaptation law: theta_hat' = -Gamma W^T e, integrated from theta_hat(0) = theta0.

    Equations (5), (58), (89), (105): W is the (n, p) regressor (Y in (5), W or W* in
    (58), (89), (105)) and e the (n,) error it is driven by (s in (5), Delta qdot +
    alpha* Delta q in (58)); the estimate theta_hat has p entries and Gamma is a positive
    scalar, a positive diagonal given as p numbers, or a (p, p) symmetric positive
    definite matrix.  With ``regressor_shape: [n]`` the block is the scalar law of
    eqs. (88), (111), (112), (120): W is an (n,) vector, theta_hat a scalar and
    theta_hat' = -gamma W^T e with a positive scalar gamma.

    Ports:
        | port      | direction | shape          | feedthrough |
        | W         | in        | (n, p) or (n,) | -           |
        | e         | in        | (n,)           | -           |
        | theta_hat | out       | (p,) or ()     | -           |

    Projection (the standard robust-adaptive modification), onto a box or a ball:

    * box, with ``lower`` and/or ``upper``: theta_hat stays in lower <= theta_hat <= upper:
      an entry that reaches a bound stops there (its update is zeroed) until the update
      points back inside; the state is theta_hat followed by one mode per entry (0 inside,
      -1 at lower, +1 at upper);
    * ball, with ``radius`` (and ``center``, default 0): theta_hat stays in
      ||theta_hat - c|| <= r (Ioannou & Sun, Robust Adaptive Control, sec. 4.4.2, the
      projection of the gradient law onto g(theta) = ||theta - c||^2 - r^2 <= 0): with
      tau = -Gamma W^T e the unprojected update and d = theta_hat - c (the outward normal),

          theta_hat' = tau                                  inside, or on the sphere with
                                                            d^T tau <= 0 (pointing inward)
          theta_hat' = tau - Gamma d (d^T tau) / (d^T Gamma d)   on the sphere, d^T tau > 0

      (for Gamma = gamma I: tau less its outward normal component; d^T theta_hat' = 0, so
      theta_hat slides along the sphere).  The state is theta (p) and one mode (0 inside,
      1 on the sphere); while on the sphere theta_hat = c + r d / ||d|| (the state put
      back on the sphere, so the estimate never leaves the ball by integration drift).

    Reaching and leaving the boundary are zero crossings located in time
    (docs/writing-blocks.md).

    Parameters:
        regressor_shape: [n, p] for a matrix regressor (estimate of p parameters), or [n]
            for a vector regressor (scalar estimate).
        gamma: adaptation gain Gamma: a positive number, p positive numbers (diagonal), or a
            (p, p) symmetric positive definite matrix; a positive number for [n].
        theta0: initial estimate theta_hat(0): one number for every entry, or p numbers.
        lower: projection box, lower bound (a number or p numbers; default none).
        upper: projection box, upper bound (a number or p numbers; default none).
        radius: projection ball, its radius r > 0 (default none; not with a box).
        center: projection ball, its center c (a number or p numbers; default 0).
    """

    params = {
        "regressor_shape": Param("array", doc="shape of W: [n, p] (matrix) or [n] (vector)"),
        "gamma": Param("array", 1.0, "adaptation gain: scalar, (p,) diagonal or (p, p) SPD"),
        "theta0": Param("array", 0.0, "initial estimate: scalar or (p,)"),
        "lower": Param("array", None, "projection: lower bound of theta_hat (default none)"),
        "upper": Param("array", None, "projection: upper bound of theta_hat (default none)"),
        "radius": Param("float", None, "projection: ball radius r (default none)"),
        "center": Param("array", 0.0, "projection: ball center c (default 0)"),
    }
    shape_from = {"regressor_shape": ("W",)}
    example = {"regressor_shape": [2, 4], "gamma": [[2.0, 0.5, 0, 0], [0.5, 1.0, 0, 0],
                                                    [0, 0, 1.0, 0], [0, 0, 0, 3.0]],
               "theta0": [1.0, 0.5, 0.2, 0.1]}

    def setup(self, regressor_shape, gamma, theta0, lower=None, upper=None, radius=None,
              center=0.0):
        shape = np.atleast_1d(np.asarray(regressor_shape))
        if shape.ndim != 1 or shape.size not in (1, 2) or np.any(shape < 1) \
                or np.any(shape != np.floor(shape)):
            raise ParameterError(f"block {self.name!r} parameter 'regressor_shape' must be [n, p] "
                                 f"or [n] with positive whole numbers, got {shape.tolist()}",
                                 block=self.name)
        n = self.require_size("n (regressor rows)", int(shape[0]), MAX_SIGNAL_SIZE)
        self._vector = shape.size == 1
        p = 1 if self._vector else self.require_size("p (parameters)", int(shape[1]), 10_000)
        self.require_size("n * p (regressor size)", n * p, MAX_SIGNAL_SIZE)

        G = np.asarray(gamma, dtype=float)

        def bad(what: str) -> ParameterError:
            # say what is wrong with the value, not only what is expected
            return ParameterError(f"block {self.name!r} parameter 'gamma' {what} (it must be a "
                                  f"positive number, {p} positive numbers, or a symmetric "
                                  f"positive definite {p}x{p} matrix)", block=self.name)
        if G.size == 1 and G.ndim <= 2:
            G = G.reshape(())
        if G.ndim == 0 or G.ndim == 1:
            if G.ndim == 1 and G.shape != (p,):
                raise bad(f"has {G.size} numbers, not 1 or {p}")
            if np.any(G <= 0.0):
                if G.ndim == 0:
                    raise bad(f"is {as_written(G)}, not positive")
                k = int(np.flatnonzero(G <= 0.0)[0])
                raise bad(f"entry {k + 1} is {as_written(G[k])}, not positive")
            self._matrix_gain = False
            self.set_param("gamma", np.broadcast_to(G, (1,)) if G.ndim == 0 else G)  # (1, 1|p)
        elif G.shape == (p, p):
            if not np.allclose(G, G.T, rtol=0.0, atol=1e-12 * np.max(np.abs(G))):
                raise bad("is not symmetric")
            try:
                np.linalg.cholesky(G)
            except np.linalg.LinAlgError:
                raise bad("is symmetric but not positive definite") from None
            self._matrix_gain = True
            self.set_param("gamma_T", G.T)                                        # (1, p, p)
        else:
            raise bad(f"is an array of shape {'x'.join(map(str, G.shape))}, not {p}x{p}")

        t0 = np.asarray(theta0, dtype=float)
        if t0.size == 1:
            t0 = np.full(p, float(t0.reshape(())))
        elif t0.shape != (p,):
            raise ParameterError(f"block {self.name!r} parameter 'theta0' must be a number or "
                                 f"{p} numbers, got shape {t0.shape}", block=self.name)

        self.declare_input("W", (n,) if self._vector else (n, p))
        self.declare_input("e", (n,))
        self.declare_output("theta_hat", () if self._vector else (p,), feedthrough=(),
                            label=r"$\hat\theta$")
        self._p = p
        self._box = lower is not None or upper is not None
        self._ball = radius is not None
        labels = ["theta_hat"] if self._vector else [f"theta_hat[{k}]" for k in range(p)]
        if self._box and self._ball:
            raise ParameterError(f"block {self.name!r}: one projection, a box ('lower', "
                                 "'upper') or a ball ('radius', 'center'), not both",
                                 block=self.name)
        if self._ball:
            c = np.asarray(center, dtype=float)
            if c.size not in (1, p):
                raise ParameterError(f"block {self.name!r} parameter 'center' must be a "
                                     f"number or {p} numbers, got shape {c.shape}",
                                     block=self.name)
            c = np.broadcast_to(c.reshape(-1), (p,))
            if not radius > 0:
                raise ParameterError(f"block {self.name!r} parameter 'radius' must be "
                                     f"positive, got {radius}", block=self.name)
            dist = float(np.linalg.norm(t0 - c))
            if dist > radius:
                raise ParameterError(f"block {self.name!r} needs theta0 in the ball: "
                                     f"||theta0 - center|| = {dist:.6g} > radius {radius:g}",
                                     block=self.name)
            self.set_param("center", c)
            self.set_param("radius", [radius])
            self.declare_state(p + 1, np.concatenate((t0, [0.0])))
            self.state_labels = labels + ["mode"]
            self.declare_zero_crossings(("ball",), 1)
        elif self._box:
            lo = np.broadcast_to(np.asarray(-np.inf if lower is None else lower, dtype=float),
                                 (p,))
            hi = np.broadcast_to(np.asarray(np.inf if upper is None else upper, dtype=float),
                                 (p,))
            if np.any(lo > hi) or np.any(t0 < lo) or np.any(t0 > hi):
                raise ParameterError(f"block {self.name!r} needs lower <= theta0 <= upper, got "
                                     f"{lo.tolist()}, {t0.tolist()}, {hi.tolist()}",
                                     block=self.name)
            self.set_param("lower", lo)
            self.set_param("upper", hi)
            self.declare_state(2 * p, np.concatenate((t0, np.zeros(p))))
            self.state_labels = labels + [f"mode[{k}]" for k in range(p)]
            self.declare_zero_crossings(("lower", "upper"), p)
        else:
            self.declare_state(p, t0)
            self.state_labels = labels
        self.finalize(1)

    def finalize(self, batch: int) -> None:
        kind = self._kind()
        gain = "gamma_T" if self._matrix_gain else "gamma"
        if self._ball:
            self.set_kernels(output=(adaptation_ball_output_scalar if kind == 0
                                     else adaptation_ball_output),
                             derivative=adaptation_ball_derivative,
                             params=(gain, "center", "radius"), static=(self._p, kind))
        elif self._box:
            self.set_kernels(output=(adaptation_box_output_scalar if kind == 0
                                     else adaptation_box_output),
                             derivative=adaptation_box_derivative,
                             params=(gain, "lower", "upper"),
                             static=(self._p, kind))
        elif self._vector:
            self.set_kernels(output=adaptation_scalar_output,
                             derivative=adaptation_vector_derivative, params=("gamma",))
        elif self._matrix_gain:
            self.set_kernels(output=adaptation_output, derivative=adaptation_matrix_derivative,
                             params=("gamma_T",))
        else:
            self.set_kernels(output=adaptation_output, derivative=adaptation_derivative,
                             params=("gamma",))


    def _update(self, t, x, u):
        """The unprojected theta_hat' (B, p)."""
        gain = self.p.gamma_T if self._matrix_gain else self.p.gamma
        return _base_update(t, x[:, :self._p], u[0], u[1], gain, self._kind())

    def zero_crossings(self, t, x, u):
        if self._ball:
            return self._ball_guards(t, x, u)
        return self._box_guards(t, x, u)

    def crossed(self, t, x, u, which):
        if self._ball:
            return self._ball_crossed(t, x, u, which)
        return self._box_crossed(t, x, u, which)

    def _ball_guards(self, t, x, u):
        """ball: r - ||theta - c|| while inside (reaches the sphere where it falls through
        0); -d^T tau while on the sphere (leaves it where the update turns inward)."""
        p, kind = self._p, self._kind()
        gain = self.p.gamma_T if self._matrix_gain else self.p.gamma
        th = ball_point(x, self.p.center, self.p.radius, p)
        d = th - self.p.center
        tau = _base_update(t, th, u[0], u[1], gain, kind)
        inside = self.p.radius - np.sqrt(np.sum(d * d, axis=1, keepdims=True))
        return np.where(x[:, p:p + 1] > 0.5, -np.sum(d * tau, axis=1, keepdims=True), inside)

    def _ball_crossed(self, t, x, u, which):
        """Reached the sphere: held on it; the update turned inward: free.  Either way the
        estimate starts from the sphere exactly."""
        p = self._p
        th = ball_point(np.concatenate((x[:, :p], np.ones_like(x[:, p:])), axis=1),
                        self.p.center, self.p.radius, p)
        mode = np.where(x[:, p:] > 0.5, 0.0, 1.0)
        new = np.concatenate((th, mode), axis=1)
        return np.where(which, new, x)

    def _kind(self) -> int:
        return 0 if self._vector else (2 if self._matrix_gain else 1)

    def _box_guards(self, t, x, u):
        """lower: theta - lower while inside, the update while held there (leaves when it
        turns positive); upper: upper - theta while inside, -update while held there."""
        p = self._p
        th, m = x[:, :p], x[:, p:]
        upd = self._update(t, x, u)
        g_lo = np.where(m < -0.5, upd, th - self.p.lower)
        g_hi = np.where(m > 0.5, -upd, self.p.upper - th)
        return np.concatenate((g_lo, g_hi), axis=1)

    def _box_crossed(self, t, x, u, which):
        p = self._p
        th, m = x[:, :p].copy(), x[:, p:].copy()
        lo = np.broadcast_to(self.p.lower, th.shape)
        hi = np.broadcast_to(self.p.upper, th.shape)
        w_lo, w_hi = which[:, :p], which[:, p:]
        free = np.abs(m) < 0.5
        hit_lo, hit_hi = w_lo & free, w_hi & free
        left = (w_lo & (m < -0.5)) | (w_hi & (m > 0.5))
        th = np.where(hit_lo, lo, np.where(hit_hi, hi, th))
        m = np.where(hit_lo, -1.0, np.where(hit_hi, 1.0, np.where(left, 0.0, m)))
        return np.concatenate((th, m), axis=1)


# ---------------------------------------------------------------- kernels (one definition)
def _like_state(dx, x):
    """dx with the state's batch length (when only the state is batched)."""
    if dx.shape[0] != x.shape[0]:
        return dx + np.zeros_like(x)
    return dx


def adaptation_output(t, x, W, e, gamma):
    """theta_hat = x."""
    return (x,)


def adaptation_scalar_output(t, x, W, e, gamma):
    """theta_hat = x (one parameter, a scalar signal)."""
    return (x[:, 0],)


def adaptation_vector_derivative(t, x, W, e, gamma):
    """theta_hat' = -gamma W . e (one parameter: W is a vector)."""
    return _like_state(-gamma * np.sum(W * e, axis=1).reshape((-1, 1)), x)


def adaptation_derivative(t, x, W, e, gamma):
    """theta_hat' = -gamma_i (W^T e)_i (diagonal gain)."""
    return _like_state(-gamma * ko.bvecmat(e, W), x)


def adaptation_matrix_derivative(t, x, W, e, gamma_T):
    """theta_hat' = -Gamma W^T e (symmetric positive definite gain)."""
    return _like_state(-ko.bvecmat(ko.bvecmat(e, W), gamma_T), x)


def _base_update(t, x, W, e, gain, kind):
    """The law's theta_hat' for the estimates x (B, p): kind 0 scalar, 1 diagonal, 2 matrix."""
    if kind == 0:
        return adaptation_vector_derivative(t, x, W, e, gain)
    if kind == 1:
        return adaptation_derivative(t, x, W, e, gain)
    return adaptation_matrix_derivative(t, x, W, e, gain)


def adaptation_box_output(t, x, W, e, gain, lower, upper, p, kind):
    """theta_hat = the first p states (the estimates; the modes follow)."""
    return (x[:, :p].copy(),)


def adaptation_box_output_scalar(t, x, W, e, gain, lower, upper, p, kind):
    """theta_hat, a scalar signal (kind 0; one kernel per output rank, so numba types each)."""
    return (x[:, 0].copy(),)


def adaptation_box_derivative(t, x, W, e, gain, lower, upper, p, kind):
    """theta_hat' = the law's update where the entry is inside the box (mode 0), 0 where it
    is held at a bound; the modes change only at crossings."""
    upd = _base_update(t, x[:, :p], W, e, gain, kind)
    dx = np.zeros(x.shape)
    dx[:, :p] = np.where(np.abs(x[:, p:]) < 0.5, upd, 0.0)
    return dx


# ---------------------------------------------------------------- the ball projection
def _times_gain(v, gain, kind):
    """Gamma v (B, p): scalar or diagonal gain times v, or the (p, p) gain (gamma_T)."""
    if kind == 2:
        return ko.bvecmat(v, gain)
    return gain * v


def ball_point(x, center, radius, p):
    """theta_hat (B, p): the state's estimate, put on the sphere c + r d / ||d|| while it is
    held there (mode x[:, p] = 1)."""
    th = x[:, :p]
    d = th - center
    norm = np.sqrt(np.sum(d * d, axis=1)).reshape((-1, 1))
    on = center + radius * d / np.maximum(norm, 1e-300)
    return np.where(x[:, p:p + 1] > 0.5, on, th)


def adaptation_ball_output(t, x, W, e, gain, center, radius, p, kind):
    """theta_hat = the estimate, on the sphere while held there."""
    return (ball_point(x, center, radius, p),)


def adaptation_ball_output_scalar(t, x, W, e, gain, center, radius, p, kind):
    """theta_hat, a scalar signal (kind 0; one kernel per output rank)."""
    return (ball_point(x, center, radius, p)[:, 0].copy(),)


def adaptation_ball_derivative(t, x, W, e, gain, center, radius, p, kind):
    """theta_hat' = tau inside; on the sphere tau - Gamma d (d^T tau) / (d^T Gamma d), the
    update with its outward component removed (Ioannou & Sun's projection); mode' = 0."""
    th = ball_point(x, center, radius, p)
    tau = _base_update(t, th, W, e, gain, kind)
    d = th - center
    gd = _times_gain(d + np.zeros_like(tau), gain, kind)
    num = np.sum(d * tau, axis=1).reshape((-1, 1))
    den = np.sum(d * gd, axis=1).reshape((-1, 1))
    projected = tau - gd * (num / np.maximum(den, 1e-300))
    dx = np.zeros((max(x.shape[0], tau.shape[0]), x.shape[1]))
    dx[:, :p] = np.where(x[:, p:p + 1] > 0.5, projected, tau)
    return dx
