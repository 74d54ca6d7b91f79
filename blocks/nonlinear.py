"""Memoryless and rate nonlinearities: saturation, dead zone, rate limit, friction, switch,
1-D table lookup, relay (with hysteresis), and the Stop block.

Every regime change is also declared as a zero-crossing function next to the kernel
(``zero_crossings``: the guard values whose sign change marks it; docs/writing-blocks.md),
so a fixed-step run ends its step exactly where a limit is reached, a switch flips or a
table segment changes (``fwdstep.run.crossings``) and keeps the solver's order.

Each block's equation lives in one module-level kernel (``output`` / ``derivative`` in the
form of docs/writing-blocks.md: ``kernel(t, x, u_1, ..., u_k, p_1, ..., p_m, s_1, ...)``),
written in the subset of NumPy that numba compiles, on arrays with a leading batch axis.
Numeric parameters (limits, rates, coefficients, tables) live in ``self.p``, so a batched
sweep may stack any of them.
"""
from __future__ import annotations

import numpy as np

from fwdstep.core.block import Block, Param, shape_str
from fwdstep.core.errors import ParameterError
from fwdstep.core.registry import register

#: The largest number of breakpoints of one Lookup1D table.
MAX_TABLE = 100_000


# ----------------------------------------------------------------------------- kernels
def saturation_output(t, x, u, lower, upper):
    """y = min(max(u, lower), upper), per element."""
    return (np.minimum(np.maximum(u, lower), upper),)


def clip_symmetric_output(t, x, u, limit):
    """y = min(max(u, -limit), limit), per element."""
    return (np.minimum(np.maximum(u, -limit), limit),)


def clip_output(t, x, u, lower, upper):
    """y = min(max(u, lower), upper), per element."""
    return (np.minimum(np.maximum(u, lower), upper),)


def clip_guards(u, lower, upper):
    """u - lower, then u - upper, per element (Clip, its limits as signals)."""
    uf, lo, hi = _flat(u), _flat(lower), _flat(upper)
    B = max(uf.shape[0], lo.shape[0], hi.shape[0])
    return np.concatenate((np.broadcast_to(uf - lo, (B, uf.shape[1])),
                           np.broadcast_to(uf - hi, (B, uf.shape[1]))), axis=1)


def dead_zone_output(t, x, u, lower, upper):
    """y = u - min(max(u, lower), upper): u - upper above, 0 inside, u - lower below."""
    return (u - np.minimum(np.maximum(u, lower), upper),)


def rate_limiter_derivative(t, x, u, time_constant, rising, falling):
    """x' = min(max((u - x) / T, -falling), rising), per element (x, u flattened)."""
    uf = np.ascontiguousarray(u).reshape((u.shape[0], x.shape[1]))   # u may be a strided view
    return np.minimum(np.maximum((uf - x) / time_constant, -falling), rising)


def rate_limiter_output_vector(t, x, u, time_constant, rising, falling):
    """y = x."""
    return (x.copy(),)


def rate_limiter_output_scalar(t, x, u, time_constant, rising, falling):
    """y = x (scalar signal)."""
    return (x[:, 0].copy(),)


def friction_law(t, x, qdot, coulomb, viscous, velocity_scale):
    """tau_f = -(F_c sgn(qdot) + F_v qdot), sgn = sign (velocity_scale 0) or tanh(qdot / v_s)
    (the law applied inside a plant, e.g. URDFArm, where no crossing is located)."""
    smooth = np.tanh(qdot / np.maximum(velocity_scale, 1e-300))
    sgn = np.where(velocity_scale > 0.0, smooth, np.sign(qdot))
    return (-(coulomb * sgn + viscous * qdot),)


def friction_output(t, x, qdot, coulomb, viscous, velocity_scale):
    """The Friction block: tau_f = -(F_c sgn(qdot) + F_v qdot), sgn = tanh(qdot / v_s) (velocity_scale > 0) or
    the sign held in the state x (+1 / -1, set where qdot crosses 0; 0: sign(qdot))."""
    smooth = np.tanh(qdot / np.maximum(velocity_scale, 1e-300))
    held = np.where(x > 0.5, 1.0, np.where(x < -0.5, -1.0, np.sign(qdot)))
    sgn = np.where(velocity_scale > 0.0, smooth, held)
    return (-(coulomb * sgn + viscous * qdot),)


def held_choice(m, control, threshold):
    """True where the Switch passes u1: its held choice m (+1 u1, -1 u2, set where control
    crosses threshold), or control >= threshold where none is held (m = 0)."""
    return (m > 0.5) | ((np.abs(m) < 0.5) & (control >= threshold))


def switch_output_same(t, x, u1, control, u2, threshold):
    """y = u1 where the held choice says so, else u2 (control per element, or scalar data)."""
    m = np.ascontiguousarray(x).reshape((x.shape[0],) + control.shape[1:])
    return (np.where(held_choice(m, control, threshold), u1, u2),)


