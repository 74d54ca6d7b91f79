"""Generic linear filters and combinations for stacked reference dynamics (paper Sec. 5).

Three blocks that keep the wiring of Theorems 7-9 independent of the number n* of unknown
frequencies:

* ``FilterDerivatives`` -- one filter num(p)/den(p) and several derivatives of its output,
  stacked on a new last axis (W_i = p^(2i-2) H*(p) psi_2 of eq. (120), i = 1..n*);
* ``TransferFunctionSum`` -- a sum of filters with one shared denominator on several inputs,
  with derivative outputs (e_2, e_2', e_2'' of the realisation of eq. (118));
* ``LinearCombination`` -- sum_k w_k u[..., k] with time-varying weights w (the
  theta_hat_i-weighted sums of eq. (a4), (a5)).
"""
from __future__ import annotations

import numpy as np

from fwdstep.core import kernelops as ko
from fwdstep.core.block import Block, Param
from fwdstep.core.errors import ParameterError
from fwdstep.core.linear import LinearBlock, observer_form
from fwdstep.core.registry import register

from .linear import MAX_LINEAR_STATES, MAX_ORDER, initial_values, polynomial, signal_shape

#: The largest number of stacked derivatives, summed inputs or combined slices.
MAX_BANK = 64


def _denominator(block, den) -> np.ndarray:
    den = polynomial(block, "den", den)
    if not np.any(den):
        raise ParameterError(f"block '{block.name}' parameter 'den' must not be zero",
                             block=block.name)
    block.require_size("denominator degree", den.size - 1, MAX_ORDER)
    return den


def _count(block, key: str, value: int, minimum: int = 0) -> int:
    if value < minimum:
        raise ParameterError(f"block '{block.name}' parameter '{key}' must be at least "
                             f"{minimum}, got {value}", block=block.name)
    return block.require_size(key, value, MAX_BANK)


