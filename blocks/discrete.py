"""Discrete-time blocks: sample and hold, unit delay, z-domain state space and transfer functions.

Every block here samples at ``t_k = offset + k * period`` (k = 0, 1, ...).  Its discrete
state is part of the diagram's state vector, with zero derivative, and changes only at the
sample instants, through ``update`` applied between Runge-Kutta steps (``fwdstep.run.events``):
the simulator ends a step exactly at every sample instant.  Outputs are functions of the
discrete state alone, so they are exactly piecewise constant, right-continuous, and no
output feeds through in continuous time; at a sample instant the new states are computed
from inputs that already see this instant's updates of other discrete blocks (a
ZeroOrderHold feeding a DiscreteStateSpace passes the sample of t_k, not of t_{k-1}).
Semantics in full: docs/discrete-time.md.
"""
from __future__ import annotations

import numpy as np

from fwdstep.core.block import Block, Param
from fwdstep.core.errors import ParameterError
from fwdstep.core.instants import sample_instants
from fwdstep.core.linear import observer_form
from fwdstep.core.registry import register

from .linear import MAX_ORDER, initial_values, polynomial, signal_shape

SAMPLING = {
    "period": Param("float", doc="sample period T [s] (> 0)"),
    "offset": Param("float", default=0.0, doc="first sample instant [s] (>= 0; default 0)"),
}


# ---------------------------------------------------------------------------- kernels
def held_output(t, x, u, template):
    """y = the held value, the first ``template`` elements of the state, in the port's
    shape (``template`` is a (1, *shape) array of zeros)."""
    size = template.size
    return (np.ascontiguousarray(x[:, :size]).reshape((x.shape[0],) + template.shape[1:]),)


def held_output_tail(t, x, u, template):
    """y = the last ``template.size`` elements of the state, in the port's shape."""
    size = template.size
    return (np.ascontiguousarray(x[:, x.shape[1] - size:]).reshape((x.shape[0],)
                                                                    + template.shape[1:]),)


def no_change(t, x, u, template):
    """Discrete states do not move between samples: dx/dt = 0."""
    return np.zeros_like(x)


def dss_update(x, u, A, B, C, D):
    """[x_d; y] <- [A x_d + B u; C x_d + D u]: x (batch, n + p), u (batch, m)."""
    n = A.shape[1]
    xd = x[:, :n]
    xnew = np.matmul(A, xd[:, :, None])[:, :, 0] + np.matmul(B, u[:, :, None])[:, :, 0]
    y = np.matmul(C, xd[:, :, None])[:, :, 0] + np.matmul(D, u[:, :, None])[:, :, 0]
    return np.concatenate((np.broadcast_to(xnew, y.shape[:1] + xnew.shape[1:]),
                           np.broadcast_to(y, xnew.shape[:1] + y.shape[1:])), axis=1)


class _Sampled(Block):
    """Shared: the sampling parameters and the sample instants."""

    discrete = True
    samples_through = True           # y after the update at t_k is made from u(t_k)

    def _sampling(self, period: float, offset: float) -> None:
        if not period > 0:
            raise ParameterError(f"block '{self.name}' parameter 'period' must be positive, got "
                                 f"{period:g}", block=self.name)
        if not offset >= 0:
            raise ParameterError(f"block '{self.name}' parameter 'offset' must be >= 0, got "
                                 f"{offset:g}", block=self.name)
        self.period, self.offset = float(period), float(offset)

    def discontinuities(self, t_final):
        return sample_instants(self, self.period, self.offset, t_final)


