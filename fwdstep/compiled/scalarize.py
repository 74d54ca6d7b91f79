"""Block kernels traced into scalar expressions, for the compiled backend's scalar code.

The compiled loop (``fwdstep.compiled.backend_numba``) calls each block's kernels, which return new
arrays: a Slotine-Li stage allocates a dozen small arrays and crosses a dozen call
boundaries, 25x the time of the same equations written as scalar code.  This module derives
that scalar code from the kernels themselves, so a block's equations still live in one place
(``Block.set_kernels``): each kernel is *run once* on arrays of symbols (``Sym``, an object
array with the signal's shape) instead of numbers, with ``np`` and ``math`` in its globals
replaced by shims that build expressions, and the kernels of ``fwdstep.core.kernelops`` replaced by
their loop twins of ``fwdstep.compiled.compiled_ops`` (run as plain Python).  What comes out is the
expression graph of every output and derivative entry, one node per arithmetic operation,
common subexpressions shared (hash-consing).  ``fwdstep.compiled.llvm_stage`` compiles it, one LLVM
instruction per node, to straight-line code with no array and no call (``Trace.expr``
writes a node as Python text, to read it).

A kernel whose control flow depends on a value (a comparison used as a flag, a pivoted
solve, ``float()`` of a symbol the shims do not cover, an unknown NumPy function) cannot be
traced: ``Untraceable`` is raised and the backend keeps the array code for the whole
diagram.  ``np.where`` and comparisons are traced as selections.

Arithmetic keeps the kernel's order of operations (IEEE results equal to the kernel's on
numbers), with these folds: a + 0, 0 + a, a - 0, a * 1, 1 * a, a / 1 (exact), and 0 * a, a * 0
to 0 (exact unless a is infinite or NaN: only for a diverging run, which the bound test
stops either way); operations on two constants are evaluated."""
from __future__ import annotations

import math
import operator
import types

import numpy as np


class Untraceable(Exception):
    """A kernel the tracer cannot turn into expressions (the message says why)."""