def switch_output_scalar1(t, x, u1, control, u2, threshold):
    """Scalar control, vector data."""
    c = control[:, None]            # control may be a strided view (no reshape in numba)
    return (np.where(held_choice(x[:, 0:1], c, threshold), u1, u2),)


def switch_output_scalar2(t, x, u1, control, u2, threshold):
    """Scalar control, matrix data."""
    c = control[:, None, None]
    m = x[:, 0:1]
    return (np.where(held_choice(m[:, :, None], c, threshold), u1, u2),)


def friction_derivative(t, x, qdot, coulomb, viscous, velocity_scale):
    """The held sign changes only at its crossings: x' = 0."""
    return np.zeros(x.shape)


def switch_derivative(t, x, u1, control, u2, threshold):
    """The held choice changes only at its crossings: x' = 0."""
    return np.zeros(x.shape)


def lookup_output(t, x, u, breakpoints, values, linear_extrapolation):
    """Piecewise-linear interpolation per element: u (Bu, N), tables (Bp, k); y = v_j + (v_{j+1} - v_j) (u - b_j) / (b_{j+1} - b_j) on
    b_j <= u < b_{j+1}; outside [b_0, b_{k-1}] the end segments are extended (linear) or u
    is clamped to the ends."""
    B = max(u.shape[0], breakpoints.shape[0])
    N = u.shape[1]
    k = breakpoints.shape[1]
    y = np.empty((B, N))
    for b in range(B):
        ub = u[min(b, u.shape[0] - 1)]
        bp = breakpoints[min(b, breakpoints.shape[0] - 1)]
        v = values[min(b, values.shape[0] - 1)]
        if not linear_extrapolation:
            ub = np.minimum(np.maximum(ub, bp[0]), bp[k - 1])
        j = np.searchsorted(bp, ub, side="right") - 1
        j = np.minimum(np.maximum(j, 0), k - 2)
        b0 = bp[j]
        v0 = v[j]
        y[b] = v0 + (v[j + 1] - v0) * (ub - b0) / (bp[j + 1] - b0)
    return (y,)


# ----------------------------------------------------------------------------- guards
# The zero-crossing functions (state events): (B, m) arrays whose sign changes mark a
# regime change; continuous along a step (docs/writing-blocks.md).
def _flat(a):
    return np.ascontiguousarray(a).reshape((a.shape[0], -1))


def interval_guards(out, t, x, u, interval):
    """out <- u - lower, then u - upper, per element (Saturation, DeadZone); ``interval``
    (B, 2, size): lower and upper flattened."""
    g = out.view()
    g.shape = (out.shape[0], 2, interval.shape[2])       # a view (raises if it cannot be)
    np.subtract(u.reshape((u.shape[0], 1, -1)), interval, out=g)


def rate_limiter_guards(x, u, time_constant, rising, falling):
    """r - rising, then r + falling, with r = (u - x) / T the unclipped rate."""
    r = (_flat(u) - x) / time_constant
    return np.concatenate((r - rising, r + falling), axis=1)


def lookup_guards(u, breakpoints):
    """u_i - b_j for every breakpoint j (name b_j), per element i."""
    uf = _flat(u)
    return (uf[:, None, :] - breakpoints[:, :, None]).reshape(
        (max(uf.shape[0], breakpoints.shape[0]), -1))


def relay_output(t, x, u, on_value, off_value, on_threshold, off_threshold, scalar):
    """y = on_value where the relay is on (its state x = 1), else off_value."""
    return (np.where(x > 0.5, on_value, off_value),)


def relay_output_scalar(t, x, u, on_value, off_value, on_threshold, off_threshold, scalar):
    """y for a scalar signal (one kernel per output rank, so numba types each)."""
    return (np.where(x[:, 0] > 0.5, on_value[:, 0], off_value[:, 0]),)


def relay_derivative(t, x, u, on_value, off_value, on_threshold, off_threshold, scalar):
    """The relay's state changes only at its crossings: x' = 0."""
    return np.zeros(x.shape)


def relay_guards(x, u, on_threshold, off_threshold):
    """Off: u - on_threshold (switches on when it reaches 0); on: u - off_threshold
    (switches off when it falls below 0).  Continuous while the state is held."""
    uf = _flat(u)
    return np.where(x > 0.5, uf - off_threshold, uf - on_threshold)


def stop_output(t, x, u):
    """No outputs: the Stop block only has a zero-crossing function."""
    return ()


# ----------------------------------------------------------------------------- helpers
def _shape(block: Block, value) -> tuple:
    arr = np.atleast_1d(np.asarray([] if value is None else value, dtype=float))
    if arr.ndim != 1 or np.any(arr < 1) or np.any(arr != np.floor(arr)) or arr.size > 2:
        raise ParameterError(
            f"block '{block.name}' parameter 'shape' must be [] (scalar), [n] or [n, m] with "
            f"positive whole numbers, got {np.asarray(value).tolist()}", block=block.name)
    return tuple(int(s) for s in arr)