@register
class FilterDerivatives(LinearBlock):
    """A filter num(p)/den(p) and derivatives of its output, stacked on a new last axis.

    Equation: y[..., k] = p^(m_k) num(p) / den(p) u, element by element, with the derivative
    orders m_k = first + k step, k = 0..count-1 (e.g. W_i = p^(2i-2) H*(p) psi_2 of eq. (120)
    with first = 0, step = 2, count = n*); every p^(m_k) num(p) / den(p) must be proper.
    Realisation: controllable canonical form per element, den(p) xi = u, state
    (xi, p xi, ..., p^(N-1) xi), N = deg den, so all outputs share N states per element and
    y[..., k] = (p^(m_k) num)(p) xi with p^N xi = u - (den(p) - p^N) xi.

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | (*shape, count) | u if some m_k = deg den - deg num, else - |

    Parameters:
        num: numerator coefficients, highest power first.
        den: denominator coefficients, highest power first.
        first: derivative order m_0 of the first output (default 0).
        step: increment of the derivative order between outputs (default 1).
        count: number of outputs stacked on the last axis (default 1).
        shape: shape of the signal u (list; [] or omitted for a scalar).
        initial: initial state, broadcast to (*shape, N) (default 0): per element
            (xi, p xi, ..., p^(N-1) xi).
    """

    params = {
        "num": Param("array", doc="numerator coefficients, highest power first"),
        "den": Param("array", doc="denominator coefficients, highest power first"),
        "first": Param("int", default=0, doc="derivative order of the first output"),
        "step": Param("int", default=1, doc="increment of the derivative order"),
        "count": Param("int", default=1, doc="number of outputs (last axis of y)"),
        "shape": Param("array", default=None, doc="signal shape, e.g. [2] or [2, 4]; "
                       "default: scalar"),
        "initial": Param("array", default=None, doc="initial state, broadcast to "
                         "(*shape, deg den) (default 0)"),
    }
    shape_from = {"shape": ("u",)}
    example = {"num": [1.0, 4.0, 4.0], "den": [1.0, 6.0, 15.0, 20.0, 15.0, 6.0, 1.0],
               "first": 0, "step": 2, "count": 3, "shape": [2]}

    def setup(self, num, den, first, step, count, shape, initial):
        den = _denominator(self, den)
        num = polynomial(self, "num", num)
        _count(self, "first", first)
        _count(self, "step", step)
        count = _count(self, "count", count, 1)
        order = den.size - 1
        orders = [first + k * step for k in range(count)]
        deg_num = num.size - 1 if np.any(num) else 0
        if deg_num + orders[-1] > order:
            raise ParameterError(
                f"block '{self.name}': derivative order {orders[-1]} of num/den (degrees "
                f"{deg_num}/{order}) is improper; the largest order allowed is "
                f"{order - deg_num}", block=self.name)
        shape = signal_shape(self, "shape", shape)
        size = int(np.prod(shape, dtype=np.int64))
        self.require_size("number of states (order x signal elements)", order * size,
                          MAX_LINEAR_STATES)
        self.require_size("number of output elements", size * count, MAX_LINEAR_STATES)
        den_monic = den / den[0]
        A = np.zeros((order, order))
        if order:
            A[:-1, 1:] = np.eye(order - 1)
            A[-1, :] = -den_monic[:0:-1]           # p^N xi = u - sum a_i p^i xi
        b = np.zeros((order, 1))
        if order:
            b[-1, 0] = 1.0 / den[0]
        C = np.zeros((count, order))
        D = np.zeros((count, 1))
        for k, m in enumerate(orders):
            poly = np.concatenate([num, np.zeros(m)])[::-1]    # ascending coefficients
            poly = np.concatenate([poly, np.zeros(order + 1 - poly.size)])[:order + 1]
            lead = poly[order]
            C[k] = poly[:order] + lead * (A[-1] if order else 0.0)
            D[k, 0] = lead / den[0]
        eye = np.eye(size)
        x0 = initial_values(self, initial, shape + (order,), "(*shape, deg den)")
        self.declare_input("u", shape)
        self.declare_output("y", shape + (count,))
        self.set_linear(np.kron(eye, A), {"u": np.kron(eye, b)}, {"y": np.kron(eye, C)},
                        {("y", "u"): np.kron(eye, D)}, x0=x0)
        self.orders = orders


