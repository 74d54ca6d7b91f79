"""Memoryless arithmetic blocks: gains, sums and products of signals."""
from __future__ import annotations

import numpy as np

from fwdstep.core import kernelops as ko
from fwdstep.core.block import Block, Param, as_written
from fwdstep.core.errors import ParameterError
from fwdstep.core.linear import LinearForm
from fwdstep.core.registry import register

from .rigid_body import _ldl_solve as ldl_solve

#: Largest signal a scalar Gain or a Sum describes as a dense LinearForm for fusion.
MAX_FUSED_SIZE = 2000


# ---------------------------------------------------------------- kernels (one definition)
def gain_scalar_output(t, x, u, K):
    """y = K u, K stored with u's rank (B, 1, ..., 1)."""
    return (K * u,)


def gain_matrix_output(t, x, u, K_T):
    """y = K u for a vector u: y[b] = u[b] @ K^T[b]."""
    return (ko.bvecmat(u, K_T),)


def sum_output(t, x, u, signs):
    """y = sum_j s_j u_j; signs stored (B, k, 1, ..., 1) so signs[:, j] has u_j's rank."""
    y = signs[:, 0] * u[0]
    for j in range(1, len(u)):
        y = y + signs[:, j] * u[j]
    return (y,)


def sum_signed_output(t, x, u, signs, minus):
    """``sum_output`` for signs shared by the batch, given as bits (bit j of ``minus`` set:
    s_j = -1): u_1 - u_2 instead of 1 u_1 + (-1) u_2, one operation per input instead of
    two, and the same numbers (1 u is u, a + (-1) b is a - b in IEEE arithmetic)."""
    if len(u) == 1:
        return (-u[0] if minus & 1 else u[0].copy(),)
    if minus & 1:
        y = -u[0]
        y = y - u[1] if minus & 2 else y + u[1]
    else:
        y = u[0] - u[1] if minus & 2 else u[0] + u[1]
    for j in range(2, len(u)):
        if (minus >> j) & 1:
            y = y - u[j]
        else:
            y = y + u[j]
    return (y,)


def solve_output(t, x, A, b, damping):
    """y = (A^T A + d 1)^-1 A^T b for m >= k (A^-1 b when A is square and d = 0), else
    y = A^T (A A^T + d 1)^-1 b, A (B, m, k), b (B, m), d = damping (B, 1): the normal
    equations by L D L^T without pivoting (the Gram matrix is positive definite: the same
    operations for every value, so the compiled backend traces it)."""
    m, k = A.shape[1], A.shape[2]
    a = [[A[:, i, j] for j in range(k)] for i in range(m)]
    v = [b[:, i] for i in range(m)]
    d = damping[:, 0]
    tall = m >= k
    size = k if tall else m
    gram = [[None] * size for _ in range(size)]
    for r in range(size):
        for c in range(r + 1):
            if tall:
                s = a[0][r] * a[0][c]
                for i in range(1, m):
                    s = s + a[i][r] * a[i][c]
            else:
                s = a[r][0] * a[c][0]
                for j in range(1, k):
                    s = s + a[r][j] * a[c][j]
            if r == c:
                s = s + d
            gram[r][c] = s
            gram[c][r] = s
    if tall:
        rhs = []
        for c in range(k):
            s = a[0][c] * v[0]
            for i in range(1, m):
                s = s + a[i][c] * v[i]
            rhs.append(s)
        y = ldl_solve(gram, rhs)
    else:
        z = ldl_solve(gram, v)
        y = []
        for c in range(k):
            s = a[0][c] * z[0]
            for i in range(1, m):
                s = s + a[i][c] * z[i]
            y.append(s)
    B = max(A.shape[0], b.shape[0], damping.shape[0])
    out = np.empty((B, k))
    for j in range(k):
        out[:, j] = y[j]
    return (out,)


def _transposed(m, flag):
    """op(m) per variant: m^T[b] where flag[b] != 0 (flag (B,) or (1,))."""
    if flag.shape[0] == 1:
        if flag[0] != 0.0:
            return np.ascontiguousarray(m.transpose((0, 2, 1)))
        return np.ascontiguousarray(m)              # a no-op for a contiguous signal
    plain = np.ascontiguousarray(m)
    swapped = np.ascontiguousarray(m.transpose((0, 2, 1)))
    out = np.empty((max(m.shape[0], flag.shape[0]),) + swapped.shape[1:])
    for b in range(out.shape[0]):
        out[b] = swapped[b if m.shape[0] > 1 else 0] if flag[b] != 0.0 else \
            plain[b if m.shape[0] > 1 else 0]
    return out