# ------------------------------------------------------------------------ expression nodes
class Sym:
    """One scalar of a traced kernel: a node of ``trace``'s graph.  ``op``: "const" (value
    in ``value``), "leaf" (name in ``value``) or an operation on ``args``."""

    __slots__ = ("trace", "op", "args", "value", "n", "invariant", "values")

    def __init__(self, trace, op, args, value, invariant):
        self.trace, self.op, self.args, self.value = trace, op, args, value
        self.invariant = invariant
        self.values = None          # a parameter leaf: its value in each variant
        self.n = len(trace.nodes)

    # arithmetic ----------------------------------------------------------------------
    def __add__(self, o):
        return self.trace.binary("+", self, o)

    def __radd__(self, o):
        return self.trace.binary("+", o, self)

    def __sub__(self, o):
        return self.trace.binary("-", self, o)

    def __rsub__(self, o):
        return self.trace.binary("-", o, self)

    def __mul__(self, o):
        return self.trace.binary("*", self, o)

    def __rmul__(self, o):
        return self.trace.binary("*", o, self)

    def __truediv__(self, o):
        return self.trace.binary("/", self, o)

    def __rtruediv__(self, o):
        return self.trace.binary("/", o, self)

    def __pow__(self, o):
        if isinstance(o, (int, float, np.integer, np.floating)) and float(o) == 2.0:
            return self.trace.binary("*", self, self)
        return self.trace.binary("**", self, o)

    def __rpow__(self, o):
        return self.trace.binary("**", o, self)

    def __neg__(self):
        return self.trace.unary("-", self)

    def __pos__(self):
        return self

    def __abs__(self):
        return self.trace.unary("abs", self)

    # comparisons (used by np.where / selections only) ----------------------------------
    def __lt__(self, o):
        return self.trace.binary("<", self, o)

    def __le__(self, o):
        return self.trace.binary("<=", self, o)

    def __gt__(self, o):
        return self.trace.binary(">", self, o)

    def __ge__(self, o):
        return self.trace.binary(">=", self, o)

    def __eq__(self, o):
        return self.trace.binary("==", self, o)

    def __ne__(self, o):
        return self.trace.binary("!=", self, o)

    __hash__ = object.__hash__

    # logic on comparisons (np.where's conditions: (k >= 0) & (t < rise + w)) ------------
    def __and__(self, o):
        return self.trace.logic("&", self, o)

    __rand__ = __and__

    def __or__(self, o):
        return self.trace.logic("|", self, o)

    __ror__ = __or__

    def __invert__(self):
        return self.trace.logic("!", self, True)

    def __bool__(self):
        return bool(self.trace.fixed(self, "a branch"))

    def __float__(self):
        return float(self.trace.fixed(self, "float()"))

    def __int__(self):
        v = float(self.trace.fixed(self, "int()"))
        if not v.is_integer():
            raise Untraceable("int() of a value that is not an integer")
        return int(v)

    __index__ = __int__

    # what NumPy's ufuncs call on an object array ----------------------------------------
    def sin(self):
        return self.trace.unary("sin", self)

    def cos(self):
        return self.trace.unary("cos", self)

    def tan(self):
        return self.trace.unary("tan", self)

    def exp(self):
        return self.trace.unary("exp", self)

    def log(self):
        return self.trace.unary("log", self)

    def sqrt(self):
        return self.trace.unary("sqrt", self)

    def tanh(self):
        return self.trace.unary("tanh", self)

    def sinh(self):
        return self.trace.unary("sinh", self)

    def cosh(self):
        return self.trace.unary("cosh", self)

    def arctan(self):
        return self.trace.unary("atan", self)

    def arcsin(self):
        return self.trace.unary("asin", self)

    def arccos(self):
        return self.trace.unary("acos", self)

    def arctan2(self, o):
        return self.trace.binary("atan2", self, o)

    def absolute(self):
        return self.trace.unary("abs", self)

    def floor(self):
        return self.trace.unary("floor", self)

    __floor__ = floor

    def sign(self):
        """NumPy's sign: 1, -1, 0 for +-0, NaN for NaN."""
        t = self.trace
        return t.select(t.binary(">", self, 0.0), 1.0, t.select(
            t.binary("<", self, 0.0), -1.0, t.select(t.binary("==", self, self), 0.0, self)))

    def square(self):
        return self.trace.binary("*", self, self)

    def conjugate(self):
        return self

    def __repr__(self):
        return f"Sym({self.trace.expr(self)})"


_EVAL = {"+": operator.add, "-": operator.sub, "*": operator.mul}
_UNARY = {"sin": "math.sin", "cos": "math.cos", "tan": "math.tan", "exp": "math.exp",
          "log": "math.log", "sqrt": "math.sqrt", "tanh": "math.tanh", "sinh": "math.sinh",
          "cosh": "math.cosh", "atan": "math.atan", "asin": "math.asin", "acos": "math.acos",
          "abs": "abs", "floor": "math.floor"}
_BINARY = {"+", "-", "*", "/", "**", "<", "<=", ">", ">=", "==", "!="}
#: nodes whose value is a condition (LLVM i1)
_CONDITIONS = {"<", "<=", ">", ">=", "==", "!=", "&", "|", "!"}
_NUMPY_BINARY = {"+": np.add, "-": np.subtract, "*": np.multiply, "/": np.divide,
                 "**": np.power, "<": np.less, "<=": np.less_equal, ">": np.greater,
                 ">=": np.greater_equal, "==": np.equal, "!=": np.not_equal,
                 "atan2": np.arctan2}
_NUMPY_UNARY = {"sin": np.sin, "cos": np.cos, "tan": np.tan, "exp": np.exp, "log": np.log,
                "sqrt": np.sqrt, "tanh": np.tanh, "sinh": np.sinh, "cosh": np.cosh,
                "atan": np.arctan, "asin": np.arcsin, "acos": np.arccos, "abs": np.abs,
                "floor": np.floor}
