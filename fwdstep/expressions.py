"""A whitelisted arithmetic evaluator for parameter expressions (never ``eval``).

Accepted: numbers, names of diagram parameters, ``pi`` and ``e``, ``+ - * / ** %`` and ``@``,
unary ``+``/``-``, list/tuple literals (-> arrays), and calls of the functions in
``FUNCTIONS`` with positional arguments.  Everything else (attribute access, subscripts,
keywords, lambdas, comprehensions, comparisons, strings, ...) is refused with a one-line
``ExpressionError``.  Integer literals are evaluated as floats, so ``10**10**10`` overflows
to a refusal at once instead of building a huge integer.
"""
from __future__ import annotations

import ast
import math
from typing import Any, Mapping

import numpy as np

from .errors import ExpressionError

MAX_EXPRESSION_LENGTH = 2000
MAX_ARRAY_SIZE = 1_000_000


def _size_arg(n) -> int:
    n = float(np.asarray(n))
    if n != math.floor(n) or n < 0:
        raise ValueError("size must be a non-negative whole number")
    if n > 10_000:
        raise ValueError(f"size {n:g} is too large (limit 10000)")
    return int(n)


def _binom(n, k):
    return float(math.comb(int(n), int(k)))


FUNCTIONS = {
    "sqrt": np.sqrt, "sin": np.sin, "cos": np.cos, "tan": np.tan,
    "asin": np.arcsin, "acos": np.arccos, "atan": np.arctan, "atan2": np.arctan2,
    "sinh": np.sinh, "cosh": np.cosh, "tanh": np.tanh,
    "exp": np.exp, "log": np.log, "log10": np.log10, "abs": np.abs,
    "floor": np.floor, "ceil": np.ceil, "round": np.round,
    "min": lambda *a: np.min(np.array(a, dtype=float)) if len(a) > 1 else np.min(a[0]),
    "max": lambda *a: np.max(np.array(a, dtype=float)) if len(a) > 1 else np.max(a[0]),
    "radians": np.radians, "degrees": np.degrees, "binom": _binom,
    "eye": lambda n: np.eye(_size_arg(n)),
    "zeros": lambda *s: np.zeros(tuple(_size_arg(v) for v in s)),
    "ones": lambda *s: np.ones(tuple(_size_arg(v) for v in s)),
    "diag": lambda v: np.diag(np.asarray(v, dtype=float)),
    "transpose": lambda a: np.transpose(np.asarray(a, dtype=float)),
    # polynomials as coefficient vectors, highest power first (numpy.polyval order)
    "concat": lambda *a: np.concatenate([np.atleast_1d(np.asarray(v, dtype=float)) for v in a]),
    "polymul": lambda a, b: np.polymul(np.atleast_1d(a), np.atleast_1d(b)),
    "polyadd": lambda a, b: np.polyadd(np.atleast_1d(a), np.atleast_1d(b)),
    "polypow": lambda a, n: _polypow(a, n),
}


def _polypow(a, n):
    n = _size_arg(n)
    if n > 200:
        raise ValueError(f"power {n} is too large (limit 200)")
    out = np.array([1.0])
    for _ in range(n):
        out = np.polymul(out, np.atleast_1d(np.asarray(a, dtype=float)))
    return out

CONSTANTS = {"pi": math.pi, "e": math.e}

_FORBIDDEN = {
    ast.Attribute: "attribute access", ast.Subscript: "subscripts", ast.Lambda: "lambdas",
    ast.ListComp: "comprehensions", ast.SetComp: "comprehensions",
    ast.DictComp: "comprehensions", ast.GeneratorExp: "comprehensions",
    ast.Compare: "comparisons", ast.BoolOp: "boolean operators", ast.IfExp: "conditionals",
    ast.Dict: "dictionaries", ast.Set: "sets", ast.Starred: "star arguments",
    ast.JoinedStr: "f-strings", ast.NamedExpr: "assignments", ast.Await: "await",
    ast.Yield: "yield", ast.YieldFrom: "yield", ast.Slice: "slices",
}
_BINOPS = {
    ast.Add: np.add, ast.Sub: np.subtract, ast.Mult: np.multiply, ast.Div: np.true_divide,
    ast.Pow: np.power, ast.Mod: np.mod, ast.MatMult: np.matmul,
}


def names_in(text: str) -> set[str]:
    """Names an expression refers to (for ordering parameters); empty on syntax errors."""
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return set()
    called = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and id(n) not in called}


