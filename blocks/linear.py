"""Linear time-invariant blocks: integrators, transfer functions and state-space systems.

All three are ``fwdstep.core.linear.LinearBlock`` subclasses: their constructors only build the
generic matrices (A, B_j, C_k, D_kj) over the vectorised (C-order flattened) ports; the
run-time code is shared.  A signal of several elements is filtered element by element (or
column by column) by taking the Kronecker product of a small realisation with an identity:
with C-order flattening, ``vec(M X) = kron(M, I_p) vec(X)`` for ``X`` of shape ``(m, p)``.
"""
from __future__ import annotations

import numpy as np

from fwdstep.core.block import Param
from fwdstep.core.errors import ParameterError
from fwdstep.core.linear import LinearBlock, observer_form
from fwdstep.core.registry import register

#: The generic linear form stores dense (N, N) matrices; refuse realisations whose dense
#: state matrix would exceed this many states (2000 states = 32 MB for A alone).
MAX_LINEAR_STATES = 2000
#: The largest transfer-function or state-space order accepted.
MAX_ORDER = 200


def signal_shape(block, key: str, value) -> tuple:
    """Convert a ``shape`` parameter (None, [], [n], [n, p], ...) to a tuple of positive ints."""
    if value is None:
        return ()
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.ndim != 1 or np.any(arr < 1) or np.any(arr != np.floor(arr)):
        raise ParameterError(
            f"block '{block.name}' parameter '{key}' must be a list of positive whole numbers "
            f"(e.g. [2] or [2, 3]; [] for a scalar), got {np.asarray(value).tolist()!r}",
            block=block.name)
    shape = tuple(int(s) for s in arr)
    block.require_size(f"number of elements of '{key}'", int(np.prod(shape, dtype=np.int64)),
                       MAX_LINEAR_STATES)
    return shape


def initial_values(block, value, shape: tuple, meaning: str) -> np.ndarray:
    """Broadcast an ``initial`` parameter to ``shape`` and flatten it (C order)."""
    if value is None:
        return np.zeros(int(np.prod(shape, dtype=np.int64)))
    arr = np.asarray(value, dtype=float)
    try:
        return np.broadcast_to(arr, shape).ravel()
    except ValueError:
        raise ParameterError(
            f"block '{block.name}' parameter 'initial' has shape {arr.shape}, which does not "
            f"broadcast to {shape} ({meaning})", block=block.name) from None


def polynomial(block, key: str, value) -> np.ndarray:
    """A polynomial coefficient list, highest power first, leading zeros removed."""
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.ndim != 1:
        raise ParameterError(
            f"block '{block.name}' parameter '{key}' must be a list of coefficients (highest "
            f"power first), got an array of shape {arr.shape}", block=block.name)
    trimmed = np.trim_zeros(arr, "f")
    return trimmed if trimmed.size else np.zeros(1)


@register
class Integrator(LinearBlock):
    """Integrator: the output is the integral of the input, element-wise for any signal shape.

    Equation: xdot = u, y = x, x(0) = initial.

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | shape | -           |

    Parameters:
        shape: shape of the signal (list; [] or omitted for a scalar).
        initial: initial value y(0), broadcast to shape (default 0).
    """

    params = {
        "shape": Param("array", default=None, doc="signal shape, e.g. [2] or [2, 3]; "
                       "default: scalar"),
        "initial": Param("array", default=None, doc="initial value, broadcast to shape "
                         "(default 0)"),
    }
    shape_from = {"shape": ("u", "y")}
    example = {"shape": [2], "initial": [1.0, -1.0]}

    def setup(self, shape, initial):
        shape = signal_shape(self, "shape", shape)
        size = int(np.prod(shape, dtype=np.int64))
        x0 = initial_values(self, initial, shape, "the signal shape")
        self.declare_input("u", shape)
        self.declare_output("y", shape, feedthrough=())
        eye = np.eye(size)
        self.set_linear(np.zeros((size, size)), {"u": eye}, {"y": eye}, x0=x0)


@register
class TransferFunction(LinearBlock):
    """Transfer function: a proper SISO num(p)/den(p) applied to every element of the signal.

    Equation: y = num(p) / den(p) u, element by element (p = d/dt), one shared denominator.
    Realisation: observer canonical form per element, x_1 = y - d0 u (d0 = the direct
    feedthrough, 0 for a strictly proper transfer function); a signal of m elements uses
    kron(A, I_m), kron(B, I_m), kron(C, I_m), d0 I_m, so the state is (order, *shape).

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | shape | u if deg num = deg den, else - |

    Parameters:
        num: numerator coefficients, highest power first (e.g. [1, 2] for p + 2).
        den: denominator coefficients, highest power first; deg num <= deg den.
        shape: shape of the signal (list; [] or omitted for a scalar).
        initial: initial observer-form state, broadcast to (order, *shape) (default 0);
            its first row is y(0) - d0 u(0).
    """

    params = {
        "num": Param("array", doc="numerator coefficients, highest power first"),
        "den": Param("array", doc="denominator coefficients, highest power first"),
        "shape": Param("array", default=None, doc="signal shape, e.g. [2] or [2, 3]; "
                       "default: scalar"),
        "initial": Param("array", default=None, doc="initial observer-form state, broadcast "
                         "to (order, *shape) (default 0)"),
    }
    shape_from = {"shape": ("u", "y")}
    example = {"num": [1.0, 2.0], "den": [1.0, 3.0, 2.0], "shape": [2]}

    def setup(self, num, den, shape, initial):
        num = polynomial(self, "num", num)
        den = polynomial(self, "den", den)
        if not np.any(den):
            raise ParameterError(f"block '{self.name}' parameter 'den' must not be zero",
                                 block=self.name)
        order = den.size - 1
        if np.any(num) and num.size - 1 > order:
            raise ParameterError(
                f"block '{self.name}' transfer function is improper: numerator degree "
                f"{num.size - 1} > denominator degree {order}", block=self.name)
        self.require_size("denominator degree", order, MAX_ORDER)
        shape = signal_shape(self, "shape", shape)
        size = int(np.prod(shape, dtype=np.int64))
        self.require_size("number of states (order x signal elements)", order * size,
                          MAX_LINEAR_STATES)
        x0 = initial_values(self, initial, (order,) + shape, "(order, *shape)")
        A, B, C, D = observer_form(den, [num])
        eye = np.eye(size)
        self.declare_input("u", shape)
        self.declare_output("y", shape)
        self.set_linear(np.kron(A, eye), {"u": np.kron(B, eye)}, {"y": np.kron(C, eye)},
                        {("y", "u"): D[0] * eye}, x0=x0)