def _per_element(block: Block, key: str, value, shape: tuple) -> np.ndarray:
    """A parameter given as a number or one value per element of ``shape``."""
    arr = np.asarray(value, dtype=float)
    try:
        return np.array(np.broadcast_to(arr, shape))
    except ValueError:
        raise ParameterError(
            f"block '{block.name}' parameter '{key}' has shape {shape_str(arr.shape)}, which "
            f"does not broadcast to the signal shape {shape_str(shape)}",
            block=block.name) from None


def _infer_shape(block: Block, shape, *arrays) -> tuple:
    """The signal shape: ``shape`` if given, else the broadcast shape of the limits."""
    if shape is not None:
        return _shape(block, shape)
    try:
        return np.broadcast_shapes(*(np.shape(a) for a in arrays))
    except ValueError:
        raise ParameterError(f"block '{block.name}': the limits do not broadcast to one shape; "
                             "give 'shape'", block=block.name) from None


# ----------------------------------------------------------------------------- blocks

def _declare_interval(block: Block, lower, upper, shape, kernel) -> None:
    """The per-element interval [lower, upper] (lower <= upper) of Saturation and DeadZone,
    their one input u and feedthrough output y of ``shape``, and their kernel."""
    lo = _per_element(block, "lower", lower, shape)
    hi = _per_element(block, "upper", upper, shape)
    if np.any(lo > hi):
        raise ParameterError(f"block '{block.name}' parameter 'lower' must not exceed "
                             f"'upper', got lower {lo.tolist()}, upper {hi.tolist()}",
                             block=block.name)
    block.declare_input("u", shape)
    block.declare_output("y", shape, feedthrough=("u",))
    block.set_param("lower", lo)
    block.set_param("upper", hi)
    block.set_param("interval", np.stack([lo.reshape(-1), hi.reshape(-1)]))   # the guards'
    block.set_kernels(output=kernel, params=("lower", "upper"))
    block.declare_zero_crossings(("lower", "upper"), int(np.prod(shape, dtype=np.int64)),
                                 kernel=interval_guards, params=("interval",))


class _Interval(Block):
    """Saturation and DeadZone: guards u - lower and u - upper (``interval_guards``)."""

@register
class Saturation(_Interval):
    """Saturation: each element clipped to [lower, upper] (e.g. a torque limit).

    Equation: y_i = min(max(u_i, lower_i), upper_i).

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | shape | u           |

    Parameters:
        lower: lower limit, a number or one per element (default -inf: none).
        upper: upper limit, a number or one per element (default +inf: none).
        shape: signal shape ([] scalar, [n], [n, m]); default: the limits' broadcast shape.
    """

    params = {
        "lower": Param("array", None, "lower limit (number or per element)"),
        "upper": Param("array", None, "upper limit (number or per element)"),
        "shape": Param("array", None, "signal shape, e.g. [2]; default: the limits' shape"),
    }
    example = {"lower": [-1.0, -2.0], "upper": [1.0, 0.5]}

    def setup(self, lower, upper, shape):
        if lower is None and upper is None:
            raise ParameterError(f"block '{self.name}' ({self.type_name}) needs 'lower', "
                                 "'upper' or both", block=self.name)
        lo = -np.inf if lower is None else np.asarray(lower, dtype=float)
        hi = np.inf if upper is None else np.asarray(upper, dtype=float)
        shape = _infer_shape(self, shape, lo, hi)
        _declare_interval(self, lo, hi, shape, saturation_output)


@register
class Clip(Block):
    """Clip: each element of u clipped to [-limit, limit] or [lower, upper], limits as signals.

    A ``Saturation`` whose limits are inputs, e.g. a torque clipped to a robot's
    ``URDFArm.effort_limit``.  Like Saturation, it declares the guards u - lower and
    u - upper (zero crossings: a run locates where a limit is reached or left).

    Equation: y_i = min(max(u_i, -limit_i), limit_i); with ``symmetric: false``,
    y_i = min(max(u_i, lower_i), upper_i) (an element with lower_i > upper_i gives upper_i).

    Ports (drawn for symmetric = true; otherwise inputs u, lower, upper):
        | port  | direction | shape | feedthrough |
        | u     | in        | shape | -           |
        | limit | in        | shape | -           |
        | y     | out       | shape | u, limit    |

    Parameters:
        symmetric: true (inputs u, limit) or false (inputs u, lower, upper).
        shape: signal shape ([] scalar, [n], [n, m]); default: set by the wiring.
    """

    params = {
        "symmetric": Param("bool", True, "limits [-limit, limit] (true) or [lower, upper]"),
        "shape": Param("array", None, "signal shape, e.g. [2]; default: from the wiring"),
    }
    shape_from = {"shape": ("u", "y", "limit", "lower", "upper")}
    example = {"shape": [2]}

    def setup(self, symmetric, shape):
        shape = _shape(self, shape)
        self.declare_input("u", shape)
        bounds = ("limit",) if symmetric else ("lower", "upper")
        for name in bounds:
            self.declare_input(name, shape)
        self.declare_output("y", shape)
        self.set_kernels(output=clip_symmetric_output if symmetric else clip_output)
        self._symmetric = symmetric
        self.declare_zero_crossings(("lower", "upper"), int(np.prod(shape, dtype=np.int64)))

    def zero_crossings(self, t, x, u):
        """u - lower and u - upper (lower = -limit when symmetric): the clip changes
        regime where either changes sign."""
        if self._symmetric:
            return clip_guards(u[0], -u[1], u[1])
        return clip_guards(u[0], u[1], u[2])


