"""A whitelisted arithmetic evaluator for parameter expressions (never ``eval``).

Accepted: numbers, names of diagram parameters, ``pi`` and ``e``, ``+ - * / ** %`` and ``@``,
unary ``+``/``-``, list/tuple literals (-> arrays), indexing and slicing with whole numbers
(``v[0]``, ``v[-1]``, ``A[1, :]``, ``v[1:3]``, ``A[:, ::2]``), and calls of the functions in
``FUNCTIONS`` with positional arguments.  Everything else (attribute access, keywords,
lambdas, comprehensions, comparisons, strings, ...) is refused with a one-line
``ExpressionError``.  Integer literals are evaluated as floats, so ``10**10**10`` overflows
to a refusal at once instead of building a huge integer.
"""
from __future__ import annotations

import ast
import difflib
import functools
import math
from typing import Any, Mapping

import numpy as np

from fwdstep.core.errors import ExpressionError

MAX_EXPRESSION_LENGTH = 2000
MAX_ARRAY_SIZE = 1_000_000


MAX_WORK = 100_000_000          # multiply-adds one operation may cost (matmul, polymul)


def _size_arg(n) -> int:
    n = float(np.asarray(n))
    if n != math.floor(n) or n < 0:
        raise ValueError("size must be a non-negative whole number")
    if n > 10_000:
        raise ValueError(f"size {n:g} is too large (limit 10000)")
    return int(n)


def _numbers(count: int, what: str) -> None:
    """Refuse, before allocating, a result of more than MAX_ARRAY_SIZE numbers."""
    if count > MAX_ARRAY_SIZE:
        raise ValueError(f"{what} would have {count} numbers (limit {MAX_ARRAY_SIZE})")


def _shape_of(*sizes) -> tuple:
    shape = tuple(_size_arg(v) for v in sizes)
    _numbers(math.prod(shape), "the array")
    return shape


def _eye(n):
    n = _size_arg(n)
    _numbers(n * n, "the identity matrix")
    return np.eye(n)


def _diag(v):
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:
        _numbers(v.size * v.size, "the diagonal matrix")
    return np.diag(v)


def _binom(n, k):
    return float(math.comb(_size_arg(n), _size_arg(k)))


def _poly(a) -> np.ndarray:
    return np.atleast_1d(np.asarray(a, dtype=float))


def _polymul(a, b):
    a, b = _poly(a), _poly(b)
    if a.ndim != 1 or b.ndim != 1:
        raise ValueError("polynomials are vectors of coefficients")
    if a.size * b.size > MAX_WORK:
        raise ValueError(f"polynomials of {a.size} and {b.size} coefficients are too long")
    return np.polymul(a, b)


def _polypow(a, n):
    n = _size_arg(n)
    a = _poly(a)
    if n > 200:
        raise ValueError(f"power {n} is too large (limit 200)")
    if a.ndim != 1:
        raise ValueError("a polynomial is a vector of coefficients")
    if (a.size * n) ** 2 > MAX_WORK:
        raise ValueError(f"a polynomial of {a.size} coefficients to the power {n} is too long")
    out = np.array([1.0])
    for _ in range(n):
        out = np.polymul(out, a)
    return out


def _concat(*arrays):
    parts = [np.atleast_1d(np.asarray(v, dtype=float)) for v in arrays]
    _numbers(sum(p.size for p in parts), "the concatenation")
    return np.concatenate(parts)


def _reshape(a, *shape):
    a = np.asarray(a, dtype=float)
    if not shape:
        raise ValueError("needs the new shape, e.g. reshape(v, 2, 3)")
    new = _shape_of(*shape)
    if math.prod(new) != a.size:
        raise ValueError(f"cannot give {a.size} numbers the shape "
                         f"({', '.join(map(str, new))})")
    return a.reshape(new)


def _extremum(reduce):
    def f(*a):
        if not a:
            raise ValueError("needs at least one argument")
        return reduce(np.array(a, dtype=float)) if len(a) > 1 else reduce(a[0])
    return f


FUNCTIONS = {
    "sqrt": np.sqrt, "sin": np.sin, "cos": np.cos, "tan": np.tan,
    "asin": np.arcsin, "acos": np.arccos, "atan": np.arctan, "atan2": np.arctan2,
    "sinh": np.sinh, "cosh": np.cosh, "tanh": np.tanh,
    "exp": np.exp, "log": np.log, "log10": np.log10, "abs": np.abs,
    "floor": np.floor, "ceil": np.ceil, "round": np.round,
    "min": _extremum(np.min), "max": _extremum(np.max),
    "radians": np.radians, "degrees": np.degrees, "binom": _binom,
    "eye": _eye,
    "zeros": lambda *s: np.zeros(_shape_of(*s)),
    "ones": lambda *s: np.ones(_shape_of(*s)),
    "diag": _diag,
    "transpose": lambda a: np.transpose(np.asarray(a, dtype=float)),
    "reshape": _reshape,                                     # reshape(v, rows[, columns])
    "size": lambda a: float(np.size(a)),                     # number of entries
    # polynomials as coefficient vectors, highest power first (numpy.polyval order)
    "concat": _concat,
    "polymul": _polymul,
    "polyadd": lambda a, b: np.polyadd(_poly(a), _poly(b)),
    "polypow": _polypow,
}

