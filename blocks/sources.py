"""Signal sources: blocks with no inputs and no state whose outputs depend on time only.

Every source evaluates closed-form expressions of ``t``; the sinusoidal and polynomial
sources also return their analytic time derivatives as extra outputs, so a desired
trajectory can supply q_d, qdot_d, qddot_d, ... without numerical differentiation.
All numeric data used at run time live in ``self.p`` with a leading batch axis, so a
batched sweep may stack any numeric parameter.
"""
from __future__ import annotations

import math

import numpy as np

from fwdstep.core.block import Block, Param, shape_str
from fwdstep.core.errors import ParameterError
from fwdstep.core.registry import register

#: The highest derivative order a source may be asked for.
MAX_DERIVATIVES = 8
#: The largest number of sinusoid terms (channels x sinusoids) one block may hold.
MAX_TERMS = 1_000_000
#: The highest polynomial degree.
MAX_DEGREE = 64


def _derivative_count(block: Block, derivatives: int) -> int:
    if not 0 <= derivatives <= MAX_DERIVATIVES:
        raise ParameterError(
            f"block '{block.name}' parameter 'derivatives' must be between 0 and "
            f"{MAX_DERIVATIVES}, got {derivatives}", block=block.name)
    return derivatives


def _derivative_names(m: int) -> list[str]:
    return ["y"] + [f"y_d{j}" for j in range(1, m + 1)]


# ---------------------------------------------------------------- kernels (one definition)
def constant_output(t, x, value):
    """y = value."""
    return (value,)


def step_output(t, x, time, after, before):
    """y_i = before_i for t < time_i, after_i from t = time_i on."""
    return (np.where(t >= time, after, before),)


def sinusoid_output(t, x, frequency, phase, coef_sin, coef_cos, offset_full):
    """Packed [y, y', ..., y^(m)]: y^(j)_i = [j = 0] offset_i + sum_k (coef_sin[j, i, k]
    sin + coef_cos[j, i, k] cos)(w_ik t + phi_ik); the signs and powers of w of d^j/dt^j are
    folded into the coefficients (sin at even orders, cos at odd orders)."""
    arg = frequency * t + phase                                   # (B, N, K)
    s = np.sin(arg)
    c = np.cos(arg)
    if arg.shape[2] == 1:                                         # one sinusoid per channel
        y = coef_sin[:, :, :, 0] * s.reshape((s.shape[0], 1, s.shape[1])) \
            + coef_cos[:, :, :, 0] * c.reshape((c.shape[0], 1, c.shape[1]))
    else:
        n, k = s.shape[1], s.shape[2]
        y = np.sum(coef_sin * s.reshape((s.shape[0], 1, n, k))
                   + coef_cos * c.reshape((c.shape[0], 1, n, k)), axis=3)
    y = y + offset_full                                           # (B, m+1, N)
    return y.reshape((y.shape[0], y.shape[1] * y.shape[2]))


def sinusoid1_output(t, x, frequency, phase, coef_sin, coef_cos, offset):
    """The same with one sinusoid per channel (K = 1), every array packed as the output is,
    (B, (m+1) N): y = coef_sin sin(w t + phi) + coef_cos cos(w t + phi) + offset, in the
    order of operations of ``sinusoid_output`` (same numbers), without its reshapes."""
    arg = frequency * t + phase
    return coef_sin * np.sin(arg) + coef_cos * np.cos(arg) + offset


def polynomial_output(t, x, coef):
    """Packed [y, y', ..., y^(m)]: y^(j)_i = sum_k coef[j, i, k] t^k (coef (B, m+1, n, d+1),
    the falling factorials of the derivatives folded in)."""
    d1 = coef.shape[3]
    powers = np.empty(d1)
    v = 1.0
    for k in range(d1):
        powers[k] = v
        v = v * t
    y = np.sum(coef * powers, axis=3)                              # (B, m+1, n)
    return y.reshape((y.shape[0], y.shape[1] * y.shape[2]))