@register
class DeadZone(_Interval):
    """DeadZone: zero output inside [lower, upper], shifted input outside (per element).

    Equation: y_i = u_i - upper_i if u_i > upper_i; 0 if lower_i <= u_i <= upper_i;
    u_i - lower_i if u_i < lower_i  (i.e. y = u - Saturation(u)).

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | shape | u           |

    Parameters:
        lower: start of the dead zone (number or per element; <= upper).
        upper: end of the dead zone (number or per element).
        shape: signal shape ([] scalar, [n], [n, m]); default: the limits' broadcast shape.
    """

    params = {
        "lower": Param("array", doc="start of the dead zone (number or per element)"),
        "upper": Param("array", doc="end of the dead zone (number or per element)"),
        "shape": Param("array", None, "signal shape, e.g. [2]; default: the limits' shape"),
    }
    example = {"lower": -0.5, "upper": [0.5, 1.0]}

    def setup(self, lower, upper, shape):
        shape = _infer_shape(self, shape, lower, upper)
        _declare_interval(self, lower, upper, shape, dead_zone_output)


@register
class RateLimiter(Block):
    """RateLimiter: a first-order lag whose rate is clipped (state-based rate limit).

    Equation: y = x,  x_i' = min(max((u_i - x_i) / T, -falling_i), rising_i),  x(0) = x0.
    While |u - x| > T * rate the output moves at exactly the limiting rate (a ramp); near
    the input it follows u as the lag 1 / (T s + 1).  As T -> 0 this is the ideal rate
    limiter (Simulink's Rate Limiter): y follows u wherever u's rate is within the limits.
    Being a state, it never feeds u through, so it breaks algebraic loops.

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | shape | -           |

    Parameters:
        rising: largest rate of increase (> 0; number or per element; units of u per s).
        falling: largest rate of decrease (> 0; default: rising).
        time_constant: T of the lag inside the limits (s, > 0; default 1e-3).
        x0: initial output (number or per element; default 0).
        shape: signal shape ([] scalar or [n]); default: the rates' broadcast shape.
    """

    params = {
        "rising": Param("array", doc="largest rate of increase (> 0)"),
        "falling": Param("array", None, "largest rate of decrease (> 0; default rising)"),
        "time_constant": Param("float", 1e-3, "lag time constant T (s)"),
        "x0": Param("array", 0.0, "initial output"),
        "shape": Param("array", None, "signal shape, [] or [n]"),
    }
    example = {"rising": [1.0, 2.0], "falling": 3.0, "time_constant": 0.1, "x0": [0.5, -0.5]}

    def setup(self, rising, falling, time_constant, x0, shape):
        falling = rising if falling is None else falling
        shape = _infer_shape(self, shape, rising, falling, x0)
        if len(shape) > 1:
            raise ParameterError(f"block '{self.name}' shape must be [] or [n], got "
                                 f"{list(shape)}", block=self.name)
        rise = _per_element(self, "rising", rising, shape).reshape(-1)
        fall = _per_element(self, "falling", falling, shape).reshape(-1)
        if np.any(rise <= 0) or np.any(fall <= 0):
            raise ParameterError(f"block '{self.name}' parameters 'rising' and 'falling' must "
                                 f"be positive, got {rise.tolist()} and {fall.tolist()}",
                                 block=self.name)
        if not time_constant > 0:
            raise ParameterError(f"block '{self.name}' parameter 'time_constant' must be "
                                 f"positive, got {time_constant}", block=self.name)
        self.declare_input("u", shape)
        self.declare_output("y", shape, feedthrough=())
        size = int(np.prod(shape, dtype=np.int64)) if shape else 1
        self.declare_state(size, _per_element(self, "x0", x0, shape).reshape(-1))
        self.set_param("time_constant", [time_constant])           # (1, 1): per variant
        self.set_param("rising", rise)
        self.set_param("falling", fall)
        out = rate_limiter_output_scalar if shape == () else rate_limiter_output_vector
        self.set_kernels(output=out, derivative=rate_limiter_derivative,
                         params=("time_constant", "rising", "falling"))
        self.declare_zero_crossings(("rising", "falling"), size)

    def zero_crossings(self, t, x, u):
        return rate_limiter_guards(x, u[0], self.p.time_constant, self.p.rising,
                                   self.p.falling)

    def state_eigenvalues(self):
        """Inside the rate limits x' = (u - x) / T: every element's eigenvalue is -1/T (the
        fastest regime; at a limit x' is constant)."""
        T = self.p.time_constant.reshape(-1, 1)
        return np.broadcast_to(-1.0 / T, (T.shape[0], self.n_states)).astype(complex)


