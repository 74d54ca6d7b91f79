"""Memoryless arithmetic blocks: gains, sums and products of signals."""
from __future__ import annotations

import numpy as np

from fwdstep.block import Block, Param, as_written
from fwdstep.errors import ParameterError
from fwdstep.linear import LinearForm
from fwdstep.registry import register

#: Largest signal a scalar Gain or a Sum describes as a dense LinearForm for fusion.
MAX_FUSED_SIZE = 2000


@register
class Gain(Block):
    """Gain: y = K u, with K a scalar (any signal shape) or a matrix (vector signal).

    Equation: y = K u.

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | (m,) for matrix K, else shape of u | u |

    Parameters:
        gain: scalar, or (m, n) matrix applied to a vector input of size n.
        shape: shape of the input signal u (list; [] for a scalar).
    """

    params = {
        "gain": Param("array", doc="scalar or (m, n) matrix"),
        "shape": Param("array", default=None, doc="input shape, e.g. [2]; default: n of the "
                       "matrix gain, or scalar"),
    }
    example = {"gain": [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]}

    def setup(self, gain, shape):
        K = np.asarray(gain, dtype=float)
        if K.ndim == 0:
            in_shape = () if shape is None else tuple(int(s) for s in np.atleast_1d(shape))
            self.declare_input("u", in_shape)
            self.declare_output("y", in_shape)
            self._matrix = False
        elif K.ndim == 2:
            in_shape = (K.shape[1],)
            if shape is not None and tuple(int(s) for s in np.atleast_1d(shape)) != in_shape:
                raise ParameterError(
                    f"block '{self.name}' parameter 'gain' has shape {K.shape}, which does not "
                    f"fit an input of shape {tuple(int(s) for s in np.atleast_1d(shape))}",
                    block=self.name)
            self.declare_input("u", in_shape)
            self.declare_output("y", (K.shape[0],))
            self._matrix = True
        else:
            raise ParameterError(f"block '{self.name}' parameter 'gain' must be a scalar or a "
                                 f"matrix, got shape {K.shape}", block=self.name)
        self.set_param("K_T", K.T if self._matrix else K)

    def output(self, t, x, u):
        if self._matrix:
            return (np.matmul(u[0][:, None, :], self.p.K_T)[:, 0, :],)
        return (self.p.K_T.reshape((-1,) + (1,) * (u[0].ndim - 1)) * u[0],)

    def linear_form(self):
        """y = K u as a ``LinearForm``, so the engine can fuse it with other linear blocks."""
        K_T = self.p.K_T
        size = self.inputs["u"].size
        if self._matrix:
            D = np.swapaxes(K_T, -1, -2)
        elif size <= MAX_FUSED_SIZE:
            D = K_T.reshape(-1, 1, 1) * np.eye(size)
        else:
            return None
        out = self.outputs["y"].size
        return LinearForm(A=np.zeros((1, 0, 0)), B={}, C=[np.zeros((1, out, 0))],
                          D={(0, 0): D})


#: The largest number of inputs or outputs of one Sum, Mux or Demux.
MAX_PORTS = 1000


def _as_written(value) -> str:
    """A numeric list for messages: whole numbers without '.0' (YAML [2, 0], not [2.0, 0.0])."""
    return as_written(value)


def _shape_param(block: Block, key: str, value, ndims: tuple | None = None) -> tuple:
    """A shape parameter (list of positive whole numbers; [] or None: scalar) -> tuple."""
    arr = np.atleast_1d(np.asarray([] if value is None else value, dtype=float))
    if arr.ndim != 1 or np.any(arr < 1) or np.any(arr != np.floor(arr)):
        raise ParameterError(
            f"block '{block.name}' parameter '{key}' must be a list of positive whole numbers "
            f"such as [3] or [2, 3] ([] for a scalar), got {_as_written(value)}",
            block=block.name)
    shape = tuple(int(s) for s in arr)
    if ndims is not None and len(shape) not in ndims:
        kinds = {0: "a scalar []", 1: "a vector [n]", 2: "a matrix [n, m]"}
        allowed = " or ".join(kinds[d] for d in ndims)
        raise ParameterError(
            f"block '{block.name}' parameter '{key}' must be {allowed}, got {list(shape)}",
            block=block.name)
    return shape