@register
class TransferFunctionSum(LinearBlock):
    """Sum of filters with one shared denominator on several inputs, with output derivatives.

    Equation: y = sum_j num_j(p) / den(p) u_j, element by element (all u_j of one shape), and
    y_dk = p^k y for k = 1..derivatives.  With the observer-canonical realisation
    xdot = A x + sum_j B_j u_j, y = C x + sum_j D_j u_j (state shared by all inputs), the
    derivatives are exact for any state:
        y_dk = C A^k x + sum_j sum_{i=0..k} h_j,(k-i) u_j^(i),
    h_j,0 = D_j, h_j,r = C A^(r-1) B_j the Markov parameters; h_j,r = 0 for r < r_j (the
    relative degree of input j), so y_dk needs the derivatives u_j^(i) for i <= k - r_j only,
    given as the inputs u<j>_d<i> (declared by ``input_derivatives``).  Used for
    e_2 = chi_2 - chi_1 of eq. (118) and its first two derivatives (docs/theorems7-9.md).

    Ports (drawn for two inputs, input_derivatives = [1, 0], derivatives = 2):
        | port  | direction | shape | feedthrough |
        | u1    | in        | shape | -           |
        | u2    | in        | shape | -           |
        | u1_d1 | in        | shape | -           |
        | y     | out       | shape | u_j with deg num_j = deg den |
        | y_d1  | out       | shape | u_j, u_j_di with h_j,(1-i) != 0 |
        | y_d2  | out       | shape | u_j, u_j_di with h_j,(2-i) != 0 |

    Parameters:
        den: shared denominator coefficients, highest power first.
        nums: list of numerators (one per input u1, u2, ...), highest power first; each of
            degree <= deg den.
        derivatives: number of derivative outputs y_d1..y_dm (default 0).
        input_derivatives: per input, how many of its derivatives are supplied as inputs
            u<j>_d1.. (default none); refused when an output needs one that is not supplied.
        omit_direct: input numbers j (from 1) whose direct terms h_j,k u_j are left out of
            every output (add them outside the block): breaks a loop through the block when
            a state-only output (y) and a direct term of the same input are in one loop, as
            e_2 -> psi_2 -> W -> v -> e_2'' in eq. (118) (default none).
        shape: shape of every input and output (list; [] or omitted for a scalar).
        initial: initial observer-form state, broadcast to (order, *shape) (default 0).
    """

    params = {
        "den": Param("array", doc="shared denominator coefficients, highest power first"),
        "nums": Param("any", doc="list of numerators, one per input, highest power first"),
        "derivatives": Param("int", default=0, doc="number of derivative outputs y_d1.."),
        "input_derivatives": Param("array", default=None, doc="per input: number of supplied "
                                   "input derivatives (default 0 each)"),
        "omit_direct": Param("array", default=None, doc="inputs j (from 1) whose direct terms "
                             "h_j,k u_j are left out of every output y_dk"),
        "shape": Param("array", default=None, doc="signal shape, e.g. [2]; default: scalar"),
        "initial": Param("array", default=None, doc="initial observer-form state, broadcast "
                         "to (order, *shape) (default 0)"),
    }
    shape_from = {"shape": ("y", "y_d1", "y_d2", "u1", "u2")}
    example = {"den": [1.0, 3.0, 3.0, 1.0], "nums": [[2.0, 1.0, 1.0], [1.0]],
               "derivatives": 2, "input_derivatives": [1, 0], "shape": [2]}

    def setup(self, den, nums, derivatives, input_derivatives, omit_direct, shape, initial):
        den = _denominator(self, den)
        order = den.size - 1
        if isinstance(nums, np.ndarray):
            nums = list(nums) if nums.ndim == 2 else [nums]
        if not isinstance(nums, (list, tuple)) or not nums:
            raise ParameterError(f"block '{self.name}' parameter 'nums' must be a non-empty "
                                 f"list of coefficient lists", block=self.name)
        m = _count(self, "number of inputs", len(nums), 1)
        nums = [polynomial(self, f"nums[{j}]", v) for j, v in enumerate(nums)]
        for j, num in enumerate(nums):
            if np.any(num) and num.size - 1 > order:
                raise ParameterError(
                    f"block '{self.name}' numerator {j + 1} has degree {num.size - 1} > "
                    f"denominator degree {order} (improper)", block=self.name)
        derivatives = _count(self, "derivatives", derivatives)
        if input_derivatives is None:
            have = [0] * m
        else:
            arr = np.atleast_1d(np.asarray(input_derivatives, dtype=float))
            if arr.shape != (m,) or np.any(arr < 0) or np.any(arr != np.floor(arr)):
                raise ParameterError(
                    f"block '{self.name}' parameter 'input_derivatives' must be {m} "
                    f"non-negative whole numbers (one per input), got {arr.tolist()}",
                    block=self.name)
            have = [int(_count(self, "input_derivatives", int(a))) for a in arr]
        omit = set()
        if omit_direct is not None:
            arr = np.atleast_1d(np.asarray(omit_direct, dtype=float))
            if arr.ndim != 1 or np.any(arr < 1) or np.any(arr > m) or np.any(arr != np.floor(arr)):
                raise ParameterError(
                    f"block '{self.name}' parameter 'omit_direct' must list input numbers "
                    f"1..{m}, got {arr.tolist()}", block=self.name)
            omit = {int(a) - 1 for a in arr}
        shape = signal_shape(self, "shape", shape)
        size = int(np.prod(shape, dtype=np.int64))
        self.require_size("number of states (order x signal elements)", order * size,
                          MAX_LINEAR_STATES)
        A, B, C, D = observer_form(den, nums)
        rel = [order - (num.size - 1) if np.any(num) else order + 1 for num in nums]

        def markov(j: int, r: int) -> float:
            if r < rel[j]:
                return 0.0
            if r == 0:
                return float(D[j])
            return float((C @ np.linalg.matrix_power(A, r - 1) @ B[:, j])[0])

        for j in range(m):
            self.declare_input(f"u{j + 1}", shape)
        for j in range(m):
            for i in range(1, have[j] + 1):
                self.declare_input(f"u{j + 1}_d{i}", shape)
        eye = np.eye(size)
        Cs, Ds = {}, {}
        for k in range(derivatives + 1):
            out = "y" if k == 0 else f"y_d{k}"
            self.declare_output(out, shape)
            Cs[out] = np.kron(C @ np.linalg.matrix_power(A, k), eye)
            for j in range(m):
                for i in range(k + 1):
                    coefficient = markov(j, k - i)
                    if coefficient == 0.0 or (i == 0 and j in omit):
                        continue
                    if i > have[j]:
                        raise ParameterError(
                            f"block '{self.name}': output {out} needs derivative {i} of input "
                            f"u{j + 1} (relative degree {rel[j]}); supply it as input "
                            f"u{j + 1}_d{i} via input_derivatives", block=self.name)
                    port = f"u{j + 1}" if i == 0 else f"u{j + 1}_d{i}"
                    Ds[(out, port)] = coefficient * eye
        x0 = initial_values(self, initial, (order,) + shape, "(order, *shape)")
        self.set_linear(np.kron(A, eye), {f"u{j + 1}": np.kron(B[:, j:j + 1], eye)
                                          for j in range(m)}, Cs, Ds, x0=x0)
        self.relative_degrees = rel
        #: direct_terms[k][j] = h_j,k, the coefficient of u_j in y_dk (for omit_direct users)
        self.direct_terms = [[markov(j, k) for j in range(m)] for k in range(derivatives + 1)]