_NUMPY_LOGIC = {"&": np.logical_and, "|": np.logical_or}


class Trace:
    """The expression graph of one compiled stage: nodes in creation order (a topological
    order), each operation on the same arguments created once."""

    def __init__(self, max_nodes: int = 20000):
        self.nodes: list = []
        self._interned: dict = {}
        self._values: dict = {}
        self.max_nodes = max_nodes
        #: (node, value) of every number a kernel needed from parameters (``fixed``): the
        #: code is written for these; a stage reused with other parameter values checks
        #: them (``decisions_hold``)
        self.decisions: list = []

    def _node(self, op, args, value, invariant) -> Sym:
        key = (op, tuple(a.n for a in args), value)
        got = self._interned.get(key)
        if got is not None:
            return got
        if len(self.nodes) >= self.max_nodes:
            raise Untraceable(f"more than {self.max_nodes} scalar operations")
        node = Sym(self, op, args, value, invariant)
        self.nodes.append(node)
        self._interned[key] = node
        return node

    def const(self, value) -> Sym:
        v = float(value)
        # -0.0 and 0.0 are one key of a dict of floats: keep their signs apart
        return self._node("const", (), (v, math.copysign(1.0, v)) if v == 0.0 else v, True)

    def leaf(self, name: str, invariant: bool, values=None) -> Sym:
        """A named input of the code; ``values``: a parameter's value in each variant."""
        node = self._node("leaf", (), name, invariant)
        if values is not None:
            node.values = np.asarray(values, dtype=float).reshape(-1)
        return node

    def lift(self, v) -> Sym:
        if isinstance(v, Sym):
            if v.trace is not self:
                raise Untraceable("a value of another trace")
            return v
        if isinstance(v, (bool, np.bool_)):
            return self.const(float(v))
        if isinstance(v, (int, float, np.integer, np.floating)):
            return self.const(v)
        raise Untraceable(f"a value of type {type(v).__name__}")

    def fixed(self, s: Sym, what: str):
        """The number of s where the kernel needs one (a branch, float(), int()): s must
        depend on parameters only, with one value over the variants; the code is then
        written for that value (the generated text differs with the branch taken, so
        another value compiles another program)."""
        if s.op == "const":
            return self.value(s)
        if not s.invariant:
            raise Untraceable(f"{what} depends on a signal or the state")
        vals = np.asarray(self.evaluate(s)).reshape(-1)
        if vals.size == 0 or not np.all(vals == vals[0]):
            raise Untraceable(f"{what} depends on a parameter that differs between variants")
        self.decisions.append((s, vals[0].item()))
        return vals[0].item()

    def decisions_hold(self, leaves: dict) -> bool:
        """Whether every number the code was written for (``decisions``) is the same with
        the parameter leaves ``leaves`` ({node number: values}) instead of their traced
        values (the other leaves as traced)."""
        memo = dict(leaves)
        for s, value in self.decisions:
            vals = np.asarray(self.evaluate(s, memo)).reshape(-1)
            if vals.size == 0 or not np.all(vals == value):
                return False
        return True

    def evaluate(self, s: Sym, memo: dict | None = None):
        """The values of a parameter-only node over the variants (NumPy); ``memo``: values
        already known by node number (default: this trace's own)."""
        if memo is None:
            memo = self._values
        if s.n in memo:
            return memo[s.n]
        if s.op == "const":
            out = np.array([self.value(s)])
        elif s.op == "leaf":
            if s.values is None:
                raise Untraceable(f"{s.value} has no value at trace time")
            out = s.values
        else:
            a = [self.evaluate(x, memo) for x in s.args]
            with np.errstate(all="ignore"):
                if s.op == "?":
                    out = np.where(a[0], a[1], a[2])
                elif s.op == "!":
                    out = np.logical_not(a[0])
                elif s.op in _NUMPY_LOGIC:
                    out = _NUMPY_LOGIC[s.op](a[0], a[1])
                elif s.op == "-" and len(a) == 1:
                    out = -a[0]
                elif s.op in _NUMPY_BINARY:
                    out = _NUMPY_BINARY[s.op](a[0], a[1])
                else:
                    out = _NUMPY_UNARY[s.op](a[0])
        memo[s.n] = out
        return out

    @staticmethod
    def value(s: Sym):
        """The number of a constant node, else None."""
        if s.op != "const":
            return None
        return s.value[0] if isinstance(s.value, tuple) else s.value

    def binary(self, op, a, b):
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            return NotImplemented
        a, b = self.lift(a), self.lift(b)
        va, vb = self.value(a), self.value(b)
        if va is not None and vb is not None and op in _EVAL:
            return self.const(_EVAL[op](va, vb))
        if op == "/" and va is not None and vb is not None and vb != 0.0:
            return self.const(va / vb)
        if op == "+":
            if vb == 0.0:
                return a
            if va == 0.0:
                return b
            if b.op == "-" and len(b.args) == 1:            # a + (-c) = a - c exactly
                return self.binary("-", a, b.args[0])
        elif op == "-":
            if vb == 0.0:
                return a
            if b.op == "-" and len(b.args) == 1:            # a - (-c) = a + c exactly
                return self.binary("+", a, b.args[0])
        elif op == "*":
            if va == 0.0 or vb == 0.0:
                return self.const(0.0)
            if vb == 1.0:
                return a
            if va == 1.0:
                return b
            if vb == -1.0:                                  # a * -1 = -a exactly
                return self.unary("-", a)
            if va == -1.0:
                return self.unary("-", b)
        elif op == "/" and vb == 1.0:
            return a
        return self._node(op, (a, b), None, a.invariant and b.invariant)

    def unary(self, op, a):
        a = self.lift(a)
        if op == "-" and a.op == "const":
            return self.const(-self.value(a))
        if op == "-" and a.op == "-" and len(a.args) == 1:
            return a.args[0]
        return self._node(op, (a,), None, a.invariant)

    def logic(self, op, a, b):
        """a and b, a or b, not a ("!", b ignored) of conditions (comparisons or flags)."""
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            return NotImplemented
        a, b = self.lift(a), self.lift(b)
        va, vb = self.value(a), self.value(b)
        if op == "!":
            return self.const(float(not va)) if va is not None else \
                self._node("!", (a,), None, a.invariant)
        if va is not None and vb is not None:
            return self.const(float(bool(va) and bool(vb) if op == "&"
                                    else bool(va) or bool(vb)))
        for c, other in ((va, b), (vb, a)):
            if c is not None:
                if (op == "&") == bool(c):       # True & x, False | x: x
                    return self.logic("|", other, False) if other.op not in _CONDITIONS \
                        else other
                return self.const(float(op == "|"))
        return self._node(op, (a, b), None, a.invariant and b.invariant)

    def select(self, c, a, b):
        c, a, b = self.lift(c), self.lift(a), self.lift(b)
        if c.op == "const":
            return a if self.value(c) else b
        return self._node("?", (c, a, b), None, c.invariant and a.invariant and b.invariant)

    # ------------------------------------------------------------------ reading the graph
    @staticmethod
    def _literal(v: float) -> str:
        if math.isnan(v):
            return "math.nan"
        if math.isinf(v):
            return "math.inf" if v > 0 else "(-math.inf)"
        return repr(v) if v >= 0 else f"({v!r})"

    def name(self, s: Sym) -> str:
        """How the code refers to node s."""
        if s.op == "const":
            return self._literal(self.value(s))
        if s.op == "leaf":
            return s.value
        return f"e{s.n}"

    def expr(self, s: Sym) -> str:
        """The right-hand side computing node s from its arguments' names."""
        if s.op in ("const", "leaf"):
            return self.name(s)
        a = [self.name(x) for x in s.args]
        if s.op == "?":
            return f"({a[1]} if {a[0]} else {a[2]})"
        if s.op == "!":
            return f"(not {a[0]})"
        if s.op in ("&", "|"):
            return f"({a[0]} {'and' if s.op == '&' else 'or'} {a[1]})"
        if s.op == "atan2":
            return f"math.atan2({a[0]}, {a[1]})"
        if s.op == "-" and len(a) == 1:
            return f"-{a[0]}"
        if s.op in _BINARY:
            return f"{a[0]} {s.op} {a[1]}"
        return f"{_UNARY[s.op]}({a[0]})"

    def needed(self, roots) -> set:
        """The operation nodes the roots depend on (themselves included)."""
        seen, todo = set(), [r for r in roots if isinstance(r, Sym)]
        while todo:
            s = todo.pop()
            if s.n in seen or s.op in ("const", "leaf"):
                continue
            seen.add(s.n)
            todo.extend(s.args)
        return seen