@register
class Friction(Block):
    """Friction: Coulomb plus viscous joint friction, a plant-side torque from qdot.

    Equation: tau_f,i = -(F_c,i sgn(qdot_i) + F_v,i qdot_i), with sgn = sign when
    velocity_scale = 0 (exact Coulomb friction, discontinuous at qdot = 0) or
    sgn(v) = tanh(v / v_s) for velocity_scale v_s > 0 (smooth, so fixed-step solvers keep
    their order).  Wire ``qdot`` from the plant and ``tau_f`` into the plant's ``tau_star``
    (through a Sum if there is also a disturbance): the friction then acts on the arm and is
    unknown to the controller.  With velocity_scale = 0 the sign is a state of the block
    (sign(qdot(0)) at t = 0), changed only where qdot_i crosses 0 (a located zero
    crossing), so every Runge-Kutta stage of a step sees one sign.

    Ports:
        | port  | direction | shape | feedthrough |
        | qdot  | in        | (n,)  | -           |
        | tau_f | out       | (n,)  | qdot        |

    Parameters:
        n: number of joints.
        coulomb: F_c >= 0, Coulomb friction torque (N m; number or (n,)).
        viscous: F_v >= 0, viscous coefficient (N m s/rad; number or (n,); default 0).
        velocity_scale: v_s >= 0 (rad/s; default 0: exact sign).
    """

    params = {
        "n": Param("int", doc="number of joints"),
        "coulomb": Param("array", 0.0, "Coulomb friction torque F_c (N m)"),
        "viscous": Param("array", 0.0, "viscous coefficient F_v (N m s/rad)"),
        "velocity_scale": Param("float", 0.0, "tanh smoothing velocity v_s (0: sign)"),
    }
    example = {"n": 2, "coulomb": [0.5, 0.3], "viscous": 0.2, "velocity_scale": 0.01}
    init_from_inputs = True

    def setup(self, n, coulomb, viscous, velocity_scale):
        if n < 1:
            raise ParameterError(f"block '{self.name}' parameter 'n' must be at least 1, got "
                                 f"{n}", block=self.name)
        fc = _per_element(self, "coulomb", coulomb, (n,))
        fv = _per_element(self, "viscous", viscous, (n,))
        if np.any(fc < 0) or np.any(fv < 0) or velocity_scale < 0:
            raise ParameterError(f"block '{self.name}' parameters 'coulomb', 'viscous' and "
                                 "'velocity_scale' must not be negative", block=self.name)
        self.declare_input("qdot", (n,))
        self.declare_output("tau_f", (n,), feedthrough=("qdot",), label=r"$\tau_f$",
                            unit="N m")
        self.set_param("coulomb", fc)
        self.set_param("viscous", fv)
        self.set_param("velocity_scale", np.full(1, velocity_scale))
        # the sign (velocity_scale 0) jumps where qdot_i crosses 0 (tanh: no guard, +1);
        # it is held in the state between crossings, so no Runge-Kutta stage of a step
        # sees the other sign (the located crossing then keeps the solver's order)
        self.declare_state(n, 0.0)
        self.state_labels = [f"sign[{i}]" for i in range(n)]
        self.set_kernels(output=friction_output, derivative=friction_derivative,
                         params=("coulomb", "viscous", "velocity_scale"))
        self.declare_zero_crossings(("qdot",), n)

    def initial_state(self, t0, u):
        return np.sign(_flat(u[0])) + np.zeros((self.p.coulomb.shape[0], 1))

    def zero_crossings(self, t, x, u):
        return np.where(self.p.velocity_scale[:, None] > 0.0, 1.0, _flat(u[0]))

    def crossed(self, t, x, u, which):
        return np.where(which, np.where(_flat(u[0]) >= 0.0, 1.0, -1.0), x)