@register
class Constant(Block):
    """Constant: y = value, a fixed array of any shape.

    Equation: y(t) = value.

    Ports:
        | port | direction | shape          | feedthrough |
        | y    | out       | shape of value | -           |

    Parameters:
        value: number, vector or matrix; its shape is the shape of y.
    """

    params = {"value": Param("array", doc="the constant (any shape)")}
    example = {"value": [1.0, -2.0]}

    def setup(self, value):
        value = np.asarray(value, dtype=float)
        self.declare_output("y", value.shape, feedthrough=())
        self.set_param("value", value)

        self.set_kernels(output=constant_output, params=("value",))


@register
class Step(Block):
    """Step: y = before for t < time, y = after from t = time on (per element).

    Equation: y_i(t) = before_i if t < time_i, else after_i.

    Ports:
        | port | direction | shape                                 | feedthrough |
        | y    | out       | broadcast shape of before, after, time | -           |

    Parameters:
        after: value from the step time on (number or array).
        before: value before the step time (default 0).
        time: step time in seconds (default 0); an array gives one step time per element.
    """

    params = {
        "after": Param("array", doc="value from the step time on"),
        "before": Param("array", default=0.0, doc="value before the step time"),
        "time": Param("array", default=0.0, doc="step time [s], scalar or per element"),
    }
    example = {"after": [1.0, 2.0], "before": 0.5, "time": [0.1, 0.2]}

    def setup(self, after, before, time):
        arrays = {"before": np.asarray(before, dtype=float),
                  "after": np.asarray(after, dtype=float),
                  "time": np.asarray(time, dtype=float)}
        try:
            shape = np.broadcast_shapes(*(a.shape for a in arrays.values()))
        except ValueError:
            found = ", ".join(f"{k} {shape_str(a.shape)}" for k, a in arrays.items())
            raise ParameterError(
                f"block '{self.name}' parameters 'before', 'after' and 'time' have shapes that "
                f"do not broadcast: {found}", block=self.name) from None
        self.declare_output("y", shape, feedthrough=())
        for key, arr in arrays.items():
            self.set_param(key, np.broadcast_to(arr, shape))

        self.set_kernels(output=step_output, params=("time", "after", "before"))
        # the jump times, also kept outside p: variants that jump at different times never
        # share a batch (its steps would be split at every variant's times)
        p = self.p
        self.jumps = tuple(np.unique(p.time[np.broadcast_to(p.before != p.after,
                                                             p.time.shape)]).tolist())

    def discontinuities(self, t_final):
        return np.asarray(self.jumps)