#: traces with more parameter entries than this are refused (their code would be long to
#: compile)
MAX_SCALAR_PARAMS = 4096


class ParameterColumns:
    """Parameters as leaves of the trace ``self.tr``: every entry a column of a matrix W
    (one row per variant, ``self.columns``), loaded into a leaf, constants where the values
    allow (the compiled stage, ``fwdstep.compiled.backend_numba._ScalarStage``, and the NumPy
    path's native block kernels, ``fwdstep.compiled.native_block``)."""

    max_columns = MAX_SCALAR_PARAMS

    def _leaf(self, values):
        """A parameter entry with these values over the variants: a column of W, loaded
        into a leaf.  The code is written for the pattern of the values (as it is for the
        zeros of a fused M): an entry that is 0, 1 or -1 in every variant is that constant
        (so 0 * a and 1 * a fold away), and entries equal to each other in every variant
        are one leaf (a Sine's frequency repeated for each derivative is one sin).  Another
        pattern writes other code, hence another cached stage."""
        values = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        first = float(values[0])
        if first in (0.0, 1.0, -1.0) and np.all(values == first):
            return self.tr.const(first)
        key = values.tobytes()
        if key in self._by_values and not np.isnan(values).any():
            return self._by_values[key]
        if len(self.columns) >= self.max_columns:
            raise Untraceable(f"more than {self.max_columns} parameter entries")
        j = len(self.columns)
        self.columns.append(values)
        node = self._by_values[key] = self.tr.leaf(f"p{j}", True, values)
        return node

    def _param(self, arr):
        """A parameter (or constant signal) array (Bp, *shape) as an object array
        (1, *shape) of leaves."""
        arr = np.asarray(arr, dtype=np.float64)
        out = np.empty((1,) + arr.shape[1:], dtype=object)
        for idx in np.ndindex(*arr.shape[1:]):
            out[(0,) + idx] = self._leaf(arr[(slice(None),) + idx])
        return out

    def column_matrix(self) -> np.ndarray:
        """W (variants, columns): column j the values of leaf p{j} (one row when they are
        shared by every variant)."""
        W = np.empty((max([len(c) for c in self.columns] + [1]), len(self.columns)))
        for j, c in enumerate(self.columns):
            W[:, j] = c
        return W