@register
class LinearCombination(Block):
    """Weighted sum over the last axis with time-varying weights: y = sum_k w_k u[..., k].

    Equation: y = sum_k w_k u[..., k], w = [c, fixed] (the signal c followed by the constant
    weights ``fixed``), e.g. v = sum_i theta_hat_i W_i of eq. (118) or the bracket
    sum_i theta_hat_i X_i + X_(n*+1) of eq. (a4), (a5) (c = theta_hat, fixed = [1]).

    Ports (drawn for weights = [m]):
        | port | direction | shape         | feedthrough |
        | c    | in        | (m,) or ()    | -           |
        | u    | in        | (*shape, K)   | -           |
        | y    | out       | shape         | c, u        |

    Parameters:
        weights: shape of c: [m] for a vector of m weights, [] for one scalar weight.
        fixed: constant weights appended after c (default none); K = m + len(fixed).
        shape: shape of each slice u[..., k] and of y (list; [] for scalars).
    """

    params = {
        "weights": Param("array", doc="shape of c: [m] or [] (scalar)"),
        "fixed": Param("array", default=None, doc="constant weights appended after c"),
        "shape": Param("array", default=None, doc="shape of y, e.g. [2] or [2, 4]"),
    }
    shape_from = {"shape": ("y",)}
    example = {"weights": [3], "fixed": [1.0], "shape": [2, 4]}

    def setup(self, weights, fixed, shape):
        wshape = np.atleast_1d(np.asarray(weights, dtype=float)) if np.ndim(weights) else \
            np.asarray(weights, dtype=float)
        if wshape.size == 0:
            m, c_shape = 1, ()
        elif wshape.shape == (1,) and wshape[0] >= 1 and wshape[0] == np.floor(wshape[0]):
            m = int(wshape[0])
            c_shape = (m,)
        else:
            raise ParameterError(f"block '{self.name}' parameter 'weights' must be [m] (m >= "
                                 f"1) or [] (a scalar), got {np.asarray(weights).tolist()}",
                                 block=self.name)
        self.require_size("number of weights", m, MAX_BANK)
        fixed = np.zeros(0) if fixed is None else np.atleast_1d(np.asarray(fixed, float))
        if fixed.ndim != 1:
            raise ParameterError(f"block '{self.name}' parameter 'fixed' must be a list of "
                                 f"numbers", block=self.name)
        self.require_size("number of fixed weights", fixed.size, MAX_BANK)
        shape = signal_shape(self, "shape", shape)
        self._K = m + fixed.size
        self._m = m
        self._size = int(np.prod(shape, dtype=np.int64))
        self._shape = shape
        self.declare_input("c", c_shape)
        self.declare_input("u", shape + (self._K,))
        self.declare_output("y", shape)
        self.set_param("fixed", fixed)
        self.set_kernels(output=linear_combination_output, params=("fixed",))