def _sizes_param(block: Block, value) -> list[int]:
    sizes = np.atleast_1d(np.asarray(value, dtype=float))
    if sizes.ndim != 1 or sizes.size == 0 or np.any(sizes < 1) \
            or np.any(sizes != np.floor(sizes)):
        raise ParameterError(
            f"block '{block.name}' parameter 'sizes' must be a non-empty list of positive whole "
            f"numbers such as [2, 1], got {_as_written(value)}", block=block.name)
    block.require_size("number of parts", sizes.size, MAX_PORTS)
    return [int(s) for s in sizes]


@register
class Sum(Block):
    """Sum: signed sum of k inputs of one shape, one input per sign.

    Equation: y = s_1 u1 + s_2 u2 + ... + s_k uk, s_i = +1 or -1 from ``signs``
    (e.g. the tracking error e = q - q_d is ``signs: "+-"``).

    Ports (drawn for signs = "+-"; one input u_i per sign):
        | port | direction | shape | feedthrough |
        | u1   | in        | shape | -           |
        | u2   | in        | shape | -           |
        | y    | out       | shape | u1, u2      |

    Parameters:
        signs: string of '+' and '-', one character per input, e.g. "+-+".
        shape: shape of every input and of y (list; [] or omitted for a scalar).
    """

    params = {
        "signs": Param("str", doc="one '+' or '-' per input, e.g. \"+-\""),
        "shape": Param("array", default=None, doc="signal shape, e.g. [2]; default scalar"),
    }
    #: kept in ``p`` per variant, so a batch may mix different signs
    stacked_params = ("signs",)
    example = {"signs": "+-", "shape": [2]}

    def setup(self, signs, shape):
        if not signs or set(signs) - {"+", "-"}:
            raise ParameterError(
                f"block '{self.name}' parameter 'signs' must be a non-empty string of '+' and "
                f"'-' such as \"+-\", got {signs!r}", block=self.name)
        self.require_size("number of inputs", len(signs), MAX_PORTS)
        shape = _shape_param(self, "shape", shape)
        for j in range(len(signs)):
            self.declare_input(f"u{j + 1}", shape)
        self.declare_output("y", shape)
        self._expand = (-1,) + (1,) * len(shape)
        # kept in p (not only as text) so a batched sweep over 'signs' stays exact
        self.set_param("signs", [1.0 if c == "+" else -1.0 for c in signs])
        self.finalize(1)

    def finalize(self, batch: int) -> None:
        signs = self.p.signs
        if np.all(signs == signs[:1]):
            row = signs[0]
            self._columns = None
            self._first_negative = row[0] < 0
            self._plus = [j for j in range(1, row.size) if row[j] > 0]
            self._minus = [j for j in range(1, row.size) if row[j] < 0]
        else:  # variants with different signs: one multiply per input
            self._columns = [signs[:, j].reshape(self._expand) for j in range(signs.shape[1])]

    def output(self, t, x, u):
        if self._columns is not None:
            y = self._columns[0] * u[0]
            for j in range(1, len(u)):
                y = y + self._columns[j] * u[j]
            return (y,)
        y = -u[0] if self._first_negative else u[0]
        for j in self._plus:
            y = y + u[j]
        for j in self._minus:
            y = y - u[j]
        return (y,)

    def linear_form(self):
        """y = sum_j s_j u_j as a ``LinearForm``, so the engine can fuse it with other
        linear blocks."""
        size = self.outputs["y"].size
        if size > MAX_FUSED_SIZE:
            return None
        signs, eye = self.p.signs, np.eye(size)
        return LinearForm(A=np.zeros((1, 0, 0)), B={}, C=[np.zeros((1, size, 0))],
                          D={(0, j): signs[:, j, None, None] * eye
                             for j in range(signs.shape[1])})