# ---------------------------------------------------------------------- symbolic arrays
def _compare(op):
    def f(a, b):
        for s in (a, b):
            if isinstance(s, Sym):
                return s.trace.binary(op, a, b)
        return _PY_COMPARE[op](a, b)
    return np.frompyfunc(f, 2, 1)


_PY_COMPARE = {"<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge,
               "==": operator.eq, "!=": operator.ne}


class SymArray(np.ndarray):
    """An object array of symbols whose comparisons give symbols (NumPy's comparisons of
    object arrays convert each result to bool, which would refuse every np.where)."""

    def __lt__(self, o):
        return _compare("<")(self, o)

    def __le__(self, o):
        return _compare("<=")(self, o)

    def __gt__(self, o):
        return _compare(">")(self, o)

    def __ge__(self, o):
        return _compare(">=")(self, o)

    def __eq__(self, o):
        return _compare("==")(self, o)

    def __ne__(self, o):
        return _compare("!=")(self, o)

    __hash__ = None


def symbolic(a) -> np.ndarray:
    """``a`` as a SymArray (object dtype)."""
    return np.asarray(a, dtype=object).view(SymArray)


def sym_array(trace: Trace, shape: tuple, name) -> np.ndarray:
    """An object array of leaves; ``name(index)`` gives each leaf's name and invariance."""
    a = np.empty(shape, dtype=object)
    for idx in np.ndindex(*shape):
        nm, inv = name(idx)
        a[idx] = trace.leaf(nm, inv)
    return a.view(SymArray)