@register
class Switch(Block):
    """Switch: passes u1 where control >= threshold, u2 elsewhere.

    Equation: y = u1 if control >= threshold, else u2 (per element when control has the
    data's shape; one choice for the whole signal when control is a scalar).  The choice
    is a state of the block (+1: u1, -1: u2; from control at t = 0), changed only where
    control - threshold crosses 0 (a located zero crossing), so every Runge-Kutta stage
    of a step sees one input.

    Ports:
        | port    | direction | shape              | feedthrough        |
        | u1      | in        | shape              | -                  |
        | control | in        | () or shape        | -                  |
        | u2      | in        | shape              | -                  |
        | y       | out       | shape              | u1, control, u2    |

    Parameters:
        threshold: the switching level (default 0).
        shape: shape of u1, u2 and y ([] scalar, [n], [n, m]; default scalar).
        per_element: true: control has the data's shape; false (default): control is scalar.
    """

    params = {
        "threshold": Param("float", 0.0, "switching level"),
        "shape": Param("array", None, "data shape, e.g. [2]; default scalar"),
        "per_element": Param("bool", False, "control has the data's shape"),
    }
    example = {"threshold": 0.5, "shape": [2]}
    init_from_inputs = True

    def setup(self, threshold, shape, per_element):
        shape = _shape(self, shape)
        self.declare_input("u1", shape)
        self.declare_input("control", shape if per_element else ())
        self.declare_input("u2", shape)
        self.declare_output("y", shape)
        # (1, 1, ...): one threshold per variant, broadcast over the data's elements
        self.set_param("threshold", np.full((1,) * len(shape), threshold))
        if per_element or shape == ():
            kernel = switch_output_same
        else:
            kernel = switch_output_scalar1 if len(shape) == 1 else switch_output_scalar2
        size = int(np.prod(shape, dtype=np.int64)) if per_element else 1
        # the choice is held in the state between crossings of control - threshold, so
        # no Runge-Kutta stage of a step sees the other input
        self.declare_state(size, 0.0)
        self.state_labels = [f"choice[{i}]" for i in range(size)]
        self.set_kernels(output=kernel, derivative=switch_derivative, params=("threshold",))
        self.declare_zero_crossings(("control",), size)

    def initial_state(self, t0, u):
        return np.where(self.zero_crossings(t0, None, u) >= 0.0, 1.0, -1.0)

    def zero_crossings(self, t, x, u):
        return _flat(u[1]) - self.p.threshold.reshape((self.p.threshold.shape[0], 1))

    def crossed(self, t, x, u, which):
        return np.where(which, np.where(self.zero_crossings(t, x, u) >= 0.0, 1.0, -1.0), x)


@register
class Lookup1D(Block):
    """Lookup1D: piecewise-linear interpolation in a 1-D table, per element of u.

    Equation: for b_j <= u_i < b_{j+1},
    y_i = v_j + (v_{j+1} - v_j) (u_i - b_j) / (b_{j+1} - b_j); outside [b_0, b_{k-1}]
    y_i = v_0 / v_{k-1} (extrapolation: clamp) or the end segment extended (linear).

    Ports:
        | port | direction | shape       | feedthrough |
        | u    | in        | (n,)        | -           |
        | y    | out       | (n,)        | u           |

    Parameters:
        breakpoints: b_0 < b_1 < ... < b_{k-1} (k >= 2, strictly increasing).
        values: v_0, ..., v_{k-1}, one per breakpoint.
        extrapolation: clamp (default) or linear.
        n: size of u and y (default 1; a scalar signal is a vector of size 1 here).
    """

    params = {
        "breakpoints": Param("array", doc="strictly increasing table inputs b_j"),
        "values": Param("array", doc="table outputs v_j, one per breakpoint"),
        "extrapolation": Param("choice", "clamp", "outside the table: clamp or linear",
                               choices=("clamp", "linear")),
        "n": Param("int", 1, "size of u and y"),
    }
    example = {"breakpoints": [0.0, 1.0, 3.0], "values": [0.0, 2.0, 1.0], "n": 2,
               "extrapolation": "linear"}

    def setup(self, breakpoints, values, extrapolation, n):
        bp = np.asarray(breakpoints, dtype=float)
        v = np.asarray(values, dtype=float)
        if bp.ndim != 1 or bp.size < 2 or np.any(np.diff(bp) <= 0):
            raise ParameterError(f"block '{self.name}' parameter 'breakpoints' must be a list "
                                 f"of at least 2 strictly increasing numbers, got "
                                 f"{bp.tolist()}", block=self.name)
        self.require_size("number of breakpoints", bp.size, MAX_TABLE)
        if v.shape != bp.shape:
            raise ParameterError(f"block '{self.name}' parameter 'values' must have one value "
                                 f"per breakpoint ({bp.size}), got shape {v.shape}",
                                 block=self.name)
        if n < 1:
            raise ParameterError(f"block '{self.name}' parameter 'n' must be at least 1, got "
                                 f"{n}", block=self.name)
        self.declare_input("u", (n,))
        self.declare_output("y", (n,), feedthrough=("u",))
        self.set_param("breakpoints", bp)
        self.set_param("values", v)
        self.set_kernels(output=lookup_output, params=("breakpoints", "values"),
                         static=(extrapolation == "linear",))
        self.declare_zero_crossings(tuple(f"b{j}" for j in range(bp.size)), n)

    def zero_crossings(self, t, x, u):
        return lookup_guards(u[0], self.p.breakpoints)