@register
class Product(Block):
    """Product: matrix-matrix, matrix-vector or vector-vector product with optional transposes.

    Equation: y = op(a) op(b), op(M) = M or M^T (e.g. Y theta_hat, Y^T s, W W^T e).
    Vectors follow numpy.matmul: a vector a is a row, a vector b a column, a.b a scalar.

    Ports (drawn for a_shape = [n, p], b_shape = [p]):
        | port | direction | shape  | feedthrough |
        | a    | in        | (n, p) | -           |
        | b    | in        | (p,)   | -           |
        | y    | out       | (n,)   | a, b        |

    Parameters:
        a_shape: shape of a, [n] or [n, m].
        b_shape: shape of b, [n] or [n, m].
        transpose_a: use a^T (a must be a matrix; default false).
        transpose_b: use b^T (b must be a matrix; default false).
    """

    params = {
        "a_shape": Param("array", doc="shape of a: [n] or [n, m]"),
        "b_shape": Param("array", doc="shape of b: [n] or [n, m]"),
        "transpose_a": Param("bool", default=False, doc="multiply by a^T"),
        "transpose_b": Param("bool", default=False, doc="multiply by b^T"),
    }
    #: kept in ``p`` per variant, so a batch may mix transposes of square operands
    stacked_params = ("transpose_a", "transpose_b")
    example = {"a_shape": [3, 2], "b_shape": [2]}

    def setup(self, a_shape, b_shape, transpose_a, transpose_b):
        a_shape = _shape_param(self, "a_shape", a_shape, (1, 2))
        b_shape = _shape_param(self, "b_shape", b_shape, (1, 2))
        for key, shape, flag in (("a", a_shape, transpose_a), ("b", b_shape, transpose_b)):
            if flag and len(shape) != 2:
                raise ParameterError(
                    f"block '{self.name}' parameter 'transpose_{key}' needs a matrix {key}, "
                    f"but {key}_shape is {list(shape)}", block=self.name)
        op_a = a_shape[::-1] if transpose_a else a_shape
        op_b = b_shape[::-1] if transpose_b else b_shape
        inner_a, inner_b = op_a[-1], op_b[0]
        if inner_a != inner_b:
            ta = "^T" if transpose_a else ""
            tb = "^T" if transpose_b else ""
            raise ParameterError(
                f"block '{self.name}': cannot multiply a{ta} by b{tb}: a_shape {list(a_shape)} "
                f"gives op(a) of shape {list(op_a)}, b_shape {list(b_shape)} gives op(b) of "
                f"shape {list(op_b)}, and the inner sizes {inner_a} and {inner_b} differ",
                block=self.name)
        self.declare_input("a", a_shape)
        self.declare_input("b", b_shape)
        self.declare_output("y", op_a[:-1] + op_b[1:])
        self._kind = (len(a_shape), len(b_shape))
        # flags kept in p so a batched sweep over them (possible for square a, b) stays exact
        self.set_param("transpose_a", float(transpose_a))
        self.set_param("transpose_b", float(transpose_b))
        self.finalize(1)

    def finalize(self, batch: int) -> None:
        self._flags = []
        for flag in (self.p.transpose_a, self.p.transpose_b):
            if np.all(flag == flag[0]):
                self._flags.append(bool(flag[0]))
            else:  # per-variant choice: a (B, 1, 1) mask
                self._flags.append((flag != 0).reshape(-1, 1, 1))

    @staticmethod
    def _op(m, flag):
        if flag is True:
            return m.swapaxes(-1, -2)
        if flag is False:
            return m
        return np.where(flag, m.swapaxes(-1, -2), m)

    def output(self, t, x, u):
        a = self._op(u[0], self._flags[0])
        b = self._op(u[1], self._flags[1])
        kind = self._kind
        if kind == (2, 2):
            return (np.matmul(a, b),)
        if kind == (2, 1):
            return (np.matmul(a, b[:, :, None])[:, :, 0],)
        if kind == (1, 2):
            return (np.matmul(a[:, None, :], b)[:, 0, :],)
        return (np.matmul(a[:, None, :], b[:, :, None])[:, 0, 0],)


@register
class ScalarProduct(Block):
    """ScalarProduct: a signal of any shape times a time-varying scalar signal.

    Equation: y = k u (e.g. theta_hat_i times a filtered signal in Theorems 8 and 9).

    Ports:
        | port | direction | shape | feedthrough |
        | k    | in        | ()    | -           |
        | u    | in        | shape | -           |
        | y    | out       | shape | k, u        |

    Parameters:
        shape: shape of u and y (list; [] or omitted for a scalar).
    """

    params = {"shape": Param("array", default=None, doc="shape of u, e.g. [2] or [2, 5]")}
    example = {"shape": [2, 3]}

    def setup(self, shape):
        shape = _shape_param(self, "shape", shape)
        self.declare_input("k", ())
        self.declare_input("u", shape)
        self.declare_output("y", shape)
        self._expand = (-1,) + (1,) * len(shape)

    def output(self, t, x, u):
        return (u[0].reshape(self._expand) * u[1],)