CONSTANTS = {"pi": math.pi, "e": math.e}

_FORBIDDEN = {
    ast.Attribute: "attribute access", ast.Lambda: "lambdas",
    ast.ListComp: "comprehensions", ast.SetComp: "comprehensions",
    ast.DictComp: "comprehensions", ast.GeneratorExp: "comprehensions",
    ast.Compare: "comparisons", ast.BoolOp: "boolean operators", ast.IfExp: "conditionals",
    ast.Dict: "dictionaries", ast.Set: "sets", ast.Starred: "star arguments",
    ast.JoinedStr: "f-strings", ast.NamedExpr: "assignments", ast.Await: "await",
    ast.Yield: "yield", ast.YieldFrom: "yield",
}
_BINOPS = {
    ast.Add: np.add, ast.Sub: np.subtract, ast.Mult: np.multiply, ast.Div: np.true_divide,
    ast.Pow: np.power, ast.Mod: np.mod, ast.MatMult: np.matmul,
}


@functools.lru_cache(maxsize=4096)
def names_in(text: str) -> frozenset[str]:
    """Names an expression refers to (for ordering parameters); empty on syntax errors.
    Remembered per text: a sweep asks about the same few expressions for every variant
    (8 parses per variant were half of a 4096-variant sweep's fixed work)."""
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return frozenset()
    called = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
    return frozenset(n.id for n in ast.walk(tree)
                     if isinstance(n, ast.Name) and id(n) not in called)


def evaluate(text: str, namespace: Mapping[str, Any], what: str = "expression") -> Any:
    """Evaluate ``text`` with names from ``namespace``; raise ``ExpressionError``."""
    src = text.strip()
    shown = " ".join(src.split())          # as written, on one line, for messages
    if len(src) > MAX_EXPRESSION_LENGTH:
        raise ExpressionError(f"{what}: expression is {len(src)} characters long "
                              f"(limit {MAX_EXPRESSION_LENGTH})")
    tree = _screened(src)                  # a sweep evaluates the same texts per variant
    screened = tree is not None
    try:
        if tree is None:
            tree = ast.parse(src, mode="eval")
    except (SyntaxError, ValueError) as exc:
        hint = ""
        if src.count("(") > src.count(")") or src.count("[") > src.count("]"):
            hint = ("; in a YAML {...} or [...] a comma ends the value, so quote expressions "
                    "that contain commas")
        raise ExpressionError(f"{what}: cannot parse expression '{shown}': "
                              f"{getattr(exc, 'msg', exc)}{hint}") from None
    except (RecursionError, MemoryError):
        raise ExpressionError(f"{what}: expression '{shown[:60]}' is nested too deeply") from None
    evaluator = _Evaluator(shown, namespace, what)
    try:
        if not screened:
            evaluator.screen(tree.body)    # raises the message
        evaluator.screened = True          # (visit need not look for forbidden nodes)
        body = tree.body
        if isinstance(body, ast.Name) and body.id in namespace:
            return namespace[body.id]     # a bare name passes any value on (a boolean flag)
        value = evaluator.visit(body)
    except RecursionError:
        raise ExpressionError(f"{what}: expression '{shown[:60]}' is nested too deeply") from None
    return value


@functools.lru_cache(maxsize=4096)
def _screened(src: str):
    """The parsed tree of ``src`` if it parses and passes ``_Evaluator.screen``, else None
    (``evaluate`` then parses or screens it itself, which raises the message).  Trees are
    only read, never changed, so one tree serves every evaluation of the same text."""
    try:
        tree = ast.parse(src, mode="eval")
        _Evaluator(src, {}, "").screen(tree.body)
    except Exception:  # noqa: BLE001 - evaluate's own path says what is wrong
        return None
    return tree