def as_nodes(trace: Trace, value, shape: tuple) -> np.ndarray:
    """A kernel's result (array, number, or nested) as an object array of nodes of
    ``shape`` (broadcast when the kernel returned a shared row)."""
    a = np.asarray(value, dtype=object) if not isinstance(value, np.ndarray) else value
    if a.dtype != object:
        a = a.astype(object)
    try:
        a = np.broadcast_to(a, shape)
    except ValueError:
        raise Untraceable(f"a result of shape {a.shape} where {shape} was declared") from None
    out = np.empty(shape, dtype=object)
    for idx in np.ndindex(*shape):
        out[idx] = trace.lift(a[idx])
    return out


# ---------------------------------------------------------------------- shims of np, math
def _obj(a):
    return symbolic(a)


class _NumpyShim(types.SimpleNamespace):
    """``np`` for a traced kernel: allocations hold objects; anything not listed here is
    NumPy's own function (fine on object arrays for shape work and sums; a numeric routine
    that needs floats fails and makes the kernel untraceable)."""

    def __init__(self, trace: Trace):
        super().__init__()
        t = trace

        def filled(shape, value):
            a = np.empty(shape, dtype=object)
            a.fill(t.const(value))
            return a.view(SymArray)

        self.empty = lambda shape, dtype=float: filled(shape, 0.0)
        self.zeros = lambda shape, dtype=float: filled(shape, 0.0)
        self.ones = lambda shape, dtype=float: filled(shape, 1.0)
        self.full = lambda shape, value, dtype=float: filled(shape, value)
        self.empty_like = lambda a, dtype=None: filled(np.shape(a), 0.0)
        self.zeros_like = lambda a, dtype=None: filled(np.shape(a), 0.0)
        self.ones_like = lambda a, dtype=None: filled(np.shape(a), 1.0)
        self.array = lambda a, dtype=None, copy=True: np.array(a, dtype=object).view(SymArray)
        self.asarray = lambda a, dtype=None: _obj(a)
        self.ascontiguousarray = lambda a, dtype=None: np.ascontiguousarray(_obj(a)).view(
            SymArray)
        self.float64 = lambda v: v if isinstance(v, (Sym, np.ndarray)) else np.float64(v)
        sel = np.frompyfunc(t.select, 3, 1)
        self.where = lambda c, a, b: sel(c, a, b)
        self.minimum = np.frompyfunc(lambda a, b: t.select(t.binary("<", b, a), b, a), 2, 1)
        self.maximum = np.frompyfunc(lambda a, b: t.select(t.binary(">", b, a), b, a), 2, 1)
        self.clip = lambda a, lo, hi: self.minimum(self.maximum(a, lo), hi)
        # (NumPy's own loops for object arrays compare with bool() or call math.floor)
        self.floor = np.frompyfunc(lambda v: t.unary("floor", v), 1, 1)
        self.sign = np.frompyfunc(lambda v: t.lift(v).sign(), 1, 1)
        for bad in ("isfinite", "isnan", "isinf", "ceil", "round", "mod",
                    "remainder", "fmod", "linalg", "einsum", "searchsorted", "interp",
                    "random", "argmax", "argmin", "sort", "argsort", "nonzero"):
            setattr(self, bad, _refuse(f"np.{bad}"))

    def __getattr__(self, name):
        return getattr(np, name)


def _refuse(what):
    def f(*args, **kwargs):
        raise Untraceable(f"{what} is not traced")
    return f