@register
class Selector(Block):
    """Selector: picks elements of a vector, in the given order (repeats allowed).

    Equation: y_j = u_{indices_j} (indices count from 0).

    Ports (drawn for n = 3, two indices):
        | port | direction | shape | feedthrough |
        | u    | in        | (n,)  | -           |
        | y    | out       | (m,)  | u           |

    Parameters:
        n: size of the input vector u.
        indices: list of m indices in 0..n-1.
    """

    params = {
        "n": Param("int", doc="size of the input vector"),
        "indices": Param("array", doc="list of indices (from 0) to pick"),
    }
    example = {"n": 3, "indices": [2, 0]}

    def setup(self, n, indices):
        if n < 1:
            raise ParameterError(f"block '{self.name}' parameter 'n' must be at least 1, got {n}",
                                 block=self.name)
        idx = np.atleast_1d(np.asarray(indices, dtype=float))
        if idx.ndim != 1 or idx.size == 0 or np.any(idx != np.floor(idx)) \
                or np.any(idx < 0) or np.any(idx >= n):
            raise ParameterError(
                f"block '{self.name}' parameter 'indices' must be a non-empty list of whole "
                f"numbers from 0 to {n - 1}, got {_as_written(indices)}", block=self.name)
        self.require_size("number of indices", idx.size, n * MAX_PORTS)
        self.declare_input("u", (n,))
        self.declare_output("y", (idx.size,))
        self.set_param("indices", idx)
        self.finalize(1)

    def finalize(self, batch: int) -> None:
        idx = self.p.indices.astype(np.intp)
        if np.all(idx == idx[:1]):
            row = idx[0]
            step_one = row.size == 1 or np.all(np.diff(row) == 1)
            # contiguous ranges are basic slices (views, no copy)
            self._pick = slice(int(row[0]), int(row[-1]) + 1) if step_one else row
            self._per_variant = None
        else:  # variants pick different elements
            self._per_variant = idx

    def output(self, t, x, u):
        if self._per_variant is not None:
            return (np.take_along_axis(u[0], self._per_variant, axis=1),)
        return (u[0][:, self._pick],)


@register
class Mux(Block):
    """Mux: concatenates vectors into one vector.

    Equation: y = [u1; u2; ...; uk].

    Ports (drawn for sizes = [2, 1]; one input u_i per size):
        | port | direction | shape  | feedthrough |
        | u1   | in        | (2,)   | -           |
        | u2   | in        | (1,)   | -           |
        | y    | out       | (3,)   | u1, u2      |

    Parameters:
        sizes: list of the input vector sizes.
    """

    params = {"sizes": Param("array", doc="input vector sizes, e.g. [2, 1]")}
    example = {"sizes": [2, 1]}

    def setup(self, sizes):
        sizes = _sizes_param(self, sizes)
        for j, size in enumerate(sizes):
            self.declare_input(f"u{j + 1}", (size,))
        self.declare_output("y", (sum(sizes),))

    def output(self, t, x, u):
        batch = max(v.shape[0] for v in u)
        return (np.concatenate([v if v.shape[0] == batch else
                                np.broadcast_to(v, (batch,) + v.shape[1:]) for v in u], axis=1),)


@register
class Demux(Block):
    """Demux: splits a vector into consecutive parts.

    Equation: [y1; y2; ...; yk] = u.

    Ports (drawn for sizes = [2, 1]; one output y_i per size):
        | port | direction | shape | feedthrough |
        | u    | in        | (3,)  | -           |
        | y1   | out       | (2,)  | u           |
        | y2   | out       | (1,)  | u           |

    Parameters:
        sizes: list of the output vector sizes (their sum is the size of u).
    """

    params = {"sizes": Param("array", doc="output vector sizes, e.g. [2, 1]")}
    example = {"sizes": [2, 1]}

    def setup(self, sizes):
        sizes = _sizes_param(self, sizes)
        self.declare_input("u", (sum(sizes),))
        ends = np.cumsum(sizes)
        self._slices = [slice(int(e - s), int(e)) for s, e in zip(sizes, ends)]
        for j, size in enumerate(sizes):
            self.declare_output(f"y{j + 1}", (size,))

    def output(self, t, x, u):
        v = u[0]
        return tuple(v[:, s] for s in self._slices)