@register
class ZeroOrderHold(_Sampled):
    """Zero-order hold: samples its input every `period` seconds and holds it.

    Equation: y(t) = u(t_k) for t_k <= t < t_{k+1}, t_k = offset + k period; y(t) = initial
    before the first sample.  At t_k the sample sees the inputs' values at t_k (right limits,
    after this instant's updates of other discrete blocks).  State: the held value m, with
    dm/dt = 0 and m <- u(t_k) at each sample.

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | shape | -           |

    Parameters:
        period: sample period T [s].
        offset: first sample instant [s] (default 0).
        shape: shape of the signal (list; [] or omitted for a scalar).
        initial: output before the first sample (default 0), broadcast to shape.
    """

    params = {**SAMPLING,
              "shape": Param("array", default=None, doc="signal shape, e.g. [2]; default scalar"),
              "initial": Param("array", default=None, doc="output before the first sample")}
    shape_from = {"shape": ("u", "y")}          # may be left out: the wiring fixes it
    example = {"period": 0.01, "shape": [2], "initial": [0.5, -0.5]}

    def setup(self, period, offset, shape, initial):
        self._sampling(period, offset)
        shape = signal_shape(self, "shape", shape)
        self.declare_input("u", shape)
        self.declare_output("y", shape, feedthrough=())
        self.declare_state(int(np.prod(shape, dtype=np.int64)),
                           initial_values(self, initial, shape, "the signal's shape"))
        self.set_param("template", np.zeros(shape))
        self.set_kernels(output=held_output, derivative=no_change, params=("template",))

    def update(self, t, x, u):
        return u[0].reshape(u[0].shape[0], -1)


@register
class UnitDelay(_Sampled):
    """Unit delay z^-1: outputs the input's previous sample.

    Equation: y(t) = u(t_{k-1}) for t_k <= t < t_{k+1} (t_k = offset + k period), y = initial
    before the second sample.  State: [held output y_k, stored sample u_k]; at each t_k:
    y_k <- u_{k-1}, u_k <- u(t_k).

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | shape | -           |

    Parameters:
        period: sample period T [s].
        offset: first sample instant [s] (default 0).
        shape: shape of the signal (list; [] or omitted for a scalar).
        initial: u_{-1}, the output until the second sample (default 0), broadcast to shape.
    """

    samples_through = False          # y after t_k is u(t_{k-1})

    params = {**SAMPLING,
              "shape": Param("array", default=None, doc="signal shape, e.g. [2]; default scalar"),
              "initial": Param("array", default=None, doc="output until the second sample")}
    shape_from = {"shape": ("u", "y")}          # may be left out: the wiring fixes it
    example = {"period": 0.01, "shape": [3], "initial": 1.0}

    def setup(self, period, offset, shape, initial):
        self._sampling(period, offset)
        shape = signal_shape(self, "shape", shape)
        size = int(np.prod(shape, dtype=np.int64))
        x0 = initial_values(self, initial, shape, "the signal's shape")
        self.declare_input("u", shape)
        self.declare_output("y", shape, feedthrough=())
        self.declare_state(2 * size, np.concatenate([x0, x0]))
        self.set_param("template", np.zeros(shape))
        self.set_kernels(output=held_output, derivative=no_change, params=("template",))

    def update(self, t, x, u):
        size = x.shape[1] // 2
        sample = u[0].reshape(u[0].shape[0], -1)
        stored = np.broadcast_to(x[:, size:], (sample.shape[0], size))
        return np.concatenate((stored, sample), axis=1)