def _math_shim(trace: Trace):
    m = types.SimpleNamespace(**{k: getattr(math, k) for k in dir(math)
                                 if not k.startswith("_")})
    for name, op in (("sin", "sin"), ("cos", "cos"), ("tan", "tan"), ("exp", "exp"),
                     ("log", "log"), ("sqrt", "sqrt"), ("tanh", "tanh"), ("sinh", "sinh"),
                     ("cosh", "cosh"), ("atan", "atan"), ("asin", "asin"), ("acos", "acos"),
                     ("fabs", "abs"), ("floor", "floor")):
        setattr(m, name, (lambda op: lambda v: trace.unary(op, v))(op))
    m.atan2 = lambda a, b: trace.binary("atan2", a, b)
    m.pow = lambda a, b: trace.binary("**", a, b)
    for bad in ("isfinite", "isnan", "isinf", "ceil", "fmod", "copysign"):
        setattr(m, bad, _refuse(f"math.{bad}"))
    return m


def _float(v):
    return v if isinstance(v, Sym) else float(v)


class Rebinder:
    """Copies of kernel functions whose globals see the shims (recursively: the helpers a
    kernel calls are copied the same way; ``fwdstep.core.kernelops`` is replaced by the loops of
    ``fwdstep.compiled.compiled_ops``, the functions numba compiles in its place)."""

    def __init__(self, trace: Trace):
        self.np = _NumpyShim(trace)
        self.math = _math_shim(trace)
        self.done: dict = {}
        from fwdstep.core import kernelops
        self.kernelops = kernelops
        self._ops = None

    def ops(self):
        if self._ops is None:
            # (imported here: with numba installed it imports numba, which kernels that
            # call no kernelops function, such as the rigid-body ones, never need)
            from fwdstep.compiled import compiled_ops
            self.ops_module = compiled_ops
            self._ops = types.SimpleNamespace(**{
                name: self.function(getattr(self.ops_module, name))
                for name in dir(self.kernelops)
                if callable(getattr(self.ops_module, name, None))
                and not name.startswith("_")})
        return self._ops

    def value(self, v):
        if v is np:
            return self.np
        if v is math:
            return self.math
        if v is self.kernelops:
            return self.ops()
        if isinstance(v, types.FunctionType):
            if getattr(v, "__module__", None) == self.kernelops.__name__:
                return getattr(self.ops(), v.__name__)
            return self.function(v)
        if hasattr(v, "py_func") and isinstance(v.py_func, types.FunctionType):
            return self.function(v.py_func)                 # a numba dispatcher
        return v

    def function(self, fn):
        if hasattr(fn, "py_func"):
            fn = fn.py_func
        got = self.done.get(fn)
        if got is not None:
            return got
        g = dict(fn.__globals__)
        new = types.FunctionType(fn.__code__, g, fn.__name__, fn.__defaults__,
                                 fn.__closure__)
        self.done[fn] = new
        for name in global_names(fn.__code__):
            if name in g:
                g[name] = self.value(g[name])
        g["float"] = _float
        return new


def run_traced(rebinder: Rebinder, fn, *args):
    """Kernel ``fn`` run on symbolic arguments: its result, or ``Untraceable``."""
    args = [symbolic(a) if isinstance(a, np.ndarray) else
            tuple(symbolic(b) for b in a) if isinstance(a, tuple) else a for a in args]
    try:
        with np.errstate(all="ignore"):
            return rebinder.function(fn)(*args)
    except (Untraceable, KeyboardInterrupt):
        raise
    except BaseException as exc:  # noqa: BLE001 - tracing is a try: whatever the kernel
        # raises on symbols (an operation the tracer lacks, or the kernel's own error, even
        # a SystemExit) leaves it to the array code, whose run names the block if it fails
        raise Untraceable(f"{type(exc).__name__}: {exc}") from None


def global_names(code) -> set:
    """The global names a function's code (and its nested functions') reads: the names
    jit_kernel rebinds and the tracer replaces."""
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= global_names(const)
    return names