@register
class StateSpace(LinearBlock):
    """State-space system (A, B, C, D) applied to a vector signal, or column by column to a matrix.

    Equation: xdot = A x + B u, y = C x + D u; with `columns` = p the input is U of shape
    (n_u, p) and each column is filtered by its own copy of the system: Xdot = A X + B U,
    Y = C X + D U (as the filtered regressor W = G(p) Y of eq. (50) needs).

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | (n_u,) or (n_u, p) | - |
        | y    | out       | (n_y,) or (n_y, p) | u if D != 0, else - |

    Parameters:
        A: (n_x, n_x) state matrix.
        B: (n_x, n_u) input matrix.
        C: (n_y, n_x) output matrix.
        D: (n_y, n_u) feedthrough matrix (default zero).
        columns: p, the number of columns of a matrix signal (default: a vector signal).
        initial: initial state, broadcast to (n_x,) or (n_x, p) (default 0).
    """

    params = {
        "A": Param("array", doc="(n_x, n_x) state matrix"),
        "B": Param("array", doc="(n_x, n_u) input matrix"),
        "C": Param("array", doc="(n_y, n_x) output matrix"),
        "D": Param("array", default=None, doc="(n_y, n_u) feedthrough matrix (default 0)"),
        "columns": Param("int", default=None, doc="number of columns p of a matrix signal "
                         "(default: vector signal)"),
        "initial": Param("array", default=None, doc="initial state, broadcast to (n_x,) or "
                         "(n_x, p) (default 0)"),
    }
    example = {"A": [[0.0, 1.0], [-2.0, -3.0]], "B": [[0.0], [1.0]], "C": [[1.0, 0.0]],
               "D": [[0.5]], "columns": 3}

    def _matrix(self, key: str, value, rows: int | None, cols: int | None, what: str):
        arr = np.asarray(value, dtype=float)
        if arr.ndim != 2:
            raise ParameterError(
                f"block '{self.name}' parameter '{key}' must be a matrix ({what}), got an "
                f"array of shape {arr.shape}", block=self.name)
        if (rows is not None and arr.shape[0] != rows) or (cols is not None
                                                             and arr.shape[1] != cols):
            raise ParameterError(
                f"block '{self.name}' parameter '{key}' has shape {arr.shape}, expected "
                f"{what}", block=self.name)
        return arr

    def setup(self, A, B, C, D, columns, initial):
        A = self._matrix("A", A, None, None, "(n_x, n_x)")
        n_x = A.shape[0]
        if A.shape != (n_x, n_x) or n_x == 0:
            raise ParameterError(
                f"block '{self.name}' parameter 'A' has shape {A.shape}, expected a non-empty "
                f"square matrix (n_x, n_x)", block=self.name)
        self.require_size("number of states n_x", n_x, MAX_ORDER)
        B = self._matrix("B", B, n_x, None, f"({n_x}, n_u) with n_x = {n_x} from A")
        n_u = B.shape[1]
        C = self._matrix("C", C, None, n_x, f"(n_y, {n_x}) with n_x = {n_x} from A")
        n_y = C.shape[0]
        if n_u == 0 or n_y == 0:
            raise ParameterError(f"block '{self.name}' needs at least one input and one "
                                 f"output (B is {B.shape}, C is {C.shape})", block=self.name)
        D = (np.zeros((n_y, n_u)) if D is None else
             self._matrix("D", D, n_y, n_u, f"({n_y}, {n_u}) = (n_y from C, n_u from B)"))
        if columns is None:
            p, in_shape, out_shape = 1, (n_u,), (n_y,)
        else:
            if columns < 1:
                raise ParameterError(f"block '{self.name}' parameter 'columns' must be at "
                                     f"least 1, got {columns}", block=self.name)
            p, in_shape, out_shape = columns, (n_u, columns), (n_y, columns)
        self.require_size("number of states (n_x x columns)", n_x * p, MAX_LINEAR_STATES)
        self.require_size("number of input elements (n_u x columns)", n_u * p,
                          MAX_LINEAR_STATES)
        self.require_size("number of output elements (n_y x columns)", n_y * p,
                          MAX_LINEAR_STATES)
        state_shape = (n_x,) if columns is None else (n_x, p)
        x0 = initial_values(self, initial, state_shape, "the state shape")
        eye = np.eye(p)
        self.declare_input("u", in_shape)
        self.declare_output("y", out_shape)
        self.set_linear(np.kron(A, eye), {"u": np.kron(B, eye)}, {"y": np.kron(C, eye)},
                        {("y", "u"): np.kron(D, eye)}, x0=x0)