@register
class Relay(Block):
    """Relay: an on/off switch with hysteresis (e.g. a bang-bang heater, a thermostat).

    Equation: the relay turns on when u reaches on_threshold and off when u falls to
    off_threshold (off_threshold <= on_threshold); y = on_value while on, off_value while
    off, per element.  Its on/off state is a state of the block, changed only at the
    located crossings (the guard is u - on_threshold while off, u - off_threshold while
    on), so every Runge-Kutta stage of a step sees one regime.  At t = 0 it is on where
    u(0) >= on_threshold.

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | shape | -           |

    Parameters:
        on_threshold: input level that switches the relay on (default 0).
        off_threshold: input level that switches it off (<= on_threshold; default 0).
        on_value: output while on (default 1).
        off_value: output while off (default 0).
        shape: signal shape ([] scalar or [n]; default scalar).
    """

    params = {
        "on_threshold": Param("float", 0.0, "switch on when u reaches it"),
        "off_threshold": Param("float", 0.0, "switch off when u falls to it"),
        "on_value": Param("float", 1.0, "output while on"),
        "off_value": Param("float", 0.0, "output while off"),
        "shape": Param("array", None, "signal shape, [] or [n]"),
    }
    example = {"on_threshold": 0.5, "off_threshold": -0.5, "on_value": 2.0,
               "off_value": -1.0, "shape": [2]}
    init_from_inputs = True

    def setup(self, on_threshold, off_threshold, on_value, off_value, shape):
        shape = _shape(self, shape)
        if len(shape) > 1:
            raise ParameterError(f"block '{self.name}' shape must be [] or [n], got "
                                 f"{list(shape)}", block=self.name)
        if off_threshold > on_threshold:
            raise ParameterError(f"block '{self.name}' parameter 'off_threshold' "
                                 f"({off_threshold:g}) must not exceed 'on_threshold' "
                                 f"({on_threshold:g})", block=self.name)
        size = shape[0] if shape else 1
        self.declare_input("u", shape)
        self.declare_output("y", shape, feedthrough=())
        self.declare_state(size, 0.0)
        for key, value in (("on_value", on_value), ("off_value", off_value),
                           ("on_threshold", on_threshold), ("off_threshold", off_threshold)):
            self.set_param(key, [value])
        self.set_kernels(output=relay_output_scalar if shape == () else relay_output,
                         derivative=relay_derivative,
                         params=("on_value", "off_value", "on_threshold", "off_threshold"),
                         static=(shape == (),))
        self.declare_zero_crossings(("switch",), size)

    def initial_state(self, t0, u):
        return (_flat(u[0]) >= self.p.on_threshold).astype(float)

    def zero_crossings(self, t, x, u):
        return relay_guards(x, u[0], self.p.on_threshold, self.p.off_threshold)

    def crossed(self, t, x, u, which):
        return np.where(which, 1.0 - x, x)


@register
class Stop(Block):
    """Stop: ends the run when its input crosses zero.

    The crossing is located in time like every zero crossing (docs/writing-blocks.md); the
    run then ends there with status "stopped", its last record at that time, and the time
    in the message (e.g. stop when a tracking error settles: wire |e| - tolerance).

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |

    Parameters:
        shape: input shape ([] scalar or [n]; any element crossing stops; default scalar).
    """

    params = {"shape": Param("array", None, "input shape, [] or [n]")}
    example = {"shape": [2]}
    stops_run = True

    def setup(self, shape):
        shape = _shape(self, shape)
        self.declare_input("u", shape)
        self.set_kernels(output=stop_output)
        self.declare_zero_crossings(("u",), int(np.prod(shape, dtype=np.int64)) if shape else 1)

    def zero_crossings(self, t, x, u):
        return _flat(u[0])


# ----------------------------------------------------------------------------- limited integrator
def limited_integrator_output(t, x, u, reset, value, lower, upper, n, scalar):
    """y = the integral (the first n states)."""
    return (x[:, :n].copy(),)


def limited_integrator_output_scalar(t, x, u, reset, value, lower, upper, n, scalar):
    """y = the integral (a scalar signal: one kernel per output rank, so numba types each)."""
    return (x[:, 0].copy(),)


def limited_integrator_derivative(t, x, u, reset, value, lower, upper, n, scalar):
    """x' = u while free (mode 0), 0 while held at a limit (mode -1 lower, +1 upper)."""
    uf = np.ascontiguousarray(u).reshape((u.shape[0], n))
    dx = np.zeros(x.shape)
    dx[:, :n] = np.where(np.abs(x[:, n:]) < 0.5, uf, 0.0)
    return dx


def limited_integrator_guards(x, u, reset, lower, upper, n):
    """lower: x - lower while free, u while held there (leaves when u turns positive);
    upper: upper - x while free, -u while held there; reset: the reset input."""
    xi, m = x[:, :n], x[:, n:]
    uf = np.ascontiguousarray(u).reshape((u.shape[0], n))
    rf = np.ascontiguousarray(reset).reshape((reset.shape[0], n))
    g_lo = np.where(m < -0.5, uf, xi - lower)
    g_hi = np.where(m > 0.5, -uf, upper - xi)
    B = max(g_lo.shape[0], g_hi.shape[0], rf.shape[0])
    return np.concatenate((np.broadcast_to(g_lo, (B, n)), np.broadcast_to(g_hi, (B, n)),
                           np.broadcast_to(rf, (B, n))), axis=1)