def annihilator_coefficients(omegas) -> np.ndarray:
    """theta_1..theta_n* of eq. (113)-(a2): prod_i (s + omega_i^2) = s^n* + theta_n* s^(n*-1)
    + ... + theta_1, so theta_1 = prod omega_i^2 and theta_n* = sum omega_i^2."""
    squares = np.asarray(omegas, dtype=float) ** 2
    return np.poly(-squares)[1:][::-1].astype(float)


@register
class FrequencyParameters(Block):
    """The constant theta_1..theta_n* of eq. (113)-(a2) computed from frequencies omega_i.

    Equation: prod_i (p^2 + omega_i^2) = p^(2n*) + theta_n* p^(2n*-2) + ... + theta_2 p^2
    + theta_1, i.e. theta_1 = prod omega_i^2, ..., theta_n* = sum omega_i^2 (for n* = 3 the
    three lines after eq. (113)); the true values that theta_hat_i of eq. (120) estimate.

    Ports:
        | port  | direction | shape | feedthrough |
        | theta | out       | (n*,) | -           |

    Parameters:
        omegas: (n*,) frequencies omega_i in rad/s.
    """

    params = {"omegas": Param("array", doc="(n*,) frequencies omega_i [rad/s]")}
    example = {"omegas": [1.0, 2.0, 3.0]}

    def setup(self, omegas):
        omegas = np.atleast_1d(np.asarray(omegas, dtype=float))
        if omegas.ndim != 1 or omegas.size == 0:
            raise ParameterError(f"block '{self.name}' parameter 'omegas' must be a non-empty "
                                 f"list of frequencies, got shape {omegas.shape}",
                                 block=self.name)
        self.require_size("number of frequencies", omegas.size, MAX_BANK)
        self.declare_output("theta", (omegas.size,), feedthrough=())
        self.set_param("theta", annihilator_coefficients(omegas))
        self.set_kernels(output=frequency_parameters_output, params=("theta",))


def linear_combination_output(t, x, c, u, fixed):
    """y = sum_k w_k u[..., k] with w = [c, fixed] (c (B, m) or (B,) for one weight)."""
    cc = np.ascontiguousarray(c)
    m = cc.size // cc.shape[0]
    K = u.shape[u.ndim - 1]
    B = max(cc.shape[0], fixed.shape[0])
    w = np.empty((B, K))
    w[:, :m] = cc.reshape((cc.shape[0], m))
    w[:, m:] = fixed
    uc = np.ascontiguousarray(u)
    size = uc.size // (uc.shape[0] * K)
    y = ko.bmatvec(uc.reshape((uc.shape[0], size, K)), w)
    return (y.reshape((y.shape[0],) + uc.shape[1:-1]),)


def frequency_parameters_output(t, x, theta):
    """theta = the constant coefficients (see the block)."""
    return (theta,)