class _Evaluator:
    def __init__(self, src: str, namespace: Mapping[str, Any], what: str):
        self.src = src
        self.ns = namespace
        self.what = what
        self.screened = False           # the whole tree passed ``screen``

    def fail(self, msg: str) -> ExpressionError:
        src = self.src if len(self.src) <= 100 else self.src[:97] + "..."
        return ExpressionError(f"{self.what}: expression '{src}' {msg}")

    def screen(self, tree) -> None:
        """Refuse forbidden constructs anywhere in the tree before evaluating anything, so
        the message names the construct itself (``__import__``, a lambda), not a symptom."""
        nodes = list(ast.walk(tree))
        for node in nodes:
            if isinstance(node, ast.Name) and node.id.startswith("__"):
                raise self.fail(f"uses the name '{node.id}'; names starting with '__' are "
                                "never allowed")
        for node in nodes:
            for kind, label in _FORBIDDEN.items():
                if isinstance(node, kind):
                    raise self.fail(f"uses a forbidden construct ({label})")

    def visit(self, node):
        if not self.screened:
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
            raise self.fail(f"contains a literal {v!r} that is not a number"[:200])
        try:
            return self._check(float(v))
        except OverflowError:
            raise self.fail("contains an integer too large to be a number") from None

    def visit_Name(self, node):
        if node.id in self.ns:
            value = self.ns[node.id]
            if value is None or isinstance(value, (bool, np.bool_, str)):
                kind = "empty (null)" if value is None else f"{value!r}, not a number"
                raise self.fail(f"uses '{node.id}', which is {kind}")
            return value
        if node.id in CONSTANTS:
            return CONSTANTS[node.id]
        if node.id in FUNCTIONS:
            raise self.fail(f"uses the function '{node.id}' without calling it")
        known = ", ".join(sorted(self.ns)) or "(none)"
        close = difflib.get_close_matches(node.id, list(self.ns) + list(CONSTANTS), n=1)
        hint = f"did you mean '{close[0]}'? " if close else ""
        if node.id.lower() in ("yes", "no", "on", "off"):
            hint = "a flag is written true or false (yes, no, on, off are names here); " + hint
        raise self.fail(f"refers to undefined name '{node.id}'; {hint}defined names are: "
                        f"{known}")

    def visit_List(self, node):
        items, total = [], 0
        for e in node.elts:
            items.append(self.visit(e))
            total += int(np.size(items[-1]))
            if total > MAX_ARRAY_SIZE:
                raise self.fail(f"builds a list of more than {MAX_ARRAY_SIZE} numbers")
        try:
            arr = np.array(items, dtype=float)
        except (ValueError, TypeError):
            raise self.fail("builds a list that is not a rectangular array of numbers") from None
        return self._check(arr)

    visit_Tuple = visit_List

    def visit_Subscript(self, node):
        value = np.asarray(self.visit(node.value), dtype=float)
        if value.ndim == 0:
            raise self.fail("indexes a single number; only arrays have entries")
        parts = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
        index = tuple(self._index_part(p) for p in parts)
        if len(index) > value.ndim:
            raise self.fail(f"uses {len(index)} indices on an array of {value.ndim} "
                            f"dimension{'s' if value.ndim > 1 else ''}")
        try:
            picked = value[index]
        except (IndexError, ValueError) as exc:
            raise self.fail(f"cannot be evaluated: {exc}") from None
        return self._check(np.array(picked, dtype=float))

    def _index_part(self, node):
        if isinstance(node, ast.Slice):
            return slice(*(None if p is None else self._whole(p)
                           for p in (node.lower, node.upper, node.step)))
        return self._whole(node)

    def _whole(self, node) -> int:
        v = np.asarray(self.visit(node), dtype=float)
        if v.ndim != 0 or v != math.floor(v) or abs(v) > MAX_ARRAY_SIZE:
            raise self.fail("uses an index that is not a whole number")
        return int(v)

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
            hint = "; write powers as '**'" if isinstance(node.op, ast.BitXor) else ""
            raise self.fail(f"uses a forbidden operator ({type(node.op).__name__}){hint}")
        a = np.asarray(self.visit(node.left), dtype=float)
        b = np.asarray(self.visit(node.right), dtype=float)
        try:
            self._precheck(op, a.shape, b.shape)
            with np.errstate(over="raise", invalid="raise", divide="raise"):
                res = op(a, b)
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
        except (ValueError, TypeError, OverflowError, IndexError, ZeroDivisionError) as exc:
            raise self.fail(f"cannot be evaluated: {name}(): {exc}"[:400]) from None
        return self._check(np.asarray(res, dtype=float) if not isinstance(res, float) else res)

    @staticmethod
    def _precheck(op, sa: tuple, sb: tuple) -> None:
        """Refuse an operation whose result or cost is too large, before doing it."""
        if op is np.matmul:
            if not sa or not sb:
                return                          # numpy refuses scalars itself
            a2 = sa if len(sa) > 1 else (1,) + sa
            b2 = sb if len(sb) > 1 else sb + (1,)
            if a2[-1] != b2[-2]:
                return                          # numpy explains the mismatch itself
            out = np.broadcast_shapes(a2[:-2], b2[:-2]) + (a2[-2], b2[-1])
            size = math.prod(out)
            if size > MAX_ARRAY_SIZE or size * a2[-1] > MAX_WORK:
                raise ValueError(f"the product of {sa} and {sb} arrays is too large")
            return
        size = math.prod(np.broadcast_shapes(sa, sb))
        if size > MAX_ARRAY_SIZE:
            raise ValueError(f"the result would have {size} numbers (limit {MAX_ARRAY_SIZE})")

    def _check(self, value):
        if type(value) is float:        # (most values: no array made)
            if not math.isfinite(value):
                raise self.fail("is not finite")
            return value
        arr = np.asarray(value)
        if arr.size > MAX_ARRAY_SIZE:
            raise self.fail(f"produces {arr.size} numbers (limit {MAX_ARRAY_SIZE})")
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise self.fail("is not finite")
        if arr.ndim == 0:
            return float(arr)
        return arr