@register
class LimitedIntegrator(Block):
    """LimitedIntegrator: an integrator held between limits, with a reset input.

    Equation: x' = u while lower < x < upper; at a limit x stays there (x' = 0) until u
    points back inside (anti-windup; Simulink's limited Integrator).  When ``reset``
    crosses zero rising, x jumps to the input ``value`` (then clipped to the limits), e.g.
    a bouncing ball's velocity v <- -e v at impact.  Reaching a limit, leaving it and the
    reset are zero crossings located in time (docs/writing-blocks.md): the state stops
    exactly at the limit.  Its state is x followed by one mode per element (0 free, -1 at
    lower, +1 at upper).

    Ports:
        | port  | direction | shape | feedthrough |
        | u     | in        | shape | -           |
        | reset | in        | shape | -           |
        | value | in        | shape | -           |
        | y     | out       | shape | -           |

    ``reset`` and ``value`` are optional (unconnected: zeros, i.e. no reset).

    Parameters:
        lower: lower limit (number or per element; default -inf).
        upper: upper limit (number or per element; default +inf).
        initial: x(0) (within the limits; default 0).
        shape: signal shape ([] scalar or [n]; default scalar).
    """

    params = {
        "lower": Param("array", None, "lower limit (default -inf)"),
        "upper": Param("array", None, "upper limit (default +inf)"),
        "initial": Param("array", 0.0, "initial value x(0)"),
        "shape": Param("array", None, "signal shape, [] or [n]"),
    }
    example = {"lower": -1.0, "upper": [1.0, 2.0], "initial": 0.5, "shape": [2]}

    def setup(self, lower, upper, initial, shape):
        shape = _shape(self, shape)
        if len(shape) > 1:
            raise ParameterError(f"block '{self.name}' shape must be [] or [n], got "
                                 f"{list(shape)}", block=self.name)
        n = shape[0] if shape else 1
        flat = (n,)
        lo = _per_element(self, "lower", -np.inf if lower is None else lower, flat)
        hi = _per_element(self, "upper", np.inf if upper is None else upper, flat)
        x0 = _per_element(self, "initial", initial, flat)
        if np.any(lo > hi) or np.any(x0 < lo) or np.any(x0 > hi):
            raise ParameterError(f"block '{self.name}' needs lower <= initial <= upper, got "
                                 f"{lo.tolist()}, {x0.tolist()}, {hi.tolist()}",
                                 block=self.name)
        for port in ("u", "reset", "value"):
            self.declare_input(port, shape, optional=port != "u")
        self.declare_output("y", shape, feedthrough=())
        self.declare_state(2 * n, np.concatenate((x0, np.zeros(n))))
        self.state_labels = [f"x[{i}]" for i in range(n)] + [f"mode[{i}]" for i in range(n)]
        self.set_param("lower", lo)
        self.set_param("upper", hi)
        self._n = n
        self.set_kernels(output=(limited_integrator_output_scalar if shape == ()
                                 else limited_integrator_output),
                         derivative=limited_integrator_derivative,
                         params=("lower", "upper"), static=(n, shape == ()))
        self.declare_zero_crossings(("lower", "upper", "reset"), n)

    def zero_crossings(self, t, x, u):
        return limited_integrator_guards(x, u[0], u[1], self.p.lower, self.p.upper, self._n)

    def crossed(self, t, x, u, which):
        n = self._n
        xi, m = x[:, :n].copy(), x[:, n:].copy()
        lo, hi = self.p.lower, self.p.upper
        lo_b, hi_b = np.broadcast_to(lo, xi.shape), np.broadcast_to(hi, xi.shape)
        w_lo, w_hi, w_reset = which[:, :n], which[:, n:2 * n], which[:, 2 * n:]
        hit_lo = w_lo & (np.abs(m) < 0.5)        # reached the lower limit: held there
        hit_hi = w_hi & (np.abs(m) < 0.5)
        left = (w_lo & (m < -0.5)) | (w_hi & (m > 0.5))       # u points back inside: free
        xi = np.where(hit_lo, lo_b, np.where(hit_hi, hi_b, xi))
        m = np.where(hit_lo, -1.0, np.where(hit_hi, 1.0, np.where(left, 0.0, m)))
        r = np.ascontiguousarray(u[1]).reshape((u[1].shape[0], n))
        fire = w_reset & (r >= 0)                # the reset rises through zero
        if fire.any():
            v = np.ascontiguousarray(u[2]).reshape((u[2].shape[0], n))
            new = np.minimum(np.maximum(v, lo_b), hi_b)
            xi = np.where(fire, new, xi)
            m = np.where(fire, 0.0, m)
        return np.concatenate((xi, m), axis=1)