def evaluate(text: str, namespace: Mapping[str, Any], what: str = "expression") -> Any:
    """Evaluate ``text`` with names from ``namespace``; raise ``ExpressionError``."""
    src = text.strip()
    if len(src) > MAX_EXPRESSION_LENGTH:
        raise ExpressionError(f"{what}: expression is {len(src)} characters long "
                              f"(limit {MAX_EXPRESSION_LENGTH})")
    try:
        tree = ast.parse(src, mode="eval")
    except (SyntaxError, ValueError) as exc:
        raise ExpressionError(f"{what}: cannot parse expression '{src}': "
                              f"{getattr(exc, 'msg', exc)}") from None
    except (RecursionError, MemoryError):
        raise ExpressionError(f"{what}: expression '{src[:60]}' is nested too deeply") from None
    try:
        value = _Evaluator(src, namespace, what).visit(tree.body)
    except RecursionError:
        raise ExpressionError(f"{what}: expression '{src[:60]}' is nested too deeply") from None
    return value


class _Evaluator:
    def __init__(self, src: str, namespace: Mapping[str, Any], what: str):
        self.src = src
        self.ns = namespace
        self.what = what

    def fail(self, msg: str) -> ExpressionError:
        return ExpressionError(f"{self.what}: expression '{self.src}' {msg}")

    def visit(self, node):
        for kind, label in _FORBIDDEN.items():
            if isinstance(node, kind):
                raise self.fail(f"uses a forbidden construct ({label})")
        method = getattr(self, "visit_" + type(node).__name__, None)
        if method is None:
            raise self.fail(f"uses a forbidden construct ({type(node).__name__})")
        return method(node)

    def visit_Constant(self, node):
        v = node.value
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(f"contains a literal {v!r} that is not a number")
        return float(v)

    def visit_Name(self, node):
        if node.id in self.ns:
            return self.ns[node.id]
        if node.id in CONSTANTS:
            return CONSTANTS[node.id]
        if node.id in FUNCTIONS:
            raise self.fail(f"uses the function '{node.id}' without calling it")
        known = ", ".join(sorted(self.ns)) or "(none)"
        raise self.fail(f"refers to undefined name '{node.id}'; defined names are: {known}")

    def visit_List(self, node):
        items = [self.visit(e) for e in node.elts]
        try:
            arr = np.array(items, dtype=float)
        except (ValueError, TypeError):
            raise self.fail("builds a list that is not a rectangular array of numbers") from None
        return arr

    visit_Tuple = visit_List

    def visit_UnaryOp(self, node):
        v = self.visit(node.operand)
        if isinstance(node.op, ast.USub):
            return self._check(np.negative(v))
        if isinstance(node.op, ast.UAdd):
            return v
        raise self.fail(f"uses a forbidden operator ({type(node.op).__name__})")

    def visit_BinOp(self, node):
        op = _BINOPS.get(type(node.op))
        if op is None:
            raise self.fail(f"uses a forbidden operator ({type(node.op).__name__})")
        a, b = self.visit(node.left), self.visit(node.right)
        try:
            with np.errstate(over="raise", invalid="raise", divide="raise"):
                res = op(np.asarray(a, dtype=float), np.asarray(b, dtype=float))
        except FloatingPointError as exc:
            raise self.fail(f"cannot be evaluated: {exc} (the result is too large or undefined)"
                            ) from None
        except (ValueError, TypeError) as exc:
            raise self.fail(f"cannot be evaluated: {exc}") from None
        return self._check(res)

    def visit_Call(self, node):
        if not isinstance(node.func, ast.Name):
            raise self.fail("calls something that is not a whitelisted function")
        name = node.func.id
        if name not in FUNCTIONS:
            raise self.fail(f"calls '{name}', which is not allowed; allowed functions are: "
                            f"{', '.join(sorted(FUNCTIONS))}")
        if node.keywords:
            raise self.fail("uses keyword arguments, which are not allowed")
        args = [self.visit(a) for a in node.args]
        try:
            with np.errstate(over="raise", invalid="raise", divide="raise"):
                res = FUNCTIONS[name](*args)
        except FloatingPointError as exc:
            raise self.fail(f"cannot be evaluated: {exc}") from None
        except (ValueError, TypeError, OverflowError) as exc:
            raise self.fail(f"cannot be evaluated: {name}(): {exc}") from None
        return self._check(np.asarray(res, dtype=float) if not isinstance(res, float) else res)

    def _check(self, value):
        arr = np.asarray(value)
        if arr.size > MAX_ARRAY_SIZE:
            raise self.fail(f"produces {arr.size} numbers (limit {MAX_ARRAY_SIZE})")
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise self.fail("is not finite")
        if arr.ndim == 0:
            return float(arr)
        return arr