@register
class DiscreteStateSpace(_Sampled):
    """Discrete-time state space (A, B, C, D) at a sample period, output held between samples.

    Equation: x[k+1] = A x[k] + B u[k], y[k] = C x[k] + D u[k], u[k] = u(t_k),
    t_k = offset + k period; y(t) = y[k] for t_k <= t < t_{k+1}, y = C x0 before the first
    sample.  State: [x (n), held y (p)].

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | (m,)  | -           |
        | y    | out       | (p,)  | -           |

    Parameters:
        A, B, C, D: matrices (n x n, n x m, p x n, p x m); D defaults to zero.
        period: sample period T [s].
        offset: first sample instant [s] (default 0).
        x0: initial state x[0] (default 0).
    """

    params = {"A": Param("array", doc="state matrix (n x n)"),
              "B": Param("array", doc="input matrix (n x m)"),
              "C": Param("array", doc="output matrix (p x n)"),
              "D": Param("array", default=None, doc="feedthrough matrix (p x m), default 0"),
              **SAMPLING,
              "x0": Param("array", default=None, doc="initial state x[0] (default 0)")}
    example = {"A": [[0.9, 0.1], [0.0, 0.8]], "B": [[0.0], [1.0]], "C": [[1.0, 0.0]],
               "D": [[0.5]], "period": 0.01, "x0": [1.0, 0.0]}

    def setup(self, A, B, C, D, period, offset, x0):
        self._sampling(period, offset)
        A, B, C = (np.atleast_2d(np.asarray(M, dtype=float)) for M in (A, B, C))
        n, m, p = A.shape[0], B.shape[1], C.shape[0]
        D = np.zeros((p, m)) if D is None else np.atleast_2d(np.asarray(D, dtype=float))
        self._realise(A, B, C, D, x0)

    def _realise(self, A, B, C, D, x0, in_shape=None, out_shape=None) -> None:
        n, m, p = A.shape[0], B.shape[1], C.shape[0]
        self.require_size("order", n, 20 * MAX_ORDER)
        want = {"A": (n, n), "B": (n, m), "C": (p, n), "D": (p, m)}
        for key, M in zip("ABCD", (A, B, C, D)):
            if M.ndim != 2 or M.shape != want[key]:
                raise ParameterError(
                    f"block '{self.name}' parameter '{key}' has shape {M.shape}; with A "
                    f"{A.shape} and the other matrices it must be {want[key]}", block=self.name)
        x0 = initial_values(self, x0, (n,), "(n,), the state's size")
        self.declare_input("u", in_shape if in_shape is not None else (m,))
        self.declare_output("y", out_shape if out_shape is not None else (p,), feedthrough=())
        self.declare_state(n + p, np.concatenate([x0, C @ x0]))
        for key, M in zip("ABCD", (A, B, C, D)):
            self.set_param(key, M)
        self.samples_through = bool(np.any(D != 0))     # y_k = C x_k + D u_k
        self.set_param("template", np.zeros(out_shape if out_shape is not None else (p,)))
        self.set_kernels(output=held_output_tail, derivative=no_change, params=("template",))

    def update(self, t, x, u):
        p = self.p
        v = u[0].reshape(u[0].shape[0], -1)
        return dss_update(x, v, p.A, p.B, p.C, p.D)


@register
class DiscreteTransferFunction(DiscreteStateSpace):
    """Discrete-time transfer function num(z)/den(z) at a sample period, per element, held.

    Equation: y[k] = num(z) / den(z) u[k] (z = the one-sample advance), u[k] = u(t_k),
    t_k = offset + k period, y(t) = y[k] for t_k <= t < t_{k+1}; element by element with
    one shared denominator.  Realisation: the observer canonical form of
    fwdstep.core.linear.observer_form (the same as TransferFunction's, in z), kron'd with the
    identity over the signal's elements; the state starts at zero (y = 0 before the first
    sample).

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | shape | -           |

    Parameters:
        num: numerator coefficients in z, highest power first (e.g. [0.5, 0] for 0.5 z).
        den: denominator coefficients in z, highest power first; deg num <= deg den.
        period: sample period T [s].
        offset: first sample instant [s] (default 0).
        shape: shape of the signal (list; [] or omitted for a scalar).
    """

    params = {"num": Param("array", doc="numerator in z, highest power first"),
              "den": Param("array", doc="denominator in z, highest power first"),
              **SAMPLING,
              "shape": Param("array", default=None, doc="signal shape, e.g. [2]; default scalar")}
    shape_from = {"shape": ("u", "y")}          # may be left out: the wiring fixes it
    example = {"num": [0.2, 0.1], "den": [1.0, -0.7], "period": 0.01, "shape": [2]}

    def setup(self, num, den, period, offset, shape):
        self._sampling(period, offset)
        num = polynomial(self, "num", num)
        den = polynomial(self, "den", den)
        if not np.any(den):
            raise ParameterError(f"block '{self.name}' parameter 'den' must not be zero",
                                 block=self.name)
        if np.any(num) and num.size > den.size:
            raise ParameterError(f"block '{self.name}' transfer function is improper (not "
                                 f"causal): numerator degree {num.size - 1} > denominator "
                                 f"degree {den.size - 1}", block=self.name)
        self.require_size("denominator degree", den.size - 1, MAX_ORDER)
        shape = signal_shape(self, "shape", shape)
        size = int(np.prod(shape, dtype=np.int64))
        A, B, C, D = observer_form(den, [num])
        eye = np.eye(size)
        self._realise(np.kron(A, eye), np.kron(B, eye), np.kron(C, eye), D[0] * eye, None,
                      in_shape=shape, out_shape=shape)