class _SinusoidSum(Block):
    """Shared machinery: y_i = offset_i + sum_k A_ik sin(w_ik t + phi_ik), and derivatives.

    Subclasses call ``_declare_sinusoids`` in ``setup`` with (N, K) arrays.
    """

    def _declare_sinusoids(self, amplitude, frequency, phase, offset, derivatives: int,
                           scalar: bool) -> None:
        m = _derivative_count(self, derivatives)
        n_channels, n_terms = amplitude.shape
        orders = np.arange(m + 1)
        # d^j/dt^j sin(a) = sin(a + j pi/2): +sin, +cos, -sin, -cos, ...  The sign is folded
        # into the coefficients: even orders multiply sin(arg), odd orders cos(arg).
        signs = np.where((orders // 2) % 2 == 0, 1.0, -1.0)
        with np.errstate(over="ignore", invalid="ignore"):
            coef = (signs[:, None, None] * amplitude[None]
                    * frequency[None] ** orders[:, None, None])        # (m+1, N, K)
        if not np.all(np.isfinite(coef)):
            j = int(np.argmax(~np.all(np.isfinite(coef), axis=(1, 2))))
            raise ParameterError(
                f"block '{self.name}': amplitude x frequency^{j} (derivative {j}) is larger "
                f"than the largest float for frequency up to {np.max(np.abs(frequency)):.3g} "
                f"rad/s; use a smaller frequency or fewer derivatives", block=self.name)
        self.set_param("frequency", frequency)
        self.set_param("phase", phase)
        self.set_param("offset", offset)
        self.set_param("even_coef", coef[0::2])
        self.set_param("odd_coef", coef[1::2])
        # the same per order: sin coefficients (0 at odd orders), cos coefficients (0 at even
        # orders), the offset at order 0 only, so one kernel call is ~8 array operations
        self.set_param("coef_sin", np.where((orders % 2 == 0)[:, None, None], coef, 0.0))
        self.set_param("coef_cos", np.where((orders % 2 == 1)[:, None, None], coef, 0.0))
        offset_full = np.zeros((m + 1, n_channels))
        offset_full[0] = offset
        self.set_param("offset_full", offset_full)
        self._m = m
        self._scalar = scalar
        shape = () if scalar else (n_channels,)
        for name in _derivative_names(m):
            self.declare_output(name, shape, feedthrough=())
        if n_terms > 1:
            self.set_kernels(output=sinusoid_output, packed=True, params=(
                "frequency", "phase", "coef_sin", "coef_cos", "offset_full"))
            return
        # one sinusoid per channel: the same coefficients packed as the output is, (m+1) N
        p = self.p
        for key, value in (("frequency", p.frequency[0, :, 0]), ("phase", p.phase[0, :, 0])):
            self.set_param(f"packed_{key}", np.tile(value, m + 1))
        for key in ("coef_sin", "coef_cos", "offset_full"):
            self.set_param(f"packed_{key}", getattr(p, key)[0].ravel())
        self.set_kernels(output=sinusoid1_output, packed=True, params=(
            "packed_frequency", "packed_phase", "packed_coef_sin", "packed_coef_cos",
            "packed_offset_full"))


def _per_channel(block: Block, key: str, value) -> np.ndarray:
    """Sine parameter -> (N, K): scalar -> (1, 1), (n,) -> (n, 1), (n, k) kept."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim > 2:
        raise ParameterError(
            f"block '{block.name}' parameter '{key}' must be a number, an (n,) vector or an "
            f"(n, k) matrix, got shape {arr.shape}", block=block.name)
    return arr.reshape(arr.shape + (1,) * (2 - arr.ndim))


def _broadcast(block: Block, arrays: dict, hint: str = "") -> tuple:
    """Common broadcast shape of named arrays, or a ParameterError naming every shape."""
    try:
        return np.broadcast_shapes(*(a.shape for a in arrays.values()))
    except ValueError:
        names = list(arrays)
        listed = ", ".join(f"'{k}' {shape_str(np.shape(a))}" for k, a in arrays.items())
        raise ParameterError(
            f"block '{block.name}' parameters {', '.join(repr(k) for k in names)} do not "
            f"broadcast to one shape: {listed}{hint}", block=block.name) from None


@register
class Sine(_SinusoidSum):
    """Sine: sum of sinusoids per channel, with its analytic time derivatives.

    Equation: y_i(t) = offset_i + sum_k A_ik sin(w_ik t + phi_ik), and
    y_dj = d^j y / dt^j = sum_k A_ik w_ik^j sin(w_ik t + phi_ik + j pi/2) for j = 1..m,
    m = derivatives (e.g. q_d, qdot_d, qddot_d for the reference dynamics (14), (16)).

    Ports (drawn for derivatives = 2; y_dj exists for j = 1..derivatives):
        | port | direction | shape | feedthrough |
        | y    | out       | (n,)  | -           |
        | y_d1 | out       | (n,)  | -           |
        | y_d2 | out       | (n,)  | -           |

    The shape is () when amplitude, frequency, phase and offset are all numbers.

    Parameters:
        amplitude: A; number, (n,) one sinusoid per channel, or (n, k) k sinusoids per channel.
        frequency: w in rad/s; same forms as amplitude.
        phase: phi in rad (default 0); same forms as amplitude.
        offset: number or (n,) (default 0).
        derivatives: m, number of derivative outputs y_d1..y_dm (0 to 8, default 0).
    Broadcasting is per channel: a 1-D array is one value per channel (axis 0), a 2-D
    array is (channel, sinusoid); write [[w1, w2]] for sinusoids shared by all channels.
    """

    params = {
        "amplitude": Param("array", doc="A (number, (n,) or (n, k))", ragged=True),
        "frequency": Param("array", doc="w [rad/s] (number, (n,) or (n, k))", ragged=True),
        "phase": Param("array", default=0.0, doc="phi [rad] (number, (n,) or (n, k))",
                       ragged=True),
        "offset": Param("array", default=0.0, doc="constant added per channel ((n,) or number)"),
        "derivatives": Param("int", default=0, doc="number of derivative outputs (0..8)"),
    }
    example = {"amplitude": [1.0, 0.5], "frequency": [[1.0, 3.0]], "phase": [0.0, 0.3],
               "offset": [0.1, -0.2], "derivatives": 2}

    def setup(self, amplitude, frequency, phase, offset, derivatives):
        parts = {"amplitude": _per_channel(self, "amplitude", amplitude),
                 "frequency": _per_channel(self, "frequency", frequency),
                 "phase": _per_channel(self, "phase", phase)}
        offset = np.asarray(offset, dtype=float)
        if offset.ndim > 1:
            raise ParameterError(
                f"block '{self.name}' parameter 'offset' must be a number or an (n,) vector, "
                f"got shape {offset.shape}", block=self.name)
        scalar = all(np.ndim(v) == 0 for v in (amplitude, frequency, phase, offset))
        n_channels, n_terms = _broadcast(
            self, parts, "; a 1-D array is one value per channel, write [[...]] for "
            "sinusoids shared by all channels")
        if offset.size not in (1, n_channels) and n_channels != 1:
            raise ParameterError(
                f"block '{self.name}' parameter 'offset' has {offset.size} values but "
                f"amplitude, frequency and phase give {n_channels} channels", block=self.name)
        n_channels = max(n_channels, offset.size)
        self.require_size("channels x sinusoids", n_channels * n_terms, MAX_TERMS)
        full = (n_channels, n_terms)
        self._declare_sinusoids(*(np.broadcast_to(parts[k], full) for k in parts),
                                np.broadcast_to(offset, (n_channels,)), derivatives, scalar)


@register
class MultiSine(_SinusoidSum):
    """MultiSine: n* frequencies shared by all channels, per-channel amplitudes and phases.

    Equation: tau*_i(t) = offset_i + sum_k A_ik sin(w_k t + phi_ik), k = 1..n* -- the
    disturbance with n* frequencies of eq. (113)/(a2); y_dj = d^j y / dt^j for j = 1..m.

    Ports (drawn for derivatives = 0; y_dj exists for j = 1..derivatives):
        | port | direction | shape | feedthrough |
        | y    | out       | (n,)  | -           |

    Parameters:
        frequencies: (n*,) frequencies w_k in rad/s.
        amplitudes: (n, n*) amplitudes A_ik (row i: channel i).
        phases: phi_ik in rad, broadcastable to (n, n*) by numpy rules (default 0).
        offset: number or (n,) (default 0).
        derivatives: m, number of derivative outputs y_d1..y_dm (0 to 8, default 0).
    """

    params = {
        "frequencies": Param("array", doc="(n*,) frequencies [rad/s]"),
        "amplitudes": Param("array", doc="(n, n*) amplitudes"),
        "phases": Param("array", default=0.0, doc="phases [rad], broadcastable to (n, n*)"),
        "offset": Param("array", default=0.0, doc="constant added per channel"),
        "derivatives": Param("int", default=0, doc="number of derivative outputs (0..8)"),
    }
    example = {"frequencies": [1.0, 2.5, 4.0], "amplitudes": [[1.0, 0.5, 0.2], [0.3, 0.0, 1.0]],
               "phases": [[0.0, 0.1, 0.2], [1.0, 1.1, 1.2]]}

    def setup(self, frequencies, amplitudes, phases, offset, derivatives):
        w = np.asarray(frequencies, dtype=float)
        A = np.asarray(amplitudes, dtype=float)
        if w.ndim != 1:
            raise ParameterError(
                f"block '{self.name}' parameter 'frequencies' must be an (n*,) vector, got "
                f"shape {w.shape}", block=self.name)
        if A.ndim != 2 or A.shape[1] != w.size:
            raise ParameterError(
                f"block '{self.name}' parameter 'amplitudes' must be an (n, n*) matrix with "
                f"n* = {w.size} columns (one per frequency), got shape {A.shape}",
                block=self.name)
        self.require_size("channels x frequencies", A.size, MAX_TERMS)
        phases = np.asarray(phases, dtype=float)
        offset = np.asarray(offset, dtype=float)
        _broadcast(self, {"amplitudes": A, "phases": phases})
        if phases.ndim > 2 or np.broadcast_shapes(A.shape, phases.shape) != A.shape:
            raise ParameterError(
                f"block '{self.name}' parameter 'phases' must broadcast to the amplitudes' "
                f"shape {A.shape}, got shape {phases.shape}", block=self.name)
        if offset.ndim > 1 or offset.size not in (1, A.shape[0]):
            raise ParameterError(
                f"block '{self.name}' parameter 'offset' must be a number or an (n,) vector "
                f"with n = {A.shape[0]}, got shape {offset.shape}", block=self.name)
        self._declare_sinusoids(A, np.broadcast_to(w, A.shape), np.broadcast_to(phases, A.shape),
                                np.broadcast_to(offset, A.shape[:1]), derivatives, False)


@register
class RandomDisturbance(_SinusoidSum):
    """RandomDisturbance: seeded band-limited random signal per channel (smooth).

    Equation: y_i(t) = sum_{k=1..N} A_ik sin(w_ik t + phi_ik), with, drawn once from
    numpy's default_rng(seed): w_ik = cutoff (k - 1 + U_ik) / N (one frequency in each of N
    equal bands of (0, cutoff)), phi_ik uniform in [0, 2 pi), A_ik Rayleigh distributed
    and scaled so that sum_k A_ik^2 / 2 = std_i^2 (the long-run mean square of channel i
    is exactly std_i^2).  A flat spectrum up to ``cutoff`` and nothing above; being a
    finite sum of sinusoids it is infinitely differentiable, so fixed-step solvers keep
    their order.

    Ports:
        | port | direction | shape | feedthrough |
        | y    | out       | (n,)  | -           |

    Parameters:
        n: number of channels.
        std: root-mean-square value per channel (number or (n,)).
        cutoff: highest frequency in rad/s (> 0).
        seed: seed of the random generator (whole number >= 0); same seed, same signal.
        components: N, sinusoids per channel (default 50).
    """

    params = {
        "n": Param("int", doc="number of channels"),
        "std": Param("array", doc="RMS value per channel (number or (n,))"),
        "cutoff": Param("float", doc="highest frequency [rad/s]"),
        "seed": Param("int", default=0, doc="random generator seed"),
        "components": Param("int", default=50, doc="sinusoids per channel"),
    }
    #: everything drawn from the seed lives in ``p``, so a batch may mix seeds
    stacked_params = ("seed",)
    example = {"n": 2, "std": [0.5, 1.0], "cutoff": 10.0, "seed": 7, "components": 20}

    def setup(self, n, std, cutoff, seed, components):
        name = self.name
        if n < 1:
            raise ParameterError(f"block '{name}' parameter 'n' must be at least 1, got {n}",
                                 block=name)
        if components < 1:
            raise ParameterError(f"block '{name}' parameter 'components' must be at least 1, "
                                 f"got {components}", block=name)
        if not cutoff > 0:
            raise ParameterError(f"block '{name}' parameter 'cutoff' must be positive, got "
                                 f"{cutoff}", block=name)
        if seed < 0:
            raise ParameterError(f"block '{name}' parameter 'seed' must be >= 0, got {seed}",
                                 block=name)
        std = np.asarray(std, dtype=float)
        if std.ndim > 1 or std.size not in (1, n) or np.any(std < 0):
            raise ParameterError(
                f"block '{name}' parameter 'std' must be a number or an (n,) vector with "
                f"n = {n}, all >= 0, got {std.tolist()}", block=name)
        self.require_size("n x components", n * components, MAX_TERMS)
        rng = np.random.default_rng(seed)
        frequency = cutoff * (np.arange(components) + rng.uniform(size=(n, components))) \
            / components
        phase = rng.uniform(0.0, 2.0 * math.pi, size=(n, components))
        amplitude = rng.rayleigh(size=(n, components))
        amplitude *= (np.broadcast_to(std, (n,)) * np.sqrt(2.0 / np.sum(amplitude ** 2, axis=1))
                      )[:, None]
        self._declare_sinusoids(amplitude, frequency, phase, np.zeros(n), 0, False)


@register
class Polynomial(Block):
    """Polynomial: y_i(t) = sum_k c_ik t^k per channel, with its analytic time derivatives.

    Equation: y_i(t) = sum_{k=0..d} c_ik t^k (ascending powers), and
    y_dj = d^j y / dt^j = sum_{k>=j} c_ik k!/(k-j)! t^(k-j) for j = 1..m, m = derivatives.
    (A ramp q_d = a + b t meets Theorem 1's assumption for every ell >= 1.)

    Ports (drawn for derivatives = 2; y_dj exists for j = 1..derivatives):
        | port | direction | shape | feedthrough |
        | y    | out       | (n,)  | -           |
        | y_d1 | out       | (n,)  | -           |
        | y_d2 | out       | (n,)  | -           |

    The shape is () when coefficients is a 1-D list.

    Parameters:
        coefficients: (n, d+1) matrix, row i = c_i0, c_i1, ..., c_id (ascending powers,
            unlike numpy.polyval); a 1-D list c_0..c_d gives a scalar signal.
        derivatives: m, number of derivative outputs y_d1..y_dm (0 to 8, default 0).
    """

    params = {
        "coefficients": Param("array", doc="(n, d+1) ascending-power coefficients per channel",
                              ragged=True),
        "derivatives": Param("int", default=0, doc="number of derivative outputs (0..8)"),
    }
    example = {"coefficients": [[0.0, 1.0, 0.5], [1.0, -0.5, 0.0]], "derivatives": 2}

    def setup(self, coefficients, derivatives):
        c = np.asarray(coefficients, dtype=float)
        if c.ndim not in (1, 2) or c.shape[-1] == 0:
            raise ParameterError(
                f"block '{self.name}' parameter 'coefficients' must be a non-empty list c_0..c_d "
                f"or an (n, d+1) matrix, got shape {c.shape}", block=self.name)
        m = _derivative_count(self, derivatives)
        scalar = c.ndim == 1
        c = c.reshape(1, -1) if scalar else c
        degree = c.shape[1] - 1
        self.require_size("degree", degree, MAX_DEGREE)
        coef = np.zeros((m + 1,) + c.shape)
        for j in range(min(m, degree) + 1):
            k = np.arange(j, degree + 1)
            falling = np.array([math.perm(int(ki), j) for ki in k], dtype=float)
            with np.errstate(over="ignore", invalid="ignore"):
                coef[j, :, :degree + 1 - j] = c[:, j:] * falling
            if not np.all(np.isfinite(coef[j])):
                raise ParameterError(
                    f"block '{self.name}': the coefficients of derivative {j} (c_k k!/(k-{j})!) "
                    f"are larger than the largest float; use smaller coefficients or fewer "
                    f"derivatives", block=self.name)
        self.set_param("coef", coef)                                  # (m+1, n, d+1)
        self._m = m
        self._scalar = scalar
        shape = () if scalar else (c.shape[0],)
        for name in _derivative_names(m):
            self.declare_output(name, shape, feedthrough=())
        self.set_kernels(output=polynomial_output, params=("coef",), packed=True)


# ---------------------------------------------------------------- piecewise-constant sources
def pulse_output(t, x, high, low, period, width, delay):
    """y = high on [delay + k period, delay + k period + width), k = 0, 1, ..., low elsewhere;
    the edges are the same floating-point numbers as Pulse.discontinuities."""
    k = np.floor((t - delay) / period)
    k = np.where(t >= delay + (k + 1.0) * period, k + 1.0, k)     # rounding of the division
    k = np.where(t < delay + k * period, k - 1.0, k)
    rise = delay + k * period
    on = (k >= 0.0) & (t < rise + width)
    return (np.where(on, high, low),)


@register
class Pulse(Block):
    """Pulse train: `high` for `width` seconds every `period` seconds from `delay` on, else `low`.

    Equation: y(t) = high if delay + k period <= t < delay + k period + width for some
    k = 0, 1, ..., else low (per element; right-continuous).  Its edges are declared as
    discontinuities, so a fixed-step run integrates it exactly (docs/discrete-time.md).

    Ports:
        | port | direction | shape                   | feedthrough |
        | y    | out       | broadcast shape of high, low | -      |

    Parameters:
        high: value during a pulse (number or array).
        low: value between pulses (default 0).
        period: pulse period [s] (> 0).
        width: pulse width [s] (0 < width < period).
        delay: start of the first pulse [s] (default 0).
    """

    params = {
        "high": Param("array", doc="value during a pulse"),
        "low": Param("array", default=0.0, doc="value between pulses"),
        "period": Param("float", doc="pulse period [s]"),
        "width": Param("float", doc="pulse width [s], 0 < width < period"),
        "delay": Param("float", default=0.0, doc="start of the first pulse [s]"),
    }
    example = {"high": [1.0, 2.0], "low": -0.5, "period": 0.2, "width": 0.05, "delay": 0.1}

    def setup(self, high, low, period, width, delay):
        if not period > 0 or not 0 < width < period:
            raise ParameterError(f"block '{self.name}': Pulse needs period > 0 and 0 < width < "
                                 f"period, got period {period:g}, width {width:g}",
                                 block=self.name)
        high, low = np.asarray(high, dtype=float), np.asarray(low, dtype=float)
        try:
            shape = np.broadcast_shapes(high.shape, low.shape)
        except ValueError:
            raise ParameterError(f"block '{self.name}' parameters 'high' {shape_str(high.shape)} "
                                 f"and 'low' {shape_str(low.shape)} do not broadcast",
                                 block=self.name) from None
        self.declare_output("y", shape, feedthrough=())
        self.set_param("high", np.broadcast_to(high, shape))
        self.set_param("low", np.broadcast_to(low, shape))
        self.period, self.width, self.delay = float(period), float(width), float(delay)
        self.set_kernels(output=pulse_output, params=("high", "low"),
                         static=(self.period, self.width, self.delay))

    def discontinuities(self, t_final):
        from fwdstep.core.instants import sample_instants
        rises = sample_instants(self, self.period, self.delay, t_final)
        return np.concatenate([rises, rises + self.width])


def piecewise_output(t, x, times, values):
    """y = values[i] with i = the number of switching times <= t (per variant)."""
    i = np.sum(times <= t, axis=1)                                   # (B,) or (1,)
    n = max(i.shape[0], values.shape[0])
    out = np.empty((n,) + values.shape[2:])
    for b in range(n):
        out[b] = values[min(b, values.shape[0] - 1), i[min(b, i.shape[0] - 1)]]
    return (out,)


@register
class PiecewiseConstant(Block):
    """Piecewise-constant signal: values[i] from times[i-1] to times[i] (a table of levels).

    Equation: y(t) = values[0] for t < times[0]; y(t) = values[i] for
    times[i-1] <= t < times[i]; y(t) = values[m] for t >= times[m-1] (right-continuous).
    The switching times are declared as discontinuities, so a fixed-step run integrates the
    signal exactly (a payload that changes at t = 5 s, a setpoint schedule).

    Ports:
        | port | direction | shape                       | feedthrough |
        | y    | out       | shape of one row of values  | -           |

    Parameters:
        times: the m switching times [s], strictly increasing.
        values: m + 1 levels (a list of numbers, or of equally shaped arrays).
    """

    params = {
        "times": Param("array", doc="switching times [s], strictly increasing"),
        "values": Param("array", doc="m + 1 levels, one more than times"),
    }
    example = {"times": [0.1, 0.25], "values": [[0.0, 1.0], [2.0, -1.0], [0.5, 0.5]]}

    def setup(self, times, values):
        times = np.atleast_1d(np.asarray(times, dtype=float))
        values = np.asarray(values, dtype=float)
        if times.ndim != 1 or (times.size > 1 and not np.all(np.diff(times) > 0)):
            raise ParameterError(f"block '{self.name}' parameter 'times' must be a strictly "
                                 "increasing list of times", block=self.name)
        if values.ndim == 0 or values.shape[0] != times.size + 1:
            raise ParameterError(f"block '{self.name}' needs one more value than times: "
                                 f"{times.size} times, {values.shape[0] if values.ndim else 1} "
                                 "values", block=self.name)
        self.declare_output("y", values.shape[1:], feedthrough=())
        self.set_param("times", times)
        self.set_param("values", values)
        self.set_kernels(output=piecewise_output, params=("times", "values"))
        self.jumps = tuple(times.tolist())   # outside p: never batched across other times

    def discontinuities(self, t_final):
        return np.asarray(self.jumps)


def piecewise_linear_output(t, x, times, values):
    """y = values interpolated linearly in t between the breakpoints, held outside them."""
    i = np.sum(times <= t, axis=1)                                   # (B,) or (1,)
    n = max(i.shape[0], values.shape[0], times.shape[0])
    m = times.shape[1]
    out = np.empty((n,) + values.shape[2:])
    for b in range(n):
        k = i[min(b, i.shape[0] - 1)]
        tb = times[min(b, times.shape[0] - 1)]
        vb = values[min(b, values.shape[0] - 1)]
        if k == 0:
            out[b] = vb[0]
        elif k == m:
            out[b] = vb[m - 1]
        else:
            w = (t - tb[k - 1]) / (tb[k] - tb[k - 1])
            out[b] = vb[k - 1] + w * (vb[k] - vb[k - 1])
    return (out,)


@register
class PiecewiseLinear(Block):
    """Piecewise-linear signal: a table of (time, value) points joined by straight lines.

    Equation: y(t) = values[0] for t < times[0]; y(t) = values[i-1] + (t - times[i-1]) /
    (times[i] - times[i-1]) (values[i] - values[i-1]) for times[i-1] <= t < times[i];
    y(t) = values[m-1] for t >= times[m-1] (a ramp, a trapezoidal profile, a load that is
    applied gradually).  Its kinks are declared as discontinuities (of the derivative), so a
    fixed-step run integrates it exactly.

    Ports:
        | port | direction | shape                       | feedthrough |
        | y    | out       | shape of one row of values  | -           |

    Parameters:
        times: the m breakpoints [s], strictly increasing (m >= 2).
        values: m values (a list of numbers, or of equally shaped arrays).
    """

    params = {
        "times": Param("array", doc="breakpoints [s], strictly increasing"),
        "values": Param("array", doc="one value per breakpoint"),
    }
    example = {"times": [0.1, 0.25, 0.4], "values": [[0.0, 1.0], [2.0, -1.0], [0.5, 0.5]]}

    def setup(self, times, values):
        times = np.atleast_1d(np.asarray(times, dtype=float))
        values = np.asarray(values, dtype=float)
        if times.ndim != 1 or times.size < 2 or not np.all(np.diff(times) > 0):
            raise ParameterError(f"block '{self.name}' parameter 'times' must be a strictly "
                                 "increasing list of at least 2 times", block=self.name)
        if values.ndim == 0 or values.shape[0] != times.size:
            raise ParameterError(f"block '{self.name}' needs one value per time: "
                                 f"{times.size} times, {values.shape[0] if values.ndim else 1} "
                                 "values", block=self.name)
        self.declare_output("y", values.shape[1:], feedthrough=())
        self.set_param("times", times)
        self.set_param("values", values)
        self.set_kernels(output=piecewise_linear_output, params=("times", "values"))
        self.jumps = tuple(times.tolist())   # outside p: never batched across other times

    def discontinuities(self, t_final):
        return np.asarray(self.jumps)
