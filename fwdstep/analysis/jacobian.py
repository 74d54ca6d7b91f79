"""Jacobians of a block, derived from its one definition.

A block states its equations once, as kernels (``Block.set_kernels``), as an exact linear
form (``fwdstep.core.linear.LinearForm``) or, for blocks that call a library numba cannot compile
(pinocchio), as its ``output``/``derivative`` methods.  ``BlockJacobian`` differentiates
whichever of these the block has, and never asks the block for a second copy of its
equations.  The methods, tried in this order:

``traced``
    The kernels are traced into an expression graph by ``fwdstep.compiled.scalarize`` (the very graph
    the compiled backend turns into straight-line code), and the graph is differentiated in
    forward mode *symbolically*: ``forward_tangents`` adds, for every node, the nodes of its
    partial derivatives to the same ``Trace`` (product rule, chain rule; a selection
    ``np.where(c, a, b)`` differentiates to ``np.where(c, da, db)``, comparisons and
    ``floor`` to zero).  The derivative nodes are ordinary nodes, so the compiled backend
    can compile them like any stage (issue 28: variational equations); here
    ``GraphProgram`` evaluates them with NumPy, for a batch of points at once.  Exact up to
    round-off.
``traced at fixed time``
    The same, for a kernel whose control flow depends on the time (a ``PiecewiseConstant``'s
    index, a noise sample's number): traced again for each time with t a constant.  Exact.
``linear form``
    A linear block's Jacobian *is* its ``LinearForm`` (the matrices it runs with).  Exact.
``central differences``
    Everything else (kernels the tracer refuses: a pivoted ``np.linalg.solve``, complex
    arithmetic, ``np.searchsorted`` on an input, pinocchio calls): Richardson-extrapolated
    central differences of the block's own ``output``/``derivative``,
    ``(4 D(h/2) - D(h)) / 3`` with ``D(h) = (f(v + h) - f(v - h)) / (2 h)`` and
    ``h = 1e-3 max(1, |v|)``: truncation error O(h^4) (about 1e-12 relative for functions
    whose fifth derivative is of the order of the function) and round-off about
    ``1e-16 |f| / h`` = 1e-13 relative; all perturbed points are one batched call.  A kink
    (saturation limit, dead-zone edge) within h of the point gives an average of the two
    one-sided slopes.  Complex-step differentiation is not used: none of the blocks the
    tracer refuses is complex-safe (two compute with complex numbers internally, two call
    pinocchio, which takes no complex arguments, and the tracer already covers every kernel
    written in real arithmetic).

Layout: a Jacobian is one matrix per point, rows = the outputs (each port vectorised in
C order, declared order) then the derivative, columns = the block's state then its inputs
(vectorised, declared order) then any parameters asked for (``params=("gain", ...)``, the
arrays of ``block.p``: for issue 28's sensitivities).  ``Jacobian.part("y.u", "u.e")`` reads
one block of it.  Entries outside an output's declared feedthrough are zero by contract and
are set to exactly zero.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from fwdstep.compiled import scalarize as sz
from fwdstep.core.linear import linear_form_of

#: a traced kernel plus its derivatives larger than this keeps central differences
MAX_DERIVATIVE_NODES = 400_000
#: exact derivatives cost about (traced operations) x (directions) nodes to build and
#: evaluate in Python; above this product (a robot's dynamics: ~1800 operations x 28
#: directions) the block's own kernels are differenced instead, ~30x faster to set up and
#: within 1e-8 relative (tests/fwdstep/test_jacobian.py, test_linearize.py)
MAX_EXACT_WORK = 20_000
#: relative step of the central differences (see the module docstring), also of the
#: parameter differences of ``fwdstep.analysis.sensitivity``
DIFFERENCE_STEP = 1e-3
#: the offsets (in steps h) of a Richardson central difference's four points
OFFSETS = (1.0, -1.0, 0.5, -0.5)


def richardson(f, h):
    """(4 D(h/2) - D(h)) / 3 from f = values at +h, -h, +h/2, -h/2 (``OFFSETS``)."""
    return (4.0 * (f[2] - f[3]) / h - (f[0] - f[1]) / (2.0 * h)) / 3.0


def moved_block(blk, dp: dict, c: int, amount: float):
    """A copy of ``blk`` with each p array ``name`` moved by amount * dp[name][:, c] (made
    ready for one variant, ``finalize(1)``); ``blk`` is left as it is."""
    return moved_variants(blk, dp, [(c, amount)])


def moved_variants(blk, dp: dict, moves: list):
    """A copy of ``blk`` (one variant, ``blk.p``'s arrays of leading length 1) whose
    variants are ``blk`` moved by each (c, amount) of ``moves``: each p array ``name``
    stacked as [p + amount * dp[name][:, c] for each move] (made ready for len(moves)
    variants, ``finalize``, as ``fwdstep.structure.compiler.stack_blocks`` does for a
    batch); ``blk`` is left as it is."""
    b = copy.copy(blk)
    b.p = SimpleNamespace(**vars(blk.p))
    for n, g in dp.items():
        arr = np.asarray(getattr(blk.p, n), dtype=float)
        setattr(b.p, n, np.concatenate([arr + amount * g[:, c].reshape(arr.shape)
                                        for c, amount in moves], axis=0))
    b.__dict__.pop("_kargs", None)
    b.finalize(len(moves))
    return b


@dataclass
class Jacobian:
    """The Jacobian of one block at B points: ``J`` (B, rows, columns).

    ``rows``: "y.PORT" -> slice (each output, vectorised), "dx" -> slice (the derivative);
    ``columns``: "x" -> slice (the state), "u.PORT" -> slice (each input), "p.NAME" -> slice
    (each parameter asked for).  ``method``: how it was obtained (module docstring)."""
    J: np.ndarray
    rows: dict
    columns: dict
    method: str

    def part(self, row: str, column: str) -> np.ndarray:
        """d row / d column, (B, size of row, size of column)."""
        return self.J[:, self.rows[row], self.columns[column]]


class BlockJacobian:
    """Differentiates one block; built once, evaluated at any number of points.

    ``params``: names of ``block.p`` arrays to differentiate with respect to as well
    (columns "p.NAME", the array's entries in C order without the batch axis)."""

    def __init__(self, block, params: tuple = ()):
        self.block = block
        self.params = tuple(params)
        for name in self.params:
            if not hasattr(block.p, name):
                raise ValueError(f"block '{block.name}' has no run-time parameter '{name}'; "
                                 f"it has: {', '.join(vars(block.p)) or '(none)'}")
        n = block.n_states
        self.rows, r = {}, 0
        for port in block.outputs.values():
            self.rows[f"y.{port.name}"] = slice(r, r + port.size)
            r += port.size
        self.rows["dx"] = slice(r, r + n)
        self.n_rows = r + n
        self.columns, c = {"x": slice(0, n)}, n
        for port in block.inputs.values():
            self.columns[f"u.{port.name}"] = slice(c, c + port.size)
            c += port.size
        for name in self.params:
            size = int(np.prod(np.shape(getattr(block.p, name))[1:], dtype=np.int64))
            self.columns[f"p.{name}"] = slice(c, c + size)
            c += size
        self.n_columns = c
        self.mask = self._feedthrough_mask()
        self._fixed_time: dict = {}
        self.method, self.why = self._choose()

    # ------------------------------------------------------------------ choice of method
    def _choose(self):
        """(method, reason the better methods were not used)."""
        blk = self.block
        k = blk.kernels
        if k is not None and (k.output is not None or k.derivative is not None):
            try:
                self._traced = _Traced(blk, self, None)
                return "traced", ""
            except _TooLarge as exc:
                return "central differences", str(exc)
            except sz.Untraceable as exc:
                why = str(exc)
            if self._time_only(why):
                return "traced at fixed time", why
            return "central differences", why
        form = linear_form_of(blk)
        if form is not None and not self.params:
            self._form = form
            return "linear form", ""
        why = "no kernels (object mode)" if form is None else "parameters of a linear form"
        return "central differences", why

    def _time_only(self, why: str) -> bool:
        """Does tracing succeed with the time fixed (a branch on t only)?"""
        try:
            self._fixed_time[0.0] = _Traced(self.block, self, 0.0)
            return True
        except sz.Untraceable:
            return False

    def _feedthrough_mask(self) -> np.ndarray:
        """(rows, columns): False where an output cannot depend on an input."""
        m = np.ones((self.n_rows, self.n_columns), dtype=bool)
        blk = self.block
        for out in blk.outputs:
            ft = blk.feedthrough(out)
            for inp in blk.inputs:
                if inp not in ft:
                    m[self.rows[f"y.{out}"], self.columns[f"u.{inp}"]] = False
        return m

    # ------------------------------------------------------------------ evaluation
    def at(self, t: float, x, u) -> Jacobian:
        """The Jacobian at time t, state ``x`` (B, n_states) and inputs ``u`` (a tuple of
        (B or 1, *shape) arrays in declared order)."""
        blk = self.block
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = tuple(np.asarray(a, dtype=float) for a in u)
        B = max([x.shape[0]] + [a.shape[0] for a in u])
        if self.method == "traced":
            J = self._traced.evaluate(t, x, u, B)
        elif self.method == "traced at fixed time":
            key = float(t)
            tr = self._fixed_time.get(key)
            if tr is None:
                if len(self._fixed_time) > 64:
                    self._fixed_time.clear()
                tr = self._fixed_time[key] = _Traced(blk, self, key)
            J = tr.evaluate(t, x, u, B)
        elif self.method == "linear form":
            J = self._linear(B)
        else:
            J = _differences(blk, self, t, x, u, B)
        J[:, ~self.mask] = 0.0
        return Jacobian(J, self.rows, self.columns, self.method)

    def _linear(self, B: int) -> np.ndarray:
        f, blk = self._form, self.block
        J = np.zeros((B, self.n_rows, self.n_columns))
        ins = list(blk.inputs)
        outs = list(blk.outputs)
        dx, xs = self.rows["dx"], self.columns["x"]
        if blk.n_states:
            J[:, dx, xs] = f.A
        for j, Bj in f.B.items():
            J[:, dx, self.columns[f"u.{ins[j]}"]] = Bj
        for k, Ck in enumerate(f.C):
            if blk.n_states:
                J[:, self.rows[f"y.{outs[k]}"], xs] = Ck
        for (k, j), Dkj in f.D.items():
            J[:, self.rows[f"y.{outs[k]}"], self.columns[f"u.{ins[j]}"]] = Dkj
        return J


# ---------------------------------------------------------------------- the traced method
class _TooLarge(sz.Untraceable):
    """Traceable, but exact derivatives would cost more than differences (MAX_EXACT_WORK)."""


class _Traced:
    """A block's kernels traced on leaves (t, x, u, the asked parameters) and their
    derivative nodes, with the program evaluating them."""

    def __init__(self, blk, owner: BlockJacobian, t_value):
        k = blk.kernels
        tr = self.trace = sz.Trace(max_nodes=MAX_DERIVATIVE_NODES)
        rb = sz.Rebinder(tr)
        n = blk.n_states
        x = sz.sym_array(tr, (1, n), lambda i: (f"x{i[1]}", False))
        us = []
        for j, port in enumerate(blk.inputs.values()):
            us.append(sz.sym_array(tr, (1,) + port.shape,
                                   lambda i, j=j, s=port.shape: (
                                       f"u{j}_{_flat(i[1:], s)}", False)))
        t = tr.leaf("t", False) if t_value is None else tr.const(t_value)
        wanted = set(owner.params)
        args = []
        for name in k.params:
            arr = np.asarray(getattr(blk.p, name), dtype=float)
            if arr.shape[0] != 1:
                raise sz.Untraceable("a batch of parameter values")
            if name in wanted:
                a = sz.sym_array(tr, (1,) + arr.shape[1:], lambda i, name=name, s=arr.shape[1:]:
                                 (f"p_{name}_{_flat(i[1:], s)}", True))
                for idx in np.ndindex(*arr.shape[1:]):
                    a[(0,) + idx].values = np.array([arr[(0,) + idx]])
            else:
                a = np.empty((1,) + arr.shape[1:], dtype=object)
                for idx in np.ndindex(*arr.shape[1:]):
                    a[(0,) + idx] = tr.const(arr[(0,) + idx])
                a = a.view(sz.SymArray)
            args.append(a)
        args += list(k.static)
        ins = [tuple(us)] if k.tuple_inputs else us
        roots = []
        if k.output is not None and blk.outputs:
            r = sz.run_traced(rb, k.output, t, x, *ins, *args)
            if k.packed:
                total = sum(p.size for p in blk.outputs.values())
                roots += list(sz.as_nodes(tr, r, (1, total)).reshape(-1))
            else:
                if len(r) != len(blk.outputs):
                    raise sz.Untraceable(f"{len(r)} outputs where {len(blk.outputs)} declared")
                for y, port in zip(r, blk.outputs.values()):
                    roots += list(sz.as_nodes(tr, y, (1,) + port.shape).reshape(-1))
        elif blk.outputs:
            raise sz.Untraceable("outputs without an output kernel")
        if n:
            if k.derivative is None:
                raise sz.Untraceable("states without a derivative kernel")
            dx = sz.run_traced(rb, k.derivative, t, x, *ins, *args)
            roots += list(sz.as_nodes(tr, dx, (1, n)).reshape(-1))
        wrt = list(x.reshape(-1))
        for a in us:
            wrt += list(np.asarray(a).reshape(-1))
        for name in owner.params:
            j = k.params.index(name) if name in k.params else None
            if j is None:
                raise sz.Untraceable(f"parameter '{name}' is not an argument of the kernels")
            wrt += list(np.asarray(args[j]).reshape(-1))
        work = len(tr.nodes) * len(wrt)
        if work > MAX_EXACT_WORK:
            raise _TooLarge(f"{len(tr.nodes)} traced operations x {len(wrt)} directions: "
                            "differences of the kernels are faster than exact derivatives")
        tangents = forward_tangents(tr, roots, wrt)
        entries = [(i, c, node) for i, d in enumerate(tangents) for c, node in d.items()]
        self.rows = np.array([e[0] for e in entries], dtype=np.intp)
        self.cols = np.array([e[1] for e in entries], dtype=np.intp)
        self.program = GraphProgram(tr, [e[2] for e in entries])
        self.shape = (owner.n_rows, owner.n_columns)
        self.n_states = n
        self.inputs = [(j, port.shape) for j, port in enumerate(blk.inputs.values())]

    def evaluate(self, t, x, u, B) -> np.ndarray:
        values = {"t": np.full(1, float(t))}
        for i in range(self.n_states):
            values[f"x{i}"] = x[:, i]
        for j, shape in self.inputs:
            flat = u[j].reshape(u[j].shape[0], -1)
            for c in range(flat.shape[1]):
                values[f"u{j}_{c}"] = flat[:, c]
        J = np.zeros((B,) + self.shape)
        if not len(self.rows):
            return J
        if B == 1:          # one point: NumPy scalars, not 1-element arrays (5x faster)
            values = {k: float(v[0]) for k, v in values.items()}
            J[0, self.rows, self.cols] = np.array(self.program.scalar(values), dtype=float)
            return J
        vals = self.program(values)
        J[:, self.rows, self.cols] = np.column_stack([np.broadcast_to(v, (B,)) for v in vals])
        return J

    @property
    def constant(self) -> bool:
        """True when the derivatives read no time, state or input (a gain, a sum)."""
        return not any(name == "t" or name[0] in "xu"
                       for name, _ in self.program.leaves.values())


def _flat(idx: tuple, shape: tuple) -> int:
    return int(np.ravel_multi_index(idx, shape)) if shape else 0


# ---------------------------------------------------------------------- forward mode
def forward_tangents(trace: sz.Trace, roots: list, wrt: list) -> list:
    """The partial derivatives of ``roots`` (nodes of ``trace``) with respect to the leaves
    ``wrt``, as nodes of the same trace: one dict per root, column k -> node d root/d wrt[k]
    (missing = identically zero).  Forward mode, node by node in creation order (a
    topological order); sparse: a node carries only the columns it depends on."""
    one = trace.const(1.0)
    return directional_tangents(trace, roots, {leaf.n: {k: one} for k, leaf in enumerate(wrt)
                                               if isinstance(leaf, sz.Sym)})


def directional_tangents(trace: sz.Trace, roots: list, seeds: dict) -> list:
    """The derivatives of ``roots`` along directions, as nodes of ``trace``: ``seeds`` maps
    a leaf's node number to its tangent {direction: node} (a leaf not in it: zero); the
    result is one dict per root, direction -> node (missing = identically zero).  With unit
    seeds (``forward_tangents``) the directions are the leaves; with seeds that are nodes
    themselves (the sensitivities S of the state, dp/dtheta of the parameters) the roots'
    tangents are J S + B: the variational equations
    (``fwdstep.analysis.compiled_sensitivity``)."""
    tangent: dict = {}

    def of(s):
        if not isinstance(s, sz.Sym):
            return {}
        if s.op == "leaf":
            return seeds.get(s.n, {})
        if s.op == "const":
            return {}
        return tangent[s.n]

    for n in sorted(trace.needed(roots)):
        s = trace.nodes[n]
        tangent[n] = _rule(trace, s, [of(a) for a in s.args])
    return [of(r) for r in roots]


def _scale(trace, d: dict, c) -> dict:
    return {k: trace.binary("*", v, c) for k, v in d.items()}


def _combine(trace, a: dict, b: dict, op: str = "+") -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = trace.binary(op, out[k], v) if k in out else (
            v if op == "+" else trace.unary("-", v))
    return out


def _rule(t: sz.Trace, s: sz.Sym, d: list) -> dict:
    """The tangent of node s from its arguments' tangents ``d``."""
    op, a = s.op, s.args
    if op in sz._CONDITIONS or op == "floor":
        return {}
    if op == "?":
        da, db = d[1], d[2]
        zero = t.const(0.0)
        return {k: t.select(a[0], da.get(k, zero), db.get(k, zero))
                for k in set(da) | set(db)}
    if not any(d):
        return {}
    if op == "+":
        return _combine(t, d[0], d[1])
    if op == "-":
        if len(a) == 1:
            return {k: t.unary("-", v) for k, v in d[0].items()}
        return _combine(t, d[0], d[1], "-")
    if op == "*":
        return _combine(t, _scale(t, d[0], a[1]), _scale(t, d[1], a[0]))
    if op == "/":
        # (da - (a/b) db) / b
        num = _combine(t, d[0], _scale(t, d[1], s), "-")
        return {k: t.binary("/", v, a[1]) for k, v in num.items()}
    if op == "**":
        base, expo = a
        c = t.value(expo)
        if c is not None and not d[1]:
            factor = t.binary("*", c, t.binary("**", base, c - 1.0)) if c != 2.0 else \
                t.binary("*", 2.0, base)
            return _scale(t, d[0], factor)
        # s = base**expo: ds = s (dexpo log(base) + expo dbase / base)
        inner = _combine(t, _scale(t, d[1], t.unary("log", base)),
                         _scale(t, d[0], t.binary("/", expo, base)))
        return _scale(t, inner, s)
    if op == "atan2":
        y, x = a
        den = t.binary("+", t.binary("*", y, y), t.binary("*", x, x))
        num = _combine(t, _scale(t, d[0], x), _scale(t, d[1], y), "-")
        return {k: t.binary("/", v, den) for k, v in num.items()}
    x = a[0]
    if op == "abs":
        zero = t.const(0.0)
        neg = t.binary("<", x, zero)
        return {k: t.select(neg, t.unary("-", v), v) for k, v in d[0].items()}
    factor = _UNARY_DERIVATIVE[op](t, x, s)
    return _scale(t, d[0], factor)


def _one_minus_square(t, v):
    return t.binary("-", 1.0, t.binary("*", v, v))


_UNARY_DERIVATIVE = {
    "sin": lambda t, x, s: t.unary("cos", x),
    "cos": lambda t, x, s: t.unary("-", t.unary("sin", x)),
    "tan": lambda t, x, s: t.binary("+", 1.0, t.binary("*", s, s)),
    "exp": lambda t, x, s: s,
    "log": lambda t, x, s: t.binary("/", 1.0, x),
    "sqrt": lambda t, x, s: t.binary("/", 0.5, s),
    "tanh": lambda t, x, s: _one_minus_square(t, s),
    "sinh": lambda t, x, s: t.unary("cosh", x),
    "cosh": lambda t, x, s: t.unary("sinh", x),
    "atan": lambda t, x, s: t.binary("/", 1.0, t.binary("+", 1.0, t.binary("*", x, x))),
    "asin": lambda t, x, s: t.binary("/", 1.0, t.unary("sqrt", _one_minus_square(t, x))),
    "acos": lambda t, x, s: t.binary("/", -1.0, t.unary("sqrt", _one_minus_square(t, x))),
}


class GraphProgram:
    """Evaluates nodes of a trace with NumPy on arrays of leaf values (one entry per point):
    the operations the roots need, once each, in creation order."""

    def __init__(self, trace: sz.Trace, roots: list):
        self.roots = [r.n for r in roots]
        needed = sorted(trace.needed(roots))
        self.consts, self.leaves = {}, {}
        for r in roots:
            self._note(trace, r)
        ops = []
        for n in needed:
            s = trace.nodes[n]
            for a in s.args:
                self._note(trace, a)
            ops.append((n, s.op, tuple(a.n for a in s.args)))
        self.ops = ops

    def _note(self, trace, s):
        if s.op == "const":
            self.consts[s.n] = np.float64(trace.value(s))
        elif s.op == "leaf":
            self.leaves[s.n] = (s.value, s.values)

    def scalar(self, values: dict) -> list:
        """The roots' values at one point, ``values`` numbers: straight-line Python on
        floats (generated once; ``math`` functions), 20-50x faster than NumPy on
        1-element arrays.  Where Python raises on what NumPy turns into inf/NaN (a division
        by zero, log of a negative number, a negative base to a fractional power), the
        NumPy evaluation gives the answer."""
        fn = self.__dict__.get("_scalar_fn")
        if fn is None:
            fn = self._scalar_fn = self._generate()
        try:
            return fn(values)
        except (ArithmeticError, ValueError, TypeError):
            return self(values, scalar=True)

    def _generate(self):
        import math
        py_binary = {"+": "+", "-": "-", "*": "*", "/": "/", "<": "<", "<=": "<=", ">": ">",
                     ">=": ">=", "==": "==", "!=": "!="}
        lines = ["def scalar_program(values):"]
        for n, (name, pv) in self.leaves.items():
            default = (float(np.reshape(pv, -1)[0]) if pv is not None and np.size(pv) == 1
                       else None)
            lines.append(f"    v{n} = values.get({name!r}, {default!r})")
        for n, value in self.consts.items():
            lines.append(f"    v{n} = {float(value)!r}")
        for n, op, a in self.ops:
            r = [f"v{k}" for k in a]
            if op == "?":
                expr = f"({r[1]} if {r[0]} else {r[2]})"
            elif op == "!":
                expr = f"(not {r[0]})"
            elif op == "&":
                expr = f"({r[0]} and {r[1]})"
            elif op == "|":
                expr = f"({r[0]} or {r[1]})"
            elif op == "-" and len(a) == 1:
                expr = f"(-{r[0]})"
            elif op == "**":
                expr = f"pow_({r[0]}, {r[1]})"
            elif op == "atan2":
                expr = f"atan2_({r[0]}, {r[1]})"
            elif op in py_binary:
                expr = f"({r[0]} {py_binary[op]} {r[1]})"
            elif op == "abs":
                expr = f"abs({r[0]})"
            else:
                expr = f"math.{op}({r[0]})"
            lines.append(f"    v{n} = {expr}")
        lines.append("    return [" + ", ".join(f"v{n}" for n in self.roots) + "]")
        ns = {"math": math, "pow_": math.pow, "atan2_": math.atan2}
        exec(compile("\n".join(lines), "<fwdstep derivative program>", "exec"), ns)  # noqa: S102
        return ns["scalar_program"]

    def __call__(self, values: dict, scalar: bool = False) -> list:
        """The roots' values; ``scalar``: the values are numbers, not arrays (leaves with
        a stored one-point value then use that number)."""
        v = dict(self.consts)
        for n, (name, pv) in self.leaves.items():
            got = values.get(name)
            if got is None:
                if pv is None:
                    raise KeyError(f"no value for leaf {name}")
                got = float(np.reshape(pv, -1)[0]) if scalar and np.size(pv) == 1 else pv
            v[n] = got
        with np.errstate(all="ignore"):
            for n, op, a in self.ops:
                if op == "?":
                    v[n] = np.where(v[a[0]], v[a[1]], v[a[2]])
                elif op == "!":
                    v[n] = np.logical_not(v[a[0]])
                elif op in sz._NUMPY_LOGIC:
                    v[n] = sz._NUMPY_LOGIC[op](v[a[0]], v[a[1]])
                elif len(a) == 1:
                    v[n] = -v[a[0]] if op == "-" else sz._NUMPY_UNARY[op](v[a[0]])
                else:
                    v[n] = sz._NUMPY_BINARY[op](v[a[0]], v[a[1]])
        return [v[n] for n in self.roots]


# ---------------------------------------------------------------------- central differences
def _call(blk, t, x, u, B) -> np.ndarray:
    """Outputs (vectorised) and derivative of the block, one row per point: (B, rows)."""
    parts = []
    if blk.outputs:
        ys = blk.output(t, x, u)
        for y, port in zip(ys, blk.outputs.values()):
            y = np.broadcast_to(np.asarray(y, dtype=float), (B,) + port.shape)
            parts.append(y.reshape(B, -1))
    if blk.n_states:
        dx = np.broadcast_to(np.asarray(blk.derivative(t, x, u), dtype=float),
                             (B, blk.n_states))
        parts.append(dx)
    return np.concatenate(parts, axis=1) if parts else np.zeros((B, 0))


def _differences(blk, owner: BlockJacobian, t, x, u, B) -> np.ndarray:
    """Richardson-extrapolated central differences (module docstring), all state and input
    columns of all B points in one batched call per step size."""
    n = blk.n_states
    sizes = [p.size for p in blk.inputs.values()]
    shapes = [p.shape for p in blk.inputs.values()]
    base = np.concatenate([np.broadcast_to(x, (B, n))] +
                          [np.broadcast_to(a, (B,) + s).reshape(B, -1)
                           for a, s in zip(u, shapes)], axis=1)
    C = base.shape[1]
    J = np.zeros((B, owner.n_rows, owner.n_columns))
    if C:
        h = DIFFERENCE_STEP * np.maximum(1.0, np.abs(base))          # (B, C)
        offsets = np.array([1.0, -1.0, 0.5, -0.5])
        # points: (4, B, C, C) = base + offset h e_c, then flattened to one batch
        pts = np.broadcast_to(base[None, :, None, :], (4, B, C, C)).copy()
        cols = np.arange(C)
        pts[:, :, cols, cols] += offsets[:, None, None] * h[None]
        flat = pts.reshape(-1, C)
        xs = flat[:, :n]
        us, c = [], n
        for size, shape in zip(sizes, shapes):
            us.append(flat[:, c:c + size].reshape((-1,) + shape))
            c += size
        with np.errstate(all="ignore"):
            f = _call(blk, t, xs, tuple(us), flat.shape[0]).reshape(4, B, C, -1)
        d1 = (f[0] - f[1]) / (2.0 * h[..., None])
        d2 = (f[2] - f[3]) / (h[..., None])
        J[:, :, :C] = np.swapaxes((4.0 * d2 - d1) / 3.0, 1, 2)
    for name in owner.params:
        J[:, :, owner.columns[f"p.{name}"]] = _parameter_differences(blk, name, t, x, u, B)
    return J


def _parameter_differences(blk, name, t, x, u, B) -> np.ndarray:
    arr = np.asarray(getattr(blk.p, name), dtype=float)
    flat = arr.reshape(arr.shape[0], -1)
    out = []
    for c in range(flat.shape[1]):
        h = DIFFERENCE_STEP * max(1.0, float(np.max(np.abs(flat[:, c]))))
        f = []
        for step in (h, -h, 0.5 * h, -0.5 * h):
            probe = copy.copy(blk)
            probe.p = SimpleNamespace(**vars(blk.p))
            moved = flat.copy()
            moved[:, c] += step
            setattr(probe.p, name, moved.reshape(arr.shape))
            probe.__dict__.pop("_kargs", None)
            probe.finalize(arr.shape[0])
            with np.errstate(all="ignore"):
                f.append(_call(probe, t, x, u, B))
        d1 = (f[0] - f[1]) / (2 * h)
        d2 = (f[2] - f[3]) / h
        out.append((4 * d2 - d1) / 3)
    return np.stack(out, axis=2) if out else np.zeros((B, 0, 0))


def block_jacobians(blocks, params: dict | None = None) -> dict:
    """name -> BlockJacobian for each block (``params``: block name -> parameter names)."""
    params = params or {}
    return {b.name: BlockJacobian(b, params.get(b.name, ())) for b in blocks}


__all__ = ["BlockJacobian", "Jacobian", "forward_tangents", "directional_tangents",
           "GraphProgram", "block_jacobians", "DIFFERENCE_STEP", "OFFSETS", "richardson",
           "moved_block", "moved_variants"]