def product_mm_output(t, x, a, b, transpose_a, transpose_b):
    """y = op(a) op(b), both matrices."""
    return (ko.bmatmul(_transposed(a, transpose_a), _transposed(b, transpose_b)),)


def product_mv_output(t, x, a, b, transpose_a, transpose_b):
    """y = op(a) b, a matrix, b a vector."""
    return (ko.bmatvec(_transposed(a, transpose_a), b),)


def product_vm_output(t, x, a, b, transpose_a, transpose_b):
    """y = a op(b), a a vector (row), b a matrix."""
    return (ko.bvecmat(a, _transposed(b, transpose_b)),)


def product_vv_output(t, x, a, b, transpose_a, transpose_b):
    """y = a . b (a scalar per variant)."""
    return (np.sum(a * b, axis=1),)


def scalar_product_output(t, x, k, u):
    """y = k u, k one number per variant."""
    c = np.ascontiguousarray(u)
    flat = c.reshape((c.shape[0], c.size // c.shape[0]))
    y = flat * k[:, None]           # k may be a strided view (no reshape in numba)
    return (y.reshape((y.shape[0],) + c.shape[1:]),)


def selector_slice_output(t, x, u, start, stop):
    """y = u[start:stop] (contiguous indices)."""
    return (u[:, start:stop],)


def selector_take_output(t, x, u, indices):
    """y_j = u_{indices_j} (indices per variant)."""
    return (ko.take1(u, indices),)


def mux_output(t, x, u):
    """y = [u1; u2; ...; uk]."""
    n = 0
    B = 1
    for v in u:
        n += v.shape[1]
        B = max(B, v.shape[0])
    y = np.empty((B, n))
    c = 0
    for v in u:
        y[:, c:c + v.shape[1]] = v
        c += v.shape[1]
    return (y,)


def demux_output(t, x, u):
    """[y1; y2; ...] = u: packed, the outputs are consecutive parts of u."""
    return u


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
    shape_from = {"shape": ("u",)}
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
        if self._matrix:
            self.set_param("K_T", K.T)
            self.set_kernels(output=gain_matrix_output, params=("K_T",))
        else:       # stored with the rank of u, so the kernel multiplies by broadcasting
            self.set_param("K_T", K.reshape((1,) * len(in_shape)))
            self.set_kernels(output=gain_scalar_output, params=("K_T",))

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
    shape_from = {"shape": ("u1", "u2", "u3", "u4", "u5", "y")}
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
        # kept in p (not only as text) so a batched sweep over 'signs' stays exact; stored
        # (k, 1, ..., 1) so that signs[:, j] has the rank of the signals
        values = np.array([1.0 if c == "+" else -1.0 for c in signs])
        self.set_param("signs", values.reshape((len(signs),) + (1,) * len(shape)))
        self.set_kernels(output=sum_output, params=("signs",), tuple_inputs=True)

    def finalize(self, batch: int) -> None:
        """A batch whose variants share the signs (one row of ``p.signs``) runs
        ``sum_signed_output`` (the signs as bits: half the operations of a two-input sum,
        the same numbers); variants with their own signs keep ``sum_output``.  (The kernel
        is picked here, after stacking, so that variants with other signs still batch.)"""
        signs = self.p.signs
        if signs.shape[0] == 1:
            minus = sum(1 << j for j, v in enumerate(signs[0].reshape(-1)) if v < 0.0)
            self.set_kernels(output=sum_signed_output, params=("signs",), static=(minus,),
                             tuple_inputs=True)
        else:
            self.set_kernels(output=sum_output, params=("signs",), tuple_inputs=True)

    def linear_form(self):
        """y = sum_j s_j u_j as a ``LinearForm``, so the engine can fuse it with other
        linear blocks."""
        size = self.outputs["y"].size
        if size > MAX_FUSED_SIZE:
            return None
        signs, eye = self.p.signs.reshape(self.p.signs.shape[:2]), np.eye(size)
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
    shape_from = {"a_shape": ("a",), "b_shape": ("b",)}
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
        # flags kept in p so a batched sweep over them (possible for square a, b) stays exact
        self.set_param("transpose_a", float(transpose_a))
        self.set_param("transpose_b", float(transpose_b))
        kernel = {(2, 2): product_mm_output, (2, 1): product_mv_output,
                  (1, 2): product_vm_output, (1, 1): product_vv_output}
        self.set_kernels(output=kernel[(len(a_shape), len(b_shape))],
                         params=("transpose_a", "transpose_b"))


@register
class Solve(Block):
    """Solve: y = A^-1 b, or the least-squares / minimum-norm / damped solution of A y = b.

    Equation: y = (A^T A + d 1)^-1 A^T b for m >= k rows (A^-1 b for a square invertible A
    and d = 0; the least-squares solution for a tall A of full rank), y = A^T (A A^T +
    d 1)^-1 b for m < k (the minimum-norm solution for d = 0): the Moore-Penrose
    pseudo-inverse A^+ b for A of full rank, damped least squares (Levenberg-Marquardt) for
    d > 0 (e.g. joint accelerations from a task-space command through a Jacobian,
    qddot = J^+ (a - Jdot qdot)).  Computed from the normal equations by L D L^T (well
    conditioned A only: the condition number is squared).

    Ports (drawn for shape = [3, 2]):
        | port | direction | shape  | feedthrough |
        | A    | in        | (m, k) | -           |
        | b    | in        | (m,)   | -           |
        | y    | out       | (k,)   | A, b        |

    Parameters:
        shape: the shape of A, [m, k] (default: from the wiring).
        damping: d >= 0 (default 0).
    """

    params = {
        "shape": Param("array", default=None, doc="shape of A: [m, k]"),
        "damping": Param("float", default=0.0, doc="d >= 0: damped least squares"),
    }
    shape_from = {"shape": ("A",)}
    example = {"shape": [3, 2]}
    #: the kernel unrolls the normal equations over Python lists: the compiled backend traces
    #: it into scalar code (fwdstep.compiled.scalarize); a stage that does not trace calls
    #: ``output`` (LAPACK) in object mode
    compile_with = "traced"

    def setup(self, shape, damping):
        shape = _shape_param(self, "shape", shape, (2,))
        if not damping >= 0.0:
            raise ParameterError(f"block '{self.name}' parameter 'damping' must be >= 0, got "
                                 f"{damping}", block=self.name)
        self.declare_input("A", shape)
        self.declare_input("b", shape[:1])
        self.declare_output("y", shape[1:])
        self.set_param("damping", [damping])
        self.set_kernels(output=solve_output, params=("damping",))

    def output(self, t, x, u):
        """The NumPy path: the same normal equations, formed by matmul and solved by LAPACK
        (numpy.linalg.solve) for every variant at once; the kernel (what compiled runs
        trace) costs ~0.6 ms per call in NumPy operations on (B,) columns.  Equal to ~1e-15
        relative for a well-conditioned A (tests/blocks/test_solve.py)."""
        A, b = u
        d = self.p.damping[:, 0, None, None]
        m, k = A.shape[1], A.shape[2]
        eye = np.eye(min(m, k))
        if m >= k:
            At = A.transpose(0, 2, 1)
            y = np.linalg.solve(At @ A + d * eye, (At @ b[:, :, None]))[:, :, 0]
        else:
            z = np.linalg.solve(A @ A.transpose(0, 2, 1) + d * eye, b[:, :, None])
            y = (A.transpose(0, 2, 1) @ z)[:, :, 0]
        return (y,)


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
    shape_from = {"shape": ("u", "y")}
    example = {"shape": [2, 3]}

    def setup(self, shape):
        shape = _shape_param(self, "shape", shape)
        self.declare_input("k", ())
        self.declare_input("u", shape)
        self.declare_output("y", shape)
        self.set_kernels(output=scalar_product_output)


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
        idx = self.p.indices
        row = idx[0]
        if np.all(idx == idx[:1]) and (row.size == 1 or np.all(np.diff(row) == 1)):
            # the same contiguous range in every variant: a basic slice (a view, no copy)
            self.set_kernels(output=selector_slice_output,
                             static=(int(row[0]), int(row[-1]) + 1))
        else:
            self.set_kernels(output=selector_take_output, params=("indices",))


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
        self.set_kernels(output=mux_output, tuple_inputs=True)


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
        self.set_kernels(output=demux_output, packed=True)
